"""gymnasium front end: every agent of every world of one BatchedEnv as a ``gymnasium.vector.VectorEnv``.

    from marl_render.envs import make_vec_env
    envs = make_vec_env("cartpole", num_worlds=64, resolution=64)   # 64 entries, one renderer
    obs, infos = envs.reset(seed=0)                                 # uint8 numpy [64, 64, 64, 3]
    obs, rewards, terminations, truncations, infos = envs.step(envs.action_space.sample())

One batched core steps all worlds and one renderer draws all views: a step is one core
step, whatever the number of entries.

Entries: ``num_envs = num_worlds x num_agents``; entry ``i`` is agent ``i % A`` of world
``i // A``, the layout of supersuit's Markov vector env (``pettingzoo_env_to_vec_env_v1`` +
``concat_vec_envs_v1``) that CleanRL's PettingZoo PPO trains with one shared policy.
Single-agent envs (cartpole) have one entry per world.

Spaces: ``single_observation_space`` is ``Box(0, 255, (H, W, 3), uint8)`` by default. With
``depth=True``, ``state_obs=True``, ``lidar=rays`` or ``action_mask=True`` it is a ``Dict`` with
"pixels", "depth", "state", "lidar" and "action_mask" (``MultiBinary(num_actions)``, int8), as in the
PettingZoo front end. ``single_action_space`` is ``Discrete(num_actions)`` or
``Box(-1, 1, (action_dim,), float32)``. ``observation_space`` / ``action_space`` are their
batches (``gymnasium.vector.utils.batch_space``). Observations are numpy views of the
renderer's output, which is fresh memory each step: no copy on the CPU.

Autoreset: ``autoreset_mode`` (a ``gymnasium.vector.AutoresetMode``; stored in
``metadata["autoreset_mode"]``) selects the core's mode (envs/core.py):

* ``NEXT_STEP`` (the default, as gymnasium's own vector envs): the step after an entry's
  episode ended resets its world; its actions are ignored and it returns the first obs
  of the new episode with reward 0, terminated and truncated False. One render per step.
* ``SAME_STEP``: the step that ends an episode returns the first obs of the new one;
  ``infos["final_obs"]`` (an object array, None for the other entries) and
  ``infos["final_info"]`` hold the ended episode's last obs and info, masked by
  ``infos["_final_obs"]`` / ``infos["_final_info"]``. A step on which a world ends renders
  twice (the final frame and the new one).
* ``DISABLED``: nothing resets by itself; ``reset(options={"reset_mask": mask})`` resets
  the worlds of the entries where the bool [num_envs] mask is True (the first reset resets
  every world, as TorchRL's does: a world never reset has no episode to keep).

Levels (an env built with ``levels=``, envs/levels.py): ``reset(options={"level_ids": ids})``
resets worlds to chosen levels (the core's ``reset_to_level``): ``ids`` is an int64 numpy array
of shape (num_worlds,), one level per world (not per entry: a world resets with all its agents),
read where ``reset_mask`` is True (all worlds without one). Infos then carry ``level`` (the level
of each entry's world) at every step and at reset. SB3: ``set_options({"level_ids": ids})``.

Agents that leave before their world ends (tag's caught prey): an entry's episode is its
world's episode. From the step its agent leaves until its world's episode ends, the
entry's observation is zeros (supersuit's "black death") and its reward 0; it reports
terminated or truncated only when the world's episode ends (then every entry of that world
does, with its real final frame).

Infos follow gymnasium's vector layout: every key has a bool mask ``"_" + key`` of the
entries that have it. Step infos are ``step_count`` and the env's own keys (e.g. spread's
``coverage``; per-world values repeated for each agent of the world). Entries that were
reset by a step (NEXT_STEP) or ended their episode on it (SAME_STEP, where the values move
to ``final_info``) have none. ``reset`` returns an empty info dict.

gymnasium ids: importing ``marl_render.envs`` registers ``marl_render/<name>-v0`` for every
env of the suite. ``gymnasium.make_vec(id, num_envs=N, **kwargs)`` builds ``make_vec_env``
with N / num_agents worlds (``gymnasium_vector_entry_point``), and ``make_vec_env`` sets
``spec`` so that ``gymnasium.make_vec(envs.spec)`` builds the same again. For the
single-agent env (cartpole) ``gymnasium.make(id)`` or ``make_gym_env(name)`` gives one world
as a ``gymnasium.Env`` (``MarlRenderGymEnv``) that passes gymnasium's ``check_env``.

Seeding: ``reset(seed=int)`` re-seeds the core's generator (one generator draws for all
worlds, so a list of per-entry seeds raises TypeError) and the env's ``np_random``.
Unknown ``reset`` options are ignored, as gymnasium envs do.
"""
from __future__ import annotations

