"""The scenario's hook contract: what a task declares and what its hooks return, checked by the driver.

A task's mistake is named at its declaration or hook (``Spread.step's reward must have shape ...``)
rather than deep in the renderer or at a later step. ``HookContract(scenario, batch, state, state_obs)``
checks the declarations once, when the driver is built; the driver then passes every hook's result
through it:

    contract = HookContract(scenario, batch, scenario.initial_state(), state_obs=False)
    state, reward, terminated, info = contract.checked_step(scenario.step(state, actions, alive, generator))
    fresh = contract.checked_state("Spread.spawn", scenario.spawn(generator))
    contract.check_values(explicit_state.fields(fresh), "Spread.spawn's state.{key}")   # bounds, check_state
    obs = contract.owned("observation", scenario.observation(state, alive), state_dim)
    mask = contract.action_mask(state, alive)

The checks on the hot path are shape, dtype and device reads and one sum per float tensor (a finite
sum proves every value finite in one reduction).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from marl_render.util.validation import describe

from . import state as explicit_state
from .scenario import BatchShape, Scenario, VectorObs
from .spec import OBS_KEYS, RESERVED_INFO


class HookContract:
    """The hooks of one built scenario, checked against its declarations and the batch; see the module
    docstring. ``bounds`` is its checked ``state_bounds()``; ``fresh_masks`` says whether its action
    mask is the default hook's (a new tensor every call, so the driver need not copy it)."""

    def __init__(self, scenario: Scenario, batch: BatchShape, state, state_obs: bool):
        self.scenario, self.batch = scenario, batch
        self.task = type(scenario).__name__
        self.step_where = f"{self.task}.{scenario.step_hook}"
        self._check_declarations(state, state_obs)
        # Every later state must match the first one field by field: {name: (shape, dtype, device)}.
        self.state_class = type(state)
        self.fields = {name: (tuple(value.shape), value.dtype, value.device)
                       for name, value in explicit_state.fields(state).items()}
        self.bounds = self._checked_bounds(scenario.state_bounds(), explicit_state.fields(state))
        self.fresh_masks = type(scenario).action_mask is Scenario.action_mask
        scenario.check_declarations(state)

    # ------------------------------------------------------------------ once, when the driver is built
    def _check_declarations(self, state, state_obs: bool) -> None:
        """A scenario whose declarations are incomplete or disagree fails here, when the env is built,
        naming the declaration or the hook (not at the first reset or step, or deep in the renderer)."""
        s, name = self.scenario, self.task
        W, A, continuous, device = self.batch
        for key, entry in s.vector_obs.items():
            if not (isinstance(key, str) and key not in OBS_KEYS and isinstance(entry, VectorObs)
                    and isinstance(entry.width, int) and entry.width >= 1 and entry.low < entry.high):
                raise ValueError(f"{name}.vector_obs must map new obs keys (not {list(OBS_KEYS)}) to "
                                 f"VectorObs(width >= 1, low < high), got {key!r}: {describe(entry)}")
        where = f"{name}.setup"
        if len(s.agent_names) != A or len(set(s.agent_names)) != A:
            raise RuntimeError(f"{where} must give teams holding {A} distinct agent names, got {s.agent_names}")
        if continuous and not (isinstance(s.action_dim, int) and s.action_dim >= 1):
            raise RuntimeError(f"{where} must declare continuous_actions(dim) with dim >= 1 for continuous=True")
        if not continuous and not (isinstance(s.num_actions, int) and s.num_actions >= 1):
            raise RuntimeError(f"{where} must declare discrete_actions(meanings) with at least one action")
        if isinstance(s.dt, bool) or not isinstance(s.dt, (int, float)) or not 0 < s.dt < math.inf:
            raise ValueError(f"{name}.dt (simulated seconds per step) must be a finite number > 0, got {s.dt!r}")
        if state_obs and not s.state_dim:
            raise ValueError(f"state_obs=True needs a task with a state observation, and {name} has none "
                             f"(state_dim 0, no observation hook)")
        check_info_keys(name, dict(s.info_keys))
        if not (dataclasses.is_dataclass(state) and not isinstance(state, type)):
            raise RuntimeError(f"{name}.initial_state must return a dataclass of tensors (envs/state.py), "
                               f"got {describe(state)}")
        # Every field has the worlds first. A field whose length is W by chance (a task's constant
        # vector) would be split between worlds by partial resets, so the task's batch shape is probed
        # with another world count too (1, or 2 for W = 1): its fields must follow it.
        probe_worlds = 2 if W == 1 else 1
        try:
            probe = explicit_state.fields(type(s)(s.params, BatchShape(probe_worlds, A, continuous,
                                                                        device)).initial_state())
        except Exception:  # a task that cannot be built for that count: the check below is all there is
            probe = None
        for field, value in explicit_state.fields(state).items():
            probed = value if probe is None else probe.get(field)
            expected = W if probe is None else probe_worlds
            if not (isinstance(value, torch.Tensor) and value.ndim and value.shape[0] == W
                    and isinstance(probed, torch.Tensor) and probed.ndim and probed.shape[0] == expected):
                got = [f"shape {list(t.shape)}" if isinstance(t, torch.Tensor) else describe(t)
                       for t in (value, probed)]
                raise ValueError(f"{name}.initial_state's field {field!r} must be a tensor with the worlds first, "
                                 f"[W, ...] (every world has its own value); with W={W} it has {got[0]}, "
                                 f"with W={expected} {got[1]}")
            if not same_device(value.device, device):
                raise ValueError(f"{name}.initial_state's field {field!r} must be on device {device}, got "
                                 f"{value.device}")

    def _checked_bounds(self, bounds, fields: dict) -> dict:
        """The scenario's state_bounds(), checked once: fields of the state, (low, high) numbers or
        one number per index of the field's last axis."""
        where = f"{self.task}.state_bounds"
        if not isinstance(bounds, dict):
            raise TypeError(f"{where} must return a dict {{field: (low, high)}}, got {describe(bounds)}")
        for key, pair in bounds.items():
            if key not in fields:
                raise ValueError(f"{where} names {key!r}, which is not a field of the state {sorted(fields)}")
            try:
                low, high = (torch.as_tensor(v, dtype=torch.float64) for v in pair)
                np.broadcast_shapes(low.shape, high.shape, fields[key].shape)  # torch's imports sympy (1.3 CPU-s)
            except (TypeError, ValueError, RuntimeError) as error:
                raise ValueError(f"{where}[{key!r}] must be (low, high), each a number or one per index of the "
                                 f"field's last axis (shape {list(fields[key].shape)}), got {describe(pair)}"
                                 ) from error
        return bounds

    # ------------------------------------------------------------------ every call of a hook
    def checked_step(self, result):
        """Scenario.step's result after checking its form, so that a task's mistake is named at its
        hook rather than deep in the renderer (shape and dtype reads, and whether the reward is finite)."""
        where = self.step_where
        if not (isinstance(result, tuple) and len(result) == 4):
            raise TypeError(f"{where} must return (state, reward, terminated, info), got {describe(result)}")
        state, reward, terminated, info = result
        state = self.checked_state(where, state)
        W, A, _, device = self.batch
        check_tensor(f"{where}'s reward", reward, (W, A), "float", device)
        check_tensor(f"{where}'s terminated", terminated, (W, A), "bool", device)
        task_keys = self.scenario.info_keys
        if not isinstance(info, dict) or set(info) != set(task_keys):
            raise ValueError(f"{where}'s info must be a dict with the keys of info_keys {sorted(task_keys)}, "
                             f"got {sorted(info) if isinstance(info, dict) else describe(info)}")
        for key, dtype in task_keys.items():
            check_tensor(f"{where}'s info[{key!r}]", info[key], (W,), dtype, device)
        # A finite sum proves every value finite in one reduction (isfinite().all() costs ~4x more);
        # a sum that overflowed is checked in full.
        if not math.isfinite(reward.sum().item()) and not bool(torch.isfinite(reward).all()):
            raise ValueError(f"{where}'s reward must be finite, got NaN or Inf in world(s) "
                             f"{(~torch.isfinite(reward)).any(1).nonzero()[:, 0].tolist()}")
        return state, reward, terminated, info

    def checked_state(self, where: str, state):
        """A hook's new state, checked field by field; cut from autograd where a field requires grad (a
        task's nn.Parameter, say): nothing the env keeps requires grad."""
        if type(state) is not self.state_class:
            raise TypeError(f"{where} must return a {self.state_class.__name__} (the class of initial_state()), "
                            f"got {describe(state)}")
        graphed = {}
        for name, (shape, dtype, device) in self.fields.items():
            value = getattr(state, name)
            check_tensor(f"{where}'s state.{name}", value, shape, dtype, device)
            if value.requires_grad:
                graphed[name] = value.detach()
        return dataclasses.replace(state, **graphed) if graphed else state

    def check_values(self, fields: dict, label: str) -> None:
        """Floats finite, every field within state_bounds and the task's check_state rules."""
        explicit_state.check_bounds(fields, self.bounds, label)
        self.scenario.check_state(fields)

    def owned(self, hook: str, value, width: int) -> torch.Tensor:
        """A hook's per-agent observation [W, A, width], checked, as a float32 copy the caller owns."""
        where = f"{self.task}.{hook}"
        W, A, _, device = self.batch
        check_tensor(where, value, (W, A, width), "float", device)
        owned = value.to(dtype=torch.float32, memory_format=torch.contiguous_format, copy=True)
        if not math.isfinite(owned.sum().item()) and not bool(torch.isfinite(owned).all()):  # as the reward's
            raise ValueError(f"{where} must return finite values, got NaN or Inf in world(s) "
                             f"{(~torch.isfinite(owned)).flatten(1).any(1).nonzero()[:, 0].tolist()}")
        return owned

    def vector_observations(self, state, alive: torch.Tensor) -> dict:
        """The task's vector observations (Scenario.vector_obs), checked, as float32 copies."""
        declared = self.scenario.vector_obs
        given = self.scenario.vector_observations(state, alive)
        if not (isinstance(given, dict) and set(given) == set(declared)):
            got = sorted(given) if isinstance(given, dict) else describe(given)
            raise ValueError(f"{self.task}.vector_observations must return a dict with the keys of "
                             f"vector_obs {sorted(declared)}, got {got}")
        return {key: self.owned("vector_observations", given[key], entry.width) for key, entry in declared.items()}

    def tagged_out(self, state) -> torch.Tensor:
        """Scenario.tagged_out of `state` (who is out of play: the social metrics), checked."""
        tagged = self.scenario.tagged_out(state)
        W, A, _, device = self.batch
        check_tensor(f"{self.task}.tagged_out", tagged, (W, A), "bool", device)
        return tagged

    def action_mask(self, state, alive: torch.Tensor) -> torch.Tensor:
        """The scenario's action mask [W, A, num_actions] of `state`, checked (the hook's own tensor:
        it may be a constant or the state's; copy it before handing it out unless fresh_masks)."""
        s = self.scenario
        mask = s.action_mask(state, alive)
        where = f"{self.task}.action_mask"
        W, A, _, device = self.batch
        check_tensor(where, mask, (W, A, s.num_actions), "bool", device)
        if not self.fresh_masks:  # an agent in the episode with no valid action cannot act, masked or not
            stuck = alive & ~mask.any(-1)
            if bool(stuck.any()):
                world, agent = stuck.nonzero()[0].tolist()
                raise ValueError(f"{where} must allow at least one action to every agent in the episode, got none "
                                 f"for {int(stuck.sum())} agent(s), e.g. world {world} agent "
                                 f"{s.agent_names[agent]!r}")
        return mask

    def name_non_finite(self, state, error: BaseException) -> None:
        """The renderer refused the instances of a state the step hook made: where fields of it are
        not finite, say so, naming the hook and the fields (the renderer knows neither)."""
        bad = [name for name, value in explicit_state.fields(state).items()
               if value.is_floating_point() and not bool(torch.isfinite(value).all())]
        if bad:
            raise ValueError(f"{self.step_where} returned a state with non-finite values (NaN or Inf) in "
                             f"{', '.join('state.' + name for name in bad)}") from error


