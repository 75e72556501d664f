"""Stable-Baselines3 front end: the gymnasium vector env of marl_render.wrappers.gymnasium
as an SB3 ``VecEnv`` (SB3 has its own vector env class and does not take gymnasium's).

    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor
    from marl_render.envs import make_sb3_env
    venv = VecMonitor(make_sb3_env("cartpole", num_worlds=32, resolution=64))
    model = PPO("CnnPolicy", venv, n_steps=128, batch_size=256).learn(100_000)

One batched core and one renderer serve all ``num_envs = num_worlds x num_agents`` entries
(the layout of marl_render.wrappers.gymnasium: entry i is agent i % A of world i // A).
SB3's conventions are met: auto-reset in the same step, the ended episode's last
observation in ``infos[i]["terminal_observation"]`` and ``infos[i]["TimeLimit.truncated"]``
for a time limit; observations are uint8 ``(H, W, 3)`` images (PPO wraps them in
``VecTransposeImage`` by itself) or a Dict (``MultiInputPolicy``). Because the final frame
is needed, a step on which a world ends renders twice.

The batch is one environment, not ``num_envs`` copies: ``get_attr`` reads an attribute of
the vector env (or of its core) once and repeats it per index; ``env_method`` calls the
method once and repeats its result; ``set_attr`` sets it once (indices are checked against
``[0, num_envs)``); ``seed(s)`` (one int) seeds the next reset with ``s`` (the core's one
generator draws for every world); ``set_options(options)`` passes one options dict (e.g.
``{"reset_mask": mask}``) to the next reset, the same for every entry.
"""
from __future__ import annotations

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv

from marl_render.validation import describe, unpicklable

from .gymnasium import MarlRenderVectorEnv, make_vec_env


def make_sb3_env(name: str, num_worlds: int = 1, **kwargs) -> MarlRenderSB3VecEnv:
    """An SB3 VecEnv of the registered environment `name` (num_worlds x num_agents entries).

    kwargs go to ``marl_render.envs.make_vec_env`` (resolution, num_agents, max_steps,
    continuous, state_obs, depth, action_mask, render_mode, seed, ...); the autoreset
    mode is SB3's (same step) and may not be passed."""
    if "autoreset_mode" in kwargs or "autoreset" in kwargs:
        raise TypeError("make_sb3_env() does not accept 'autoreset_mode' or 'autoreset': SB3 resets "
                        "in the same step (AutoresetMode.SAME_STEP)")
    venv = make_vec_env(name, num_worlds, autoreset_mode=AutoresetMode.SAME_STEP, **kwargs)
    try:
        return MarlRenderSB3VecEnv(venv)
    except BaseException:
        venv.close()
        raise


