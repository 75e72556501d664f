"""What the front ends share, written once: PettingZoo, gymnasium (and SB3 and RLlib over it),
TorchRL (and BenchMARL over it) and JAX each translate the same driver (envs/core.py) and its
``env.spec`` (envs/spec.py) into their library's terms, and the parts that are not a translation
live here:

* building: ``closed_on_error`` closes what a front end built when wrapping it fails, and
  ``refuse_num_processes`` refuses the keyword only make_env and make_torchrl_env take;
* checks of a front end's own arguments: ``check_core`` (the wrapped driver), ``check_flag``,
  ``check_render_mode``;
* observations: ``observation_keys`` (which of the spec's keys a front end hands out) and
  ``numpy_observations`` (numpy arrays, the action mask as int8);
* resets: ``require_levels`` (the level guard, envs/levels.py) and ``reset_core``, the one
  dispatch of a reset onto the driver's reset / reset_worlds / reset_to_level.

Functions rather than a base class, because the front ends already derive from their library's
class (``pettingzoo.ParallelEnv``, ``gymnasium.vector.VectorEnv``, ``torchrl.envs.EnvBase``),
as VMAS's gym wrappers mix in ``BaseGymWrapper``'s helpers. Nothing here runs per step except
``numpy_observations``, which is the conversion the step did inline before.
"""
from __future__ import annotations

import contextlib

import numpy as np
import torch

from marl_render.envs.core import BatchedEnv
from marl_render.envs.focal import FocalEnv
from marl_render.envs.levels import require_levels
from marl_render.envs.options import flag as check_flag
from marl_render.validation import describe

CORES = (BatchedEnv, FocalEnv)  # the drivers a front end wraps (TorchRL's also takes a MultiProcessEnv)


@contextlib.contextmanager
def closed_on_error(env):
    """``with closed_on_error(make_env(...)) as core: return Wrapper(core)``: `env`, just built and
    held by nobody else, is closed if the block raises (a wrapper refusing its arguments leaves no
    GL context or worker process behind)."""
    try:
        yield env
    except BaseException:
        env.close()
        raise


def refuse_num_processes(maker: str, kwargs: dict) -> None:
    """TypeError if `kwargs` (of the front end `maker`) hold num_processes, before anything is built."""
    if "num_processes" in kwargs:
        raise TypeError(f"{maker}() does not accept 'num_processes': only marl_render.envs.make_env and "
                        f"make_torchrl_env split the worlds over worker processes (docs/distributed.md)")


def check_core(env, *, name: str = "env", kinds: tuple = CORES, no_autoreset: str | None = None) -> None:
    """The driver a front end wraps: one of `kinds`, open, and (with `no_autoreset`, the reason the
    front end resets by itself) built with autoreset=False; else TypeError / ValueError naming `name`."""
    if not isinstance(env, kinds):
        raise TypeError(f"{name} must be a marl_render BatchedEnv (see marl_render.envs.make_env), "
                        f"got {describe(env)}")
    if no_autoreset is not None and env.autoreset:
        raise ValueError(f"{name} must be built with autoreset=False: {no_autoreset}")
    if env.closed:
        raise ValueError(f"{name} is closed")


def check_render_mode(render_mode, modes: tuple) -> None:
    if render_mode is not None and render_mode not in modes:
        raise ValueError(f"render_mode must be None or one of {list(modes)}, got {render_mode!r}")


def observation_keys(env, action_mask: bool) -> tuple:
    """The keys of the spec's observations a gymnasium-style front end hands out: all of them, the
    action mask only when asked for (so that the common pixels-only case stays a plain Box, what
    image wrappers expect). ValueError for action_mask=True with continuous actions."""
    if action_mask and env.spec.action.continuous:
        raise ValueError("action_mask=True needs a discrete env (continuous=False); continuous actions have no mask")
    return tuple(key for key in env.spec.obs_keys if key != "action_mask" or action_mask)


def numpy_observations(obs: dict, keys: tuple, to_numpy) -> dict:
    """{key: to_numpy(obs[key])} for `keys`, the action mask as int8 (the dtype gymnasium's
    MultiBinary holds and ``Discrete.sample(mask=...)`` requires)."""
    arrays = {key: to_numpy(obs[key]) for key in keys}
    if "action_mask" in arrays:
        arrays["action_mask"] = arrays["action_mask"].astype(np.int8)
    return arrays


def reset_core(core, seed: int | None, *, worlds: torch.Tensor | None = None, levels: torch.Tensor | None = None,
               full: bool) -> dict:
    """The driver's observations after resetting the worlds where `worlds` (bool [W]; None: all) is
    True, to `levels` (int64 [W], checked; None: the level sampler's choice), `seed` re-seeding its
    generator first. `full` (a front end's first reset, and every PettingZoo reset) resets every
    world first, with `seed`, and then sets the levels: the driver needs a full reset before a
    partial one."""
    if full:
        obs = core.reset(seed=seed)
        if levels is None:
            return obs
        return core.reset_to_level(_all_worlds(core) if worlds is None else worlds, levels)
    if levels is not None:
        return core.reset_to_level(_all_worlds(core) if worlds is None else worlds, levels, seed=seed)
    return core.reset(seed=seed) if worlds is None else core.reset_worlds(worlds, seed=seed)


def _all_worlds(core) -> torch.Tensor:
    return torch.ones(core.num_worlds, dtype=torch.bool)


__all__ = ["CORES", "check_core", "check_flag", "check_render_mode", "closed_on_error", "numpy_observations",
           "observation_keys", "refuse_num_processes", "require_levels", "reset_core"]