def check_info_keys(task: str, keys: dict) -> None:
    """info_keys: {str: torch.dtype}, none of them a name the driver's own info entries use."""
    for key, dtype in keys.items():
        if not isinstance(key, str) or not isinstance(dtype, torch.dtype):
            raise TypeError(f"{task}.info_keys must map str names to torch dtypes, got {key!r}: {describe(dtype)}")
    reserved = sorted(key for key in keys if key in RESERVED_INFO or key.startswith("_"))
    if reserved:
        raise ValueError(f"{task}.info_keys names {reserved}, which the driver's own info entries use "
                         f"({list(RESERVED_INFO)}, and gymnasium's masks '_' + key); rename the "
                         f"task's statistic(s) (they would replace the driver's values, or be replaced by them)")


def check_tensor(what: str, value, shape: tuple, dtype, device: torch.device) -> None:
    """A hook's tensor has the declared shape, dtype (a torch.dtype, or "float" / "bool") and device."""
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{what} must be a torch.Tensor of shape {list(shape)}, got {describe(value)}")
    if dtype == "float":
        dtype_ok, want_dtype = value.is_floating_point(), "a float dtype"
    elif dtype == "bool":
        dtype_ok, want_dtype = value.dtype == torch.bool, "torch.bool"
    else:
        dtype_ok, want_dtype = value.dtype == dtype, str(dtype)
    if tuple(value.shape) != shape or not dtype_ok or not same_device(value.device, device):
        raise ValueError(f"{what} must have shape {list(shape)}, {want_dtype}, device {device}; got shape "
                         f"{list(value.shape)}, {value.dtype}, device {value.device}")


def same_device(given: torch.device, want: torch.device) -> bool:
    return given.type == want.type and (want.index is None or given.index == want.index)