class MarlRenderSB3VecEnv(VecEnv):
    """A same-step ``MarlRenderVectorEnv`` as an SB3 VecEnv; see the module docstring."""

    def __init__(self, venv: MarlRenderVectorEnv):
        if not isinstance(venv, MarlRenderVectorEnv):
            raise TypeError(f"venv must be a MarlRenderVectorEnv (see marl_render.envs.make_vec_env), "
                            f"got {describe(venv)}")
        if venv.metadata["autoreset_mode"] != AutoresetMode.SAME_STEP:
            raise ValueError(f"venv must reset in the same step as SB3 does (autoreset_mode=AutoresetMode.SAME_STEP), "
                             f"got {venv.metadata['autoreset_mode']}")
        self.venv = venv
        self._actions = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    def seed(self, seed: int | None = None) -> list:
        """SB3's seed: entry i is given seed + i for the next reset; the core's one generator takes
        the first. One int (or None for a random one), as SB3's VecEnv.seed documents."""
        if seed is not None and (isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer))):
            raise TypeError(f"seed must be None or one int (entry i then gets seed + i, as SB3's VecEnv.seed does; "
                            f"per-entry seeds are not supported: one generator draws for every world), "
                            f"got {describe(seed)}")
        return super().seed(None if seed is None else int(seed))

    def set_options(self, options: list | dict | None = None) -> None:
        """Options for the next reset, as SB3's VecEnv.set_options (e.g. {"reset_mask": mask}, see
        marl_render.wrappers.gymnasium). One reset serves every entry, so a list must hold the same
        options for all of them."""
        if options is not None and not isinstance(options, (dict, list, tuple)):
            raise TypeError(f"options must be None, a dict or a list of {self.num_envs} dicts, got {describe(options)}")
        if isinstance(options, (list, tuple)):
            if len(options) != self.num_envs or not all(isinstance(o, dict) for o in options):
                raise ValueError(f"options must be None, a dict or a list of {self.num_envs} dicts (num_envs), "
                                 f"got {describe(options)}")
            if any(not _same_options(o, options[0]) for o in options[1:]):
                raise ValueError("options must be the same for every entry: one reset serves the whole batch "
                                 "(pass one dict)")
        super().set_options(options)

    def reset(self):
        seed = self._seeds[0]  # seed(s) gives entry i the seed s + i; the core takes one
        options = self._options[0] or None  # set_options keeps the same dict for every entry
        observations, _ = self.venv.reset(seed=seed, options=options)
        self._reset_seeds()
        self._reset_options()
        return observations

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        if self._actions is None:
            raise RuntimeError("call step_async(actions) before step_wait()")
        actions, self._actions = self._actions, None
        observations, rewards, terminations, truncations, info = self.venv.step(actions)
        dones = terminations | truncations
        infos = [{} for _ in range(self.num_envs)]  # SB3's API: one dict per entry
        for i in np.flatnonzero(dones):  # only the entries whose episode ended
            infos[i]["terminal_observation"] = info["final_obs"][i]
            infos[i]["TimeLimit.truncated"] = bool(truncations[i] and not terminations[i])
        return observations, rewards, dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self):
        frames = self.venv.render()
        return [None] * self.num_envs if frames is None else list(frames)

    def get_attr(self, attr_name: str, indices=None) -> list:
        indices = self._get_indices(indices)
        target = self.venv if hasattr(self.venv, attr_name) else self.venv.core
        value = getattr(target, attr_name)
        return [value for _ in indices]

    def set_attr(self, attr_name: str, value, indices=None) -> None:
        self._get_indices(indices)
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list:
        indices = self._get_indices(indices)
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result for _ in indices]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list:
        return [False for _ in self._get_indices(indices)]

    def __reduce__(self):
        raise unpicklable("a MarlRenderSB3VecEnv", "marl_render.envs.make_sb3_env")

    def __repr__(self):
        return f"MarlRenderSB3VecEnv({self.venv!r})"

    def _get_indices(self, indices) -> list:
        """SB3's indices (None, an int or ints) as a list, checked against [0, num_envs) (negative ones
        count from the end, as a list of envs would take them): an IndexError names a bad one."""
        n = self.num_envs
        given = range(n) if indices is None else [indices] if isinstance(indices, (int, np.integer)) else indices
        try:
            given = list(given)
        except TypeError:
            raise TypeError(f"indices must be None, an int or a sequence of ints, got {describe(indices)}") from None
        for index in given:
            if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)):
                raise TypeError(f"indices must be None, an int or a sequence of ints, got {describe(indices)}")
            if not -n <= index < n:
                raise IndexError(f"indices must be in [0, {n}) (num_envs = {n}), got {describe(indices)}")
        return [int(index) % n for index in given]


__all__ = ["MarlRenderSB3VecEnv", "make_sb3_env"]


def _same_options(a: dict, b: dict) -> bool:
    """Whether two option dicts are equal, numpy arrays (e.g. a reset mask) compared by value."""
    if a.keys() != b.keys():
        return False
    return all(np.array_equal(a[k], b[k]) if isinstance(a[k], np.ndarray) or isinstance(b[k], np.ndarray)
               else a[k] == b[k] for k in a)
