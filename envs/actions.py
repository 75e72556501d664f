"""What a caller hands the driver: actions, checked against the action space, and the other tensors
of its calls (reset masks, level ids), cut from autograd where they enter.

    actions = checked(given, env.spec, env.device)   # int64 [W, A] or float32 [W, A, action_dim], the env's own copy
    mask = world_mask(given_mask, num_worlds, device)  # bool [W]

Each raises TypeError / ValueError naming the argument, the expected and the given, before the
driver changes anything. (Which actions the action mask allows is envs/masking.py's.)
"""
from __future__ import annotations

import numpy as np
import torch

from marl_render.util.validation import FLOAT_DTYPES, as_tensor, describe

from .spec import EnvSpec


def from_user(name: str, value):
    """A tensor the user handed in, cut from its autograd graph (a policy output that was not
    detached would otherwise flow into the state, and through torch.where survive every
    reset); nested, sparse and meta tensors, which have no plain data to read, are a TypeError."""
    if not isinstance(value, torch.Tensor):
        return value
    if value.is_nested or value.layout != torch.strided or value.device.type == "meta":
        kind = "a nested tensor" if value.is_nested else f"layout {value.layout}"
        raise TypeError(f"{name} must be a dense tensor with data, got {kind} on {value.device}")
    return value.detach()


def world_mask(mask, num_worlds: int, device: torch.device) -> torch.Tensor:
    """A reset's mask of worlds: bool [num_worlds] on `device`."""
    mask = as_tensor("mask", from_user("mask", mask), dtype_kind="bool")
    if tuple(mask.shape) != (num_worlds,):
        raise ValueError(f"mask must be a bool tensor of shape [{num_worlds}] (num_worlds), "
                         f"got shape {list(mask.shape)}")
    return mask.to(device)


@torch.no_grad()
def checked(actions, spec: EnvSpec, device: torch.device) -> torch.Tensor:
    """Validated actions on `device` (long [W, A] or float32 [W, A, action_dim]) of an env described by
    `spec`; raises TypeError / ValueError naming `actions`, the expected and the given."""
    W, A, action = spec.num_worlds, spec.num_agents, spec.action
    if not isinstance(actions, (torch.Tensor, np.ndarray, list, tuple)):
        raise TypeError(f"actions must be a torch.Tensor (or array-like), got {describe(actions)}")
    actions = from_user("actions", actions)
    if action.continuous:
        (action_dim,) = action.shape
        want = f"a float tensor of shape [{W}, {A}, {action_dim}] (worlds, agents, action_dim) in [-1, 1]"
        if isinstance(actions, (torch.Tensor, np.ndarray)) and not (
                torch.is_tensor(actions) and actions.is_floating_point()
                or isinstance(actions, np.ndarray) and np.issubdtype(actions.dtype, np.floating)):
            raise TypeError(f"actions must be {want}, got {describe(actions)}")
        tensor = as_tensor("actions", actions, dtype_kind="float")
        tensor = tensor if tensor.dtype in FLOAT_DTYPES else tensor.to(torch.float32)  # float8: no isfinite
        if tuple(tensor.shape) != (W, A, action_dim):
            raise ValueError(f"actions must be {want}, got shape {list(tensor.shape)}")
        if not bool(torch.isfinite(tensor).all()):
            raise ValueError(f"actions must be {want}, got non-finite values (NaN/Inf)")
        if bool((tensor.abs() > 1).any()):
            raise ValueError(f"actions must be {want}, got values in "
                             f"[{tensor.min().item():.4g}, {tensor.max().item():.4g}] (clamp them first)")
        return tensor.to(device=device, dtype=torch.float32, copy=True)  # the env's own: see below
    want = f"an integer tensor of shape [{W}, {A}] (worlds, agents) with values in [0, {action.num_actions})"
    try:
        tensor = as_tensor("actions", actions, dtype_kind="int")
    except TypeError as exc:
        raise TypeError(f"actions must be {want}, got {describe(actions)}") from exc
    if tuple(tensor.shape) != (W, A):
        raise ValueError(f"actions must be {want}, got shape {list(tensor.shape)}")
    checked = tensor.to(torch.float64) if tensor.dtype in (torch.uint16, torch.uint32, torch.uint64) else tensor
    if checked.numel():
        low, high = (value.item() for value in torch.aminmax(checked))
        if low < 0 or high >= action.num_actions:
            raise ValueError(f"actions must be {want}, got values in [{low}, {high}]")
    # A copy even where no conversion is needed: a task may keep actions in its state, and the
    # caller's tensor (a rollout buffer written in place) must not change the env afterwards.
    return tensor.to(device=device, dtype=torch.int64, copy=True)