import gymnasium
import numpy as np
import torch
from gymnasium import logger
from gymnasium.envs.registration import EnvSpec
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from marl_render.envs.levels import check_level_ids
from marl_render.envs.registry import env_class, make_env, split_kwargs
from marl_render.validation import describe, positive_int, unpicklable
from marl_render.wrappers import spaces as spaces_from_spec
from marl_render.wrappers.common import (
    check_core,
    check_flag,
    check_render_mode,
    closed_on_error,
    numpy_observations,
    observation_keys,
    refuse_num_processes,
    require_levels,
    reset_core,
)

RENDER_MODES = ("rgb_array",)
CORE_AUTORESET = {AutoresetMode.NEXT_STEP: "next_step", AutoresetMode.SAME_STEP: "same_step",
                  AutoresetMode.DISABLED: False}
_MODE_OF_CORE = {mode: autoreset for autoreset, mode in CORE_AUTORESET.items()}
_NOT_STEP_INFO = ("done_worlds", "autoreset_worlds", "final_obs", "final_level")  # carried by the step's own outputs
_VECTOR_ONLY = ("autoreset_mode", "action_mask", "render_mode")  # make_vec_env's own keywords, not make_env's


def make_vec_env(name: str, num_worlds: int = 1, *, autoreset_mode=AutoresetMode.NEXT_STEP,
                 action_mask: bool = False, render_mode: str | None = None, **kwargs) -> MarlRenderVectorEnv:
    """A gymnasium VectorEnv of the registered environment `name`: num_worlds x num_agents entries.

    autoreset_mode: an AutoresetMode (or its value, e.g. "SameStep"); default NEXT_STEP.
    action_mask: add the action mask to a Dict observation (discrete envs).
    render_mode: None or "rgb_array" (render() then gives each entry its world's overview).
    kwargs go to ``marl_render.envs.make_env`` (resolution, num_agents, max_steps, continuous,
    state_obs, depth, seed, device and the env's own arguments); ``autoreset`` is set from
    autoreset_mode and may not be passed."""
    refuse_num_processes("make_vec_env", kwargs)
    if "autoreset" in kwargs:
        raise TypeError("make_vec_env() does not accept 'autoreset'; pass autoreset_mode="
                        "gymnasium.vector.AutoresetMode.NEXT_STEP, SAME_STEP or DISABLED")
    mode = _autoreset_mode(autoreset_mode)
    check_flag("action_mask", action_mask)
    check_render_mode(render_mode, RENDER_MODES)
    with closed_on_error(make_env(name, num_worlds=num_worlds, autoreset=CORE_AUTORESET[mode], **kwargs)) as core:
        envs = MarlRenderVectorEnv(core, action_mask=action_mask, render_mode=render_mode)
    # gymnasium.make_vec(envs.spec) builds the same again (num_envs is the number of entries).
    envs.spec = _spec(name, vector_entry_point=f"{__name__}:gymnasium_vector_entry_point",
                      kwargs=dict(name=name, num_envs=envs.num_envs, autoreset_mode=mode.value,
                                  action_mask=action_mask, render_mode=render_mode, **kwargs))
    return envs


