"""Elementwise physics written once, run on numpy arrays (CPU) or torch tensors (any device).

A small batch (16 cart-poles) needs microseconds of arithmetic, but every torch call costs
1-2.5 us of dispatch on this project's machine, and an RK4 step with its reward is about 150
calls; a numpy call costs 0.3-1 us. So the dynamics and rewards that have many small ops take an ``ops`` namespace and
use only operators and the functions below; ``for_tensors`` picks numpy for plain CPU float
tensors (sharing their memory, no copy) and torch otherwise (CUDA, autograd, other dtypes).

The transcendental functions of the numpy namespace go through torch's own kernels: numpy's
cos and sin differ from torch's in the last bit for some inputs, and the two paths must give
the same bits (the arithmetic operators are IEEE-exact in both).
"""
from __future__ import annotations

import contextlib

import numpy as np
import torch


def _through_torch(function):
    def apply(array: np.ndarray) -> np.ndarray:
        return function(torch.from_numpy(array)).numpy()
    apply.__name__ = function.__name__
    return apply


class TorchOps:
    """The torch namespace (the reference: any device, autograd, every float dtype)."""

    cos, sin, exp, cosh, tanh = torch.cos, torch.sin, torch.exp, torch.cosh, torch.tanh
    where, zeros_like, ones_like, abs = torch.where, torch.zeros_like, torch.ones_like, torch.abs
    isfinite, maximum, minimum, copysign = torch.isfinite, torch.maximum, torch.minimum, torch.copysign
    reciprocal = torch.reciprocal

    @staticmethod
    def norm(x, keepdim: bool = False):
        """Euclidean norm over the last axis."""
        return torch.linalg.vector_norm(x, dim=-1, keepdim=keepdim)

    @staticmethod
    def clamp_min(x, low):
        return x.clamp_min(low)

    @staticmethod
    def clamp_max(x, high):
        return x.clamp(max=high)

    @staticmethod
    def max_last(x):
        """(largest value, index of its first occurrence) over the last axis."""
        values, indices = x.max(dim=-1)
        return values, indices

    @staticmethod
    def pick(x, index, axis: int):
        """x's entries at `index` along `axis` (index has x's shape without that axis and the last)."""
        expanded = index.unsqueeze(axis).unsqueeze(-1).expand(*index.shape[:axis], 1, *index.shape[axis:], x.shape[-1])
        return torch.gather(x, axis, expanded).squeeze(axis)

    @staticmethod
    def swap_last(x):
        return x.transpose(-1, -2)

    @staticmethod
    def min_last(x):
        return x.min(dim=-1).values

    @staticmethod
    def sum_xy(x):
        """Sum over a last axis of 2 (x, y)."""
        return x.sum(-1)

    @staticmethod
    def cast_like(x, like):
        return x.to(like.dtype)

    @staticmethod
    def stack(arrays, axis: int):
        return torch.stack(arrays, dim=axis)

    @staticmethod
    def concatenate(arrays, axis: int):
        return torch.cat(arrays, dim=axis)

    @staticmethod
    def clip(x, low, high):
        return x.clamp(low, high)

    @staticmethod
    def quiet():
        return contextlib.nullcontext()


class NumpyOps:
    """numpy arithmetic with torch's transcendental kernels (see the module docstring)."""

    cos, sin, exp, cosh, tanh = (_through_torch(f) for f in (torch.cos, torch.sin, torch.exp, torch.cosh, torch.tanh))
    where, zeros_like, ones_like, abs, clip = np.where, np.zeros_like, np.ones_like, np.abs, np.clip
    isfinite, maximum, minimum, copysign = np.isfinite, np.maximum, np.minimum, np.copysign
    reciprocal, clamp_min, clamp_max = np.reciprocal, np.maximum, np.minimum

    @staticmethod
    def quiet():
        """IEEE results without numpy's warnings (torch gives inf and NaN silently too)."""
        return np.errstate(all="ignore")

    @staticmethod
    def norm(x, keepdim: bool = False):
        # torch's float32 norm accumulates differently from sqrt(sum(x * x)): use its kernel
        return torch.linalg.vector_norm(torch.from_numpy(x), dim=-1, keepdim=keepdim).numpy()

    @staticmethod
    def max_last(x):
        return x.max(axis=-1), x.argmax(axis=-1)

    @staticmethod
    def pick(x, index, axis: int):
        return np.take_along_axis(x, np.expand_dims(index, (axis, -1)), axis=axis).squeeze(axis)

    @staticmethod
    def swap_last(x):
        return np.swapaxes(x, -1, -2)

    @staticmethod
    def min_last(x):
        return x.min(axis=-1)

    @staticmethod
    def sum_xy(x):
        # numpy's reduction machinery costs microseconds on small strided arrays; x + y is one add
        return x[..., 0] + x[..., 1]

    @staticmethod
    def cast_like(x, like):
        return x.astype(like.dtype)

    @staticmethod
    def stack(arrays, axis: int):
        if axis != -1:
            return np.stack(arrays, axis=axis)
        # np.stack is Python code (about 3 us); filling an empty array costs a third of that.
        out = np.empty(arrays[0].shape + (len(arrays),), dtype=np.result_type(*arrays))
        for index, array in enumerate(arrays):
            out[..., index] = array
        return out

    @staticmethod
    def concatenate(arrays, axis: int):
        return np.concatenate(arrays, axis=axis)


def for_tensors(*tensors: torch.Tensor):
    """NumpyOps when every tensor is on the CPU and outside autograd, and every float one is
    float32 or float64 (bool and integer tensors go along as they are); else TorchOps."""
    for tensor in tensors:
        if tensor.device.type != "cpu" or tensor.requires_grad or (
                tensor.is_floating_point() and tensor.dtype not in (torch.float32, torch.float64)):
            return TorchOps
    return NumpyOps


def to_ops(ops, tensor: torch.Tensor):
    """`tensor` as the namespace's array type (numpy: a view of the same memory)."""
    return tensor.numpy() if ops is NumpyOps else tensor


def to_tensor(value) -> torch.Tensor:
    """A result back as a tensor (numpy: a tensor over the array's memory, no copy)."""
    return torch.from_numpy(value) if isinstance(value, np.ndarray) else value
