"""Explicit env state: everything a later step depends on, as named tensors.

An environment keeps its simulation in one frozen dataclass of ``[W, ...]`` tensors (``env.sim``
hands out a copy; for spread: body positions, velocities, yaws and landmarks). Reset and step replace it with a
new one and never write into it, as gymnax does with its state. With the core's step counters,
alive mask and random generator it is the whole state of the env:

    state = env.get_state()     # {name: tensor} copies: the fields of env.sim, "step_count",
                                # "alive" and "rng" (the generator's state, uint8 on the CPU)
    state["pos"][0, 1] = torch.tensor([0.5, 0.0])
    env.set_state(state)        # validated against the current state, then restored exactly
"""
from __future__ import annotations

import dataclasses

import torch

from marl_render.util.validation import describe


def fields(sim) -> dict:
    """{name: tensor} of a simulation-state dataclass, in field order (no copies)."""
    return {f.name: getattr(sim, f.name) for f in dataclasses.fields(sim)}


def select_worlds(mask: torch.Tensor, new, old):
    """The state with `new`'s worlds where mask [W] (bool) is True and `old`'s elsewhere."""
    def pick(a, b):
        return torch.where(mask.reshape(-1, *(1,) * (a.ndim - 1)), a, b)
    return type(old)(**{name: pick(value, getattr(old, name)) for name, value in fields(new).items()})


def checked(state, template: dict) -> dict:
    """Copies of `state`'s tensors after checking them against `template` (the env's current state):
    the same keys, and per key a tensor of the same shape, dtype and device (check_bounds then checks
    the values). Raises TypeError / ValueError naming the key, the expected and the given."""
    if not isinstance(state, dict):
        raise TypeError(f"state must be a dict of tensors as returned by get_state(), got {describe(state)}")
    missing, unknown = sorted(set(template) - set(state)), sorted(set(state) - set(template))
    if missing or unknown:
        raise ValueError(f"state must have the keys {sorted(template)}, got missing {missing} and unknown {unknown}")
    copies = {}
    for key, want in template.items():
        given = state[key]
        if not isinstance(given, torch.Tensor):
            raise TypeError(f"state[{key!r}] must be a torch.Tensor, got {describe(given)}")
        for what in ("shape", "dtype", "device"):
            if getattr(given, what) != getattr(want, what):
                raise ValueError(f"state[{key!r}] must have {what} {_show(getattr(want, what))}, "
                                 f"got {_show(getattr(given, what))}")
        copies[key] = given.detach().clone()
    return copies


def check_bounds(state: dict, bounds: dict, label: str = "state[{key!r}]") -> None:
    """Raise ValueError naming the key if a tensor of `state` is not finite (floating ones) or leaves
    its (low, high) in `bounds` ({key: (low, high)}; low / high a number, or one number per index of
    the last axis, e.g. the arena's (hx, hy) for positions). `label` words the key in the message."""
    for key, value in state.items():
        if value.is_floating_point() and value.numel() and not bool(torch.isfinite(value).all()):
            raise ValueError(f"{label.format(key=key)} must be finite, got NaN or Inf values")
    for key, (low, high) in bounds.items():
        value = state[key]
        if not value.numel():
            continue
        lo = torch.as_tensor(low, dtype=torch.float64, device=value.device)  # the env's device (CUDA too)
        hi = torch.as_tensor(high, dtype=torch.float64, device=value.device)
        wide = value.to(torch.float64)  # int64 counters compared exactly enough; no overflow in the test
        if bool(((wide < lo) | (wide > hi)).any()):
            raise ValueError(f"{label.format(key=key)} must be within [{_bound(low)}, {_bound(high)}], got values in "
                             f"[{wide.min().item():.6g}, {wide.max().item():.6g}]")


def _bound(value) -> str:
    return str(list(value)) if isinstance(value, (tuple, list)) else f"{value:g}"


def _show(value) -> str:
    return str(list(value)) if isinstance(value, torch.Size) else str(value)