def gymnasium_id(name: str) -> str:
    """The gymnasium id of the env `name`: "marl_render/<name>-v0"."""
    return f"marl_render/{name}-v0"


def _spec(name: str, **fields) -> EnvSpec | None:
    try:
        return EnvSpec(gymnasium_id(name), **fields)
    except Exception:  # a user-registered name gymnasium cannot parse as an id: no spec, as before
        return None


def gymnasium_vector_entry_point(name: str, num_envs: int = 1, **kwargs) -> MarlRenderVectorEnv:
    """``gymnasium.make_vec("marl_render/<name>-v0", num_envs=N, **kwargs)``: make_vec_env with
    N / num_agents worlds (num_envs counts entries, worlds x agents, so it must be a multiple of
    num_agents); kwargs as make_vec_env's."""
    num_envs = positive_int("num_envs", num_envs)
    agents = _agents_per_world(name, kwargs)
    if isinstance(agents, (int, np.integer)) and not isinstance(agents, bool) and agents >= 1 and num_envs % agents:
        raise ValueError(f"num_envs must be a multiple of num_agents={agents} for {name!r} (num_envs = num_worlds x "
                         f"num_agents entries), got {num_envs}")
    worlds = max(1, num_envs // agents) if isinstance(agents, (int, np.integer)) else num_envs
    with closed_on_error(make_vec_env(name, worlds, **kwargs)) as envs:
        if envs.num_envs != num_envs:
            raise ValueError(f"num_envs must be a multiple of num_agents={envs.num_agents} for {name!r}, "
                             f"got {num_envs}")
        return envs


def _agents_per_world(name: str, kwargs: dict):
    """The agent count make_vec_env(name, **kwargs) builds for: the task's own keywords may set it
    (tag's num_predators, num_prey), so it is the task's num_agents_for, not only num_agents."""
    scenario = env_class(name)
    core_kwargs = {key: value for key, value in kwargs.items() if key not in _VECTOR_ONLY}
    options, params = split_kwargs(scenario, core_kwargs)  # an unknown keyword is refused here, by name
    agents = scenario.num_agents_for(params, options.num_agents)
    return scenario.default_num_agents if agents is None else agents


def make_gym_env(name: str, *, render_mode: str | None = None, **kwargs) -> MarlRenderGymEnv:
    """A single-world ``gymnasium.Env`` of the single-agent env `name` (cartpole), also made by
    ``gymnasium.make("marl_render/<name>-v0")``. Observations are one agent's (H, W, 3) uint8
    frame (or its Dict, as make_vec_env's entries), actions one action; an episode ends by
    termination or at max_steps (truncation), and the env waits for ``reset()`` (no autoreset).
    kwargs go to ``marl_render.envs.make_env`` (resolution, max_steps, continuous, state_obs,
    depth, seed, device, ...); num_worlds (1) and autoreset are set here."""
    for key in ("num_worlds", "autoreset", "autoreset_mode"):
        if key in kwargs:
            raise TypeError(f"make_gym_env() does not accept {key!r}: a gymnasium.Env is one world that resets "
                            f"when reset() is called; use make_vec_env for batched worlds")
    with closed_on_error(make_vec_env(name, 1, autoreset_mode=AutoresetMode.DISABLED, render_mode=render_mode,
                                      **kwargs)) as envs:
        if envs.num_agents != 1:
            raise ValueError(f"make_gym_env needs a single-agent env, and {name!r} has {envs.num_agents} agents: use "
                             f"make_parallel_env (PettingZoo) or make_vec_env (one entry per agent) for it")
        env = MarlRenderGymEnv(envs)
    env.spec = _spec(name, entry_point=f"{__name__}:make_gym_env", kwargs=dict(name=name, render_mode=render_mode,
                                                                               **kwargs))
    return env


class MarlRenderGymEnv(gymnasium.Env):
    """One world of a single-agent env as a ``gymnasium.Env``: a one-entry MarlRenderVectorEnv
    (autoreset DISABLED) seen one entry at a time; see make_gym_env. ``vector`` is that vector
    env, owned (closed in ``close()``)."""

    def __init__(self, vector: MarlRenderVectorEnv):
        if not isinstance(vector, MarlRenderVectorEnv) or vector.num_envs != 1:
            raise TypeError(f"vector must be a MarlRenderVectorEnv with one entry (see make_gym_env), "
                            f"got {describe(vector)}")
        self.vector = vector
        self.observation_space = vector.single_observation_space
        self.action_space = vector.single_action_space
        self.render_mode = vector.render_mode
        self.metadata = {"render_modes": list(RENDER_MODES), "render_fps": round(1 / vector.core.dt),
                         "name": vector.core.name}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        observations, _ = self.vector.reset(seed=seed, options=options)  # checks seed before anything changes
        super().reset(seed=None if seed is None else int(seed))
        return self._one(observations), {}

    def step(self, action):
        observations, rewards, terminations, truncations, infos = self.vector.step(self._batch(action))
        info = {key: value[0] for key, value in infos.items() if not key.startswith("_")}
        return (self._one(observations), float(rewards[0]), bool(terminations[0]), bool(truncations[0]), info)

    def render(self):
        """The world's overview, uint8 (H, W, 3), with render_mode="rgb_array"; else None."""
        frames = self.vector.render()
        return None if frames is None else frames[0]

    def close(self):
        self.vector.close()

    def __reduce__(self):
        raise unpicklable("a MarlRenderGymEnv", "marl_render.wrappers.gymnasium.make_gym_env")

    def __repr__(self):
        return f"MarlRenderGymEnv({self.vector.core.name})"

    def _batch(self, action):
        """The action as the vector env's batch of one entry."""
        if isinstance(action, (torch.Tensor, np.ndarray)):
            return action[None]
        return np.asarray([action])

    def _one(self, observations):
        if isinstance(observations, dict):
            return {key: value[0] for key, value in observations.items()}
        return observations[0]


def _autoreset_mode(value) -> AutoresetMode:
    try:
        return AutoresetMode(value)
    except ValueError:
        raise ValueError(f"autoreset_mode must be a gymnasium.vector.AutoresetMode (or one of "
                         f"{[m.value for m in AutoresetMode]}), got {describe(value)}") from None


class MarlRenderVectorEnv(VectorEnv):
    """All worlds and agents of a ``BatchedEnv`` as one gymnasium VectorEnv; see the module
    docstring. ``core`` is the wrapped BatchedEnv, owned (closed in ``close()``); its
    ``autoreset`` gives the autoreset mode."""

    def __init__(self, env, *, action_mask: bool = False, render_mode: str | None = None):
        check_core(env)
        check_flag("action_mask", action_mask)
        check_render_mode(render_mode, RENDER_MODES)
        self._obs_keys = observation_keys(env, action_mask)
        self._dict_obs = self._obs_keys != ("pixels",)
        self.core = env
        self.num_worlds, self.num_agents = env.num_worlds, env.num_agents
        self.num_envs = env.num_worlds * env.num_agents
        self.render_mode = render_mode
        self.metadata = {"autoreset_mode": _MODE_OF_CORE[env.autoreset], "render_modes": list(RENDER_MODES),
                         "name": env.name}
        self.single_observation_space = spaces_from_spec.observation_space(env.spec, self._obs_keys)
        self.single_action_space = spaces_from_spec.action_space(env.spec)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._started = False

    # ------------------------------------------------------------------ API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """(observations, {}) of a new episode in every world, or only in the worlds of
        ``options["reset_mask"]`` (after the first reset, which resets every world); `seed`
        re-seeds the core's generator first."""
        if seed is not None and (isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer))):
            raise TypeError(f"seed must be None or an int (one generator draws for every world, so per-entry "
                            f"seeds are not supported), got {describe(seed)}")
        seed = None if seed is None else int(seed)  # gymnasium's own seeding takes Python ints only
        worlds = self._reset_mask(options)
        levels = self._level_ids(options, worlds)
        obs = reset_core(self.core, seed, worlds=worlds, levels=levels, full=not self._started)
        super().reset(seed=seed)
        self._started = True
        infos = {} if self.core.levels is None else _masked({"level": self._entries(self.core.level_ids)}, None)
        return self._observations(obs), infos

    def step(self, actions):
        """(observations, rewards, terminations, truncations, infos), one entry per (world, agent)."""
        if self.core.closed:
            raise RuntimeError("this environment is closed; create a new one")
        if not self._started:
            raise RuntimeError("call reset() before step()")
        obs, reward, terminated, truncated, info = self.core.step(self._actions(actions))
        done_worlds = info["done_worlds"][:, None]
        n = self.num_envs
        terminations = (terminated & done_worlds).reshape(n).cpu().numpy()
        truncations = (truncated & done_worlds).reshape(n).cpu().numpy()
        return (self._observations(obs), reward.reshape(n).cpu().numpy(), terminations, truncations,
                self._infos(info))

    def render(self):
        """A tuple with each entry's frame: the overview of its world (render_mode="rgb_array")."""
        if self.render_mode is None:
            logger.warn("You are calling render() without a render_mode; pass render_mode='rgb_array' to make_vec_env.")
            return None
        overview = self.core.render_overview().cpu().numpy()
        return tuple(np.repeat(overview, self.num_agents, axis=0))

    def close_extras(self, **kwargs):
        self.core.close()

    def __reduce__(self):
        raise unpicklable("a MarlRenderVectorEnv", "marl_render.envs.make_vec_env")

    def __repr__(self):
        return (f"MarlRenderVectorEnv({self.core.name}, num_envs={self.num_envs} = {self.num_worlds} worlds x "
                f"{self.num_agents} agents, autoreset_mode={self.metadata['autoreset_mode']})")

    # ------------------------------------------------------------------ internals
    def _reset_mask(self, options) -> torch.Tensor | None:
        """bool [W] worlds to reset from options["reset_mask"] (bool [num_envs]); None: all worlds."""
        if options is None:
            return None
        if not isinstance(options, dict):
            raise TypeError(f"options must be None or a dict, got {describe(options)}")
        if "reset_mask" not in options:
            return None
        mask = options["reset_mask"]
        want = f"a bool numpy array of shape ({self.num_envs},) (num_envs), the same for all agents of a world"
        if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
            raise TypeError(f"options['reset_mask'] must be {want}, got {describe(mask)}")
        if mask.shape != (self.num_envs,):
            raise ValueError(f"options['reset_mask'] must be {want}, got shape {mask.shape}")
        per_world = mask.reshape(self.num_worlds, self.num_agents)
        if not (per_world == per_world[:, :1]).all():
            raise ValueError(f"options['reset_mask'] must be {want}: a world resets with all of its agents")
        return torch.from_numpy(per_world[:, 0].copy())

    def _level_ids(self, options, worlds: torch.Tensor | None) -> torch.Tensor | None:
        """int64 [W] levels from options["level_ids"] (numpy int, shape (num_worlds,)); None if absent."""
        if not isinstance(options, dict) or "level_ids" not in options:
            return None
        require_levels(self.core, "options['level_ids']")
        ids = options["level_ids"]
        want = f"an int64 numpy array of shape ({self.num_worlds},) (num_worlds: one level per world)"
        if not isinstance(ids, np.ndarray) or not np.issubdtype(ids.dtype, np.integer):
            raise TypeError(f"options['level_ids'] must be {want}, got {describe(ids)}")
        if ids.shape != (self.num_worlds,):
            raise ValueError(f"options['level_ids'] must be {want}, got shape {ids.shape}")
        return check_level_ids("options['level_ids']", torch.from_numpy(ids.astype(np.int64)), self.num_worlds,
                               where=worlds)

    def _actions(self, actions):
        """The actions as the core's [W, A(, action_dim)] batch (the core checks dtype and values)."""
        if not isinstance(actions, (torch.Tensor, np.ndarray)):
            try:
                actions = np.asarray(actions)
            except (TypeError, ValueError):
                raise TypeError(f"actions must be an array of shape {self.action_space.shape}, "
                                f"got {describe(actions)}") from None
        if tuple(actions.shape) != self.action_space.shape:
            raise ValueError(f"actions must be an array of shape {self.action_space.shape} (num_envs = "
                             f"{self.num_worlds} worlds x {self.num_agents} agents), got shape {tuple(actions.shape)}")
        return actions.reshape(self.num_worlds, self.num_agents, *self.single_action_space.shape)

    def _observations(self, obs: dict):
        """numpy [num_envs, ...] per key; departed agents of running worlds see zeros."""
        core = self.core
        over = core.episode_over()
        departed = ~core.alive & ~over[:, None]
        if bool(departed.any()):
            for key in self._obs_keys:
                if key != "action_mask":
                    obs[key][departed] = 0
        arrays = numpy_observations(obs, self._obs_keys, self._entries)
        return arrays if self._dict_obs else arrays["pixels"]

    def _entries(self, value: torch.Tensor) -> np.ndarray:
        """numpy [num_envs, ...] of a core tensor [W, A, ...] (per agent) or [W, ...] (per world)."""
        W, A = self.num_worlds, self.num_agents
        if value.dim() >= 2 and value.shape[1] == A:
            value = value.reshape(W * A, *value.shape[2:])
        elif A > 1:
            value = value.repeat_interleave(A, dim=0)
        return value.cpu().numpy()

    def _infos(self, info: dict) -> dict:
        mode = self.metadata["autoreset_mode"]
        step_info = {key: self._entries(value) for key, value in info.items()
                     if key not in _NOT_STEP_INFO and isinstance(value, torch.Tensor)}
        if mode == AutoresetMode.DISABLED:
            without = None
        else:  # NEXT_STEP: worlds reset by this step; SAME_STEP: worlds whose episode ended
            without = self._entries(info["autoreset_worlds"])
        infos = _masked(step_info, None if without is None else ~without)
        if mode == AutoresetMode.SAME_STEP and without.any():
            final_obs = self._observations_of_final(info["final_obs"], without)
            if "final_level" in info:  # the ended episodes' levels, not the new ones
                step_info["level"] = self._entries(info["final_level"])
            infos.update(final_obs=final_obs, _final_obs=without.copy(),
                         final_info=_masked(step_info, without), _final_info=without.copy())
        return infos

    def _observations_of_final(self, obs: dict, ended: np.ndarray) -> np.ndarray:
        """gymnasium's final_obs: an object array with each ended entry's last observation."""
        arrays = numpy_observations(obs, self._obs_keys, self._entries)
        final = np.full(self.num_envs, None, dtype=object)
        for i in np.flatnonzero(ended):  # one object per ended entry is gymnasium's layout
            final[i] = {key: value[i] for key, value in arrays.items()} if self._dict_obs else arrays["pixels"][i]
        return final


def _masked(values: dict, mask: np.ndarray | None) -> dict:
    """gymnasium's vector info layout: each key with its "_key" bool mask (None: all entries);
    keys no entry has are left out."""
    if mask is not None and not mask.any():
        return {}
    out = {}
    for key, value in values.items():
        out[key] = value
        out["_" + key] = np.ones(len(value), dtype=bool) if mask is None else mask.copy()
    return out


__all__ = ["MarlRenderGymEnv", "MarlRenderVectorEnv", "make_gym_env", "make_vec_env", "gymnasium_id",
           "gymnasium_vector_entry_point", "CORE_AUTORESET", "RENDER_MODES"]
