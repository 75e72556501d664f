"""Elementwise physics written once, run on numpy arrays (CPU) or torch tensors (any device).

A small batch (16 cart-poles) needs microseconds of arithmetic, but every torch call costs
about 1.5 us of dispatch, and an RK4 step is about 150 calls; numpy's call costs about
0.6 us. So the dynamics and rewards that have many small ops take an ``ops`` namespace and
use only operators and the functions below; ``for_tensor`` picks numpy for plain CPU float
tensors (sharing their memory, no copy) and torch otherwise (CUDA, autograd, other dtypes).

The transcendental functions of the numpy namespace go through torch's own kernels: numpy's
cos and sin differ from torch's in the last bit for some inputs, and the two paths must give
the same bits (the arithmetic operators are IEEE-exact in both).
"""
from __future__ import annotations

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

    @staticmethod
    def stack(arrays, axis: int):
        return torch.stack(arrays, dim=axis)

    @staticmethod
    def concatenate(arrays, axis: int):
        return torch.cat(arrays, dim=axis)

    @staticmethod
    def clip(x, low, high):
        return x.clamp(low, high)


class NumpyOps:
    """numpy arithmetic with torch's transcendental kernels (see the module docstring)."""

    cos, sin, exp, cosh, tanh = (_through_torch(f) for f in (torch.cos, torch.sin, torch.exp, torch.cosh, torch.tanh))
    where, zeros_like, ones_like, abs, clip = np.where, np.zeros_like, np.ones_like, np.abs, np.clip

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


def for_tensor(tensor: torch.Tensor):
    """NumpyOps for a CPU float32/float64 tensor outside autograd, else TorchOps."""
    if tensor.device.type == "cpu" and tensor.dtype in (torch.float32, torch.float64) and not tensor.requires_grad:
        return NumpyOps
    return TorchOps


def to_ops(ops, tensor: torch.Tensor):
    """`tensor` as the namespace's array type (numpy: a view of the same memory)."""
    return tensor.numpy() if ops is NumpyOps else tensor


def to_tensor(value) -> torch.Tensor:
    """A result back as a tensor (numpy: a tensor over the array's memory, no copy)."""
    return torch.from_numpy(value) if isinstance(value, np.ndarray) else value
