"""PettingZoo front end: one world of a BatchedEnv as a ``pettingzoo.ParallelEnv``.

    from marl_render.wrappers.pettingzoo import make_parallel_env
    env = make_parallel_env("spread", resolution=32, render_mode="rgb_array")
    obs, infos = env.reset(seed=0)           # obs[agent]: uint8 [H, W, 3]
    while env.agents:
        actions = {a: env.action_space(a).sample() for a in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)
    frame = env.render()                     # every agent's view + the overview, side by side
    env.close()

Spaces (the same for every agent):

* observation: ``Box(0, 255, (H, W, 3), uint8)`` (1 channel with ``grayscale=True``) when the core yields only pixels (the
  default). With ``depth=True``, ``state_obs=True`` or ``action_mask=True`` it is a
  ``Dict`` with "pixels", "depth" (``Box(0, far, (H, W), float32)``: metres, clamped at the
  camera's far plane), "state" (``Box(-inf, inf, (state_dim,), float32)``) and
  "action_mask" (``MultiBinary(num_actions)``, int8: the dtype gymnasium's
  ``Discrete.sample(mask=...)`` requires). Discrete cores always compute an action mask;
  it is exposed only when asked for with ``action_mask=True`` so that the common
  pixels-only case stays a plain Box (what image wrappers such as supersuit's expect).
* action: ``Discrete(num_actions)`` or ``Box(-1, 1, (action_dim,), float32)``.

Episode semantics follow PettingZoo: ``agents`` holds the agents still in the episode; an
agent that leaves (caught prey, time limit) appears once more in the returned dicts with
terminated / truncated True and is then gone; when every agent is done ``agents == []``
and ``reset()`` starts a new episode. The core is built with ``autoreset=False``.

Infos: ``reset`` returns ``{agent: {}}``; ``step`` returns, per agent, the core's info
entries of this world as Python scalars (or numpy arrays): ``step_count`` and the env's
own keys (e.g. spread's ``collisions``, ``coverage``).

Input checks (every call checks all of its input before it changes anything):

* ``step(actions)``: a dict with exactly one action for every agent in ``agents``.
  Unknown agent names raise KeyError; an action for an agent that already left raises
  KeyError too unless ``departed_actions="ignore"`` (torchrl's
  ``PettingZooWrapper(use_mask=True)`` sends an action for every agent, alive or not);
  a missing action raises KeyError; a wrongly typed action raises ``ActionTypeError``
  (a TypeError and a ValueError); out-of-range / NaN / wrongly shaped actions raise
  ValueError. Every message names the agent.
* ``reset(seed, options)``: ``options`` must be None or a dict; this env knows no option
  keys yet, so any key raises ValueError unless ``unknown_options="ignore"``
  (``pettingzoo.test.parallel_api_test`` calls ``reset(options={"options": 1})``).
"""
from __future__ import annotations

import functools
import gymnasium
import numpy as np
import pettingzoo
import torch
from gymnasium import spaces

from marl_render.validation import describe

RENDER_MODES = ("rgb_array",)
KNOWN_OPTIONS: frozenset = frozenset()  # reset(options=...) keys this env understands
_POLICIES = ("raise", "ignore")
_GAP = 2  # pixels between the tiles of render()
_GAP_COLOR = 40


class ActionTypeError(TypeError, ValueError):
    """An action of the wrong type (e.g. a float for a Discrete space); both a TypeError and a ValueError."""


class AgentKeyError(KeyError):
    """KeyError about an agent name, printed without KeyError's extra quotes."""

    def __str__(self):
        return str(self.args[0]) if self.args else ""


def make_parallel_env(name: str, *, render_mode: str | None = None, action_mask: bool = False,
                      departed_actions: str = "raise", unknown_options: str = "raise",
                      **kwargs) -> "MarlRenderParallelEnv":
    """A PettingZoo ParallelEnv of the registered environment `name`, one world.

    kwargs go to ``marl_render.envs.registry.make_env`` (resolution, num_agents, max_steps,
    continuous, state_obs, depth, seed, device and the env's own arguments); num_worlds
    (always 1) and autoreset (always False) are set here and may not be passed."""
    from marl_render.envs.registry import make_env

    for key in ("num_worlds", "autoreset"):
        if key in kwargs:
            raise TypeError(f"make_parallel_env() does not accept {key!r}: a PettingZoo env is one world "
                            f"(num_worlds=1) and resets only when reset() is called (autoreset=False); "
                            f"use make_torchrl_env or marl_render.envs.make_env for batched worlds")
    # Check the wrapper's own arguments before building the (GL-backed) core.
    _check_render_mode(render_mode)
    _check_flag("action_mask", action_mask)
    _check_policy("departed_actions", departed_actions)
    _check_policy("unknown_options", unknown_options)
    core = make_env(name, num_worlds=1, **kwargs)
    try:
        env = MarlRenderParallelEnv(core, render_mode=render_mode, action_mask=action_mask,
                                    departed_actions=departed_actions, unknown_options=unknown_options)
    except BaseException:
        core.close()
        raise
    # How to build this env again: pickling (vectorising wrappers copy envs that way) makes
    # a fresh env of the same configuration in the receiving process, not a GL state copy.
    env._recipe = (name, dict(render_mode=render_mode, action_mask=action_mask, departed_actions=departed_actions,
                              unknown_options=unknown_options, **kwargs))
    return env


def _rebuild(name, kwargs):
    return make_parallel_env(name, **kwargs)


def _check_render_mode(render_mode):
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be None or one of {list(RENDER_MODES)}, got {render_mode!r}")


def _check_flag(name, value):
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a bool, got {describe(value)}")


def _check_policy(name, value):
    if value not in _POLICIES:
        raise ValueError(f"{name} must be one of {list(_POLICIES)}, got {value!r}")


class MarlRenderParallelEnv(pettingzoo.ParallelEnv):
    """One world of a ``BatchedEnv`` (num_worlds=1, autoreset=False) as a PettingZoo ParallelEnv.

    See the module docstring. ``core`` is the wrapped BatchedEnv; the env owns it and
    closes it in ``close()``."""

    metadata = {"name": "marl_render", "render_modes": list(RENDER_MODES), "is_parallelizable": True}
    _recipe = None  # (name, make_parallel_env kwargs) when built by make_parallel_env

    def __reduce__(self):
        if self._recipe is None:
            raise TypeError("only envs built by make_parallel_env can be pickled (they are rebuilt from their "
                            "configuration; GL state itself cannot be copied)")
        name, kwargs = self._recipe
        return _rebuild, (name, kwargs)

    def __init__(self, env, *, render_mode: str | None = None, action_mask: bool = False,
                 departed_actions: str = "raise", unknown_options: str = "raise"):
        from marl_render.envs.core import BatchedEnv

        if not isinstance(env, BatchedEnv):
            raise TypeError(f"env must be a marl_render BatchedEnv (see marl_render.envs.make_env), "
                            f"got {describe(env)}")
        if env.num_worlds != 1:
            raise ValueError(f"env must have num_worlds=1 for PettingZoo (one world per env), got {env.num_worlds}")
        if env.autoreset:
            raise ValueError("env must be built with autoreset=False: the PettingZoo env resets only in reset()")
        if env.closed:
            raise ValueError("env is closed")
        _check_render_mode(render_mode)
        _check_flag("action_mask", action_mask)
        _check_policy("departed_actions", departed_actions)
        _check_policy("unknown_options", unknown_options)
        if action_mask and env.continuous:
            raise ValueError("action_mask=True needs a discrete env (continuous=False); "
                             "continuous actions have no mask")

        self.core = env
        self.render_mode = render_mode
        self.departed_actions = departed_actions
        self.unknown_options = unknown_options
        self.metadata = {**type(self).metadata, "name": env.name}
        self.possible_agents = list(env.agent_names)
        self.agents: list[str] = []
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}
        self._obs_keys = tuple(k for k in env.obs_keys if k != "action_mask" or action_mask)
        self._dict_obs = self._obs_keys != ("pixels",)

        H, W = env.resolution
        keys, far, state_dim, num_actions = self._obs_keys, float(env.far), env.state_dim, env.num_actions
        channels = env.pixel_channels

        def make_obs_space():
            if not self._dict_obs:
                return spaces.Box(0, 255, (H, W, channels), np.uint8)
            parts = {"pixels": spaces.Box(0, 255, (H, W, channels), np.uint8)}
            if "depth" in keys:
                parts["depth"] = spaces.Box(0.0, far, (H, W), np.float32)
            if "state" in keys:
                parts["state"] = spaces.Box(-np.inf, np.inf, (state_dim,), np.float32)
            if "action_mask" in keys:
                parts["action_mask"] = spaces.MultiBinary(num_actions)
            return spaces.Dict(parts)

        def make_action_space():
            if env.continuous:
                return spaces.Box(-1.0, 1.0, (env.action_dim,), np.float32)
            return spaces.Discrete(env.num_actions)

        # One space object per agent (seeding one agent's space must not affect another's).
        self.observation_spaces = {agent: make_obs_space() for agent in self.possible_agents}
        self.action_spaces = {agent: make_action_space() for agent in self.possible_agents}
        self._pixels = None  # uint8 [A, H, W, 3] of the last reset / step, for render()

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent):
        try:
            return self.observation_spaces[agent]
        except (KeyError, TypeError):
            raise AgentKeyError(f"unknown agent {agent!r}; possible_agents: {self.possible_agents}") from None

    def action_space(self, agent):
        try:
            return self.action_spaces[agent]
        except (KeyError, TypeError):
            raise AgentKeyError(f"unknown agent {agent!r}; possible_agents: {self.possible_agents}") from None

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, options: dict | None = None):
        """(observations, infos) of a new episode; `seed` re-seeds the core's generator."""
        self._check_options(options)
        obs = self.core.reset(seed=seed)  # validates seed before changing anything
        self.agents = [a for a, alive in zip(self.possible_agents, self.core.alive[0].tolist()) if alive]
        observations = self._observations(obs, self.agents)
        return observations, {agent: {} for agent in self.agents}

    def step(self, actions: dict):
        """(observations, rewards, terminations, truncations, infos) of the agents that were
        in the episode before this step; agents that are done are then removed from ``agents``."""
        if self.core.closed:
            raise RuntimeError("this environment is closed; create a new one")
        if self._pixels is None:
            raise RuntimeError("call reset() before step()")
        if not self.agents:
            raise RuntimeError("the episode is over (every agent is done, agents == []); "
                               "call reset() to start a new one")
        batch = self._actions_tensor(actions)
        obs, reward, terminated, truncated, info = self.core.step(batch)
        acting = self.agents
        rew = reward[0].tolist()
        term = terminated[0].tolist()
        trunc = truncated[0].tolist()
        observations = self._observations(obs, acting)
        rewards, terminations, truncations, infos = {}, {}, {}, {}
        world_info = _world_info(info, len(self.possible_agents))
        for agent in acting:
            i = self._index[agent]
            rewards[agent] = float(rew[i])
            terminations[agent] = bool(term[i])
            truncations[agent] = bool(trunc[i])
            infos[agent] = {k: v(i) for k, v in world_info.items()}
        self.agents = [a for a in acting if not (terminations[a] or truncations[a])]
        return observations, rewards, terminations, truncations, infos

    def render(self):
        """uint8 [H, W, 3]: every agent's last view (upscaled) and the overview, side by side.

        Returns None (with a warning) when the env was built with render_mode=None."""
        if self.render_mode is None:
            gymnasium.logger.warn("You are calling render() without a render_mode; pass "
                                  "render_mode='rgb_array' to make_parallel_env.")
            return None
        if self._pixels is None:
            raise RuntimeError("call reset() before render()")
        overview = self.core.render_overview()[0].cpu().numpy()
        views = self._pixels if self._pixels.shape[-1] == 3 else self._pixels.repeat(3, axis=-1)  # gray
        return tile_views(list(views), overview)

    def close(self):
        self.core.close()

    def __repr__(self):
        return f"MarlRenderParallelEnv({self.core!r}, render_mode={self.render_mode!r})"

    # ------------------------------------------------------------------ internals
    def _check_options(self, options):
        if options is None:
            return
        if not isinstance(options, dict):
            raise TypeError(f"options must be None or a dict, got {describe(options)}")
        unknown = sorted(map(repr, set(options) - KNOWN_OPTIONS))
        if unknown and self.unknown_options == "raise":
            raise ValueError(f"unknown reset option(s) {', '.join(unknown)} in options; known options: "
                             f"{sorted(KNOWN_OPTIONS)}. Build the env with unknown_options='ignore' to ignore "
                             f"them (pettingzoo.test.parallel_api_test passes options={{'options': 1}})")

    def _actions_tensor(self, actions) -> torch.Tensor:
        """Checks the actions dict and returns the core's [1, A(, d)] action tensor."""
        if not isinstance(actions, dict):
            raise TypeError(f"actions must be a dict {{agent: action}} for the agents {self.agents}, "
                            f"got {describe(actions)}")
        live = set(self.agents)
        for agent in actions:
            if agent in live:
                continue
            if agent in self._index:
                if self.departed_actions == "ignore":
                    continue
                raise AgentKeyError(f"actions has an action for agent {agent!r}, which has left the episode "
                                    f"(terminated or truncated); give actions only for env.agents = {self.agents} "
                                    f"(or build the env with departed_actions='ignore')")
            raise AgentKeyError(f"actions has an action for unknown agent {agent!r}; "
                                f"possible_agents: {self.possible_agents}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise AgentKeyError(f"actions is missing an action for agent(s) {missing}; every agent in "
                                f"env.agents = {self.agents} must act")
        core = self.core
        if core.continuous:
            batch = torch.zeros(1, core.num_agents, core.action_dim, dtype=torch.float32)
            for agent in self.agents:
                batch[0, self._index[agent]] = torch.from_numpy(_continuous_action(agent, actions[agent],
                                                                                   core.action_dim))
        else:
            batch = torch.zeros(1, core.num_agents, dtype=torch.int64)
            for agent in self.agents:
                batch[0, self._index[agent]] = _discrete_action(agent, actions[agent], core.num_actions)
        return batch

    def _observations(self, obs: dict, agents) -> dict:
        arrays = {key: obs[key][0].cpu().numpy() for key in self._obs_keys}  # [A, ...]
        if "action_mask" in arrays:
            arrays["action_mask"] = arrays["action_mask"].astype(np.int8)
        self._pixels = arrays["pixels"]
        if not self._dict_obs:
            pixels = arrays["pixels"]
            return {agent: pixels[self._index[agent]] for agent in agents}
        return {agent: {key: value[self._index[agent]] for key, value in arrays.items()} for agent in agents}


def _world_info(info: dict, num_agents: int) -> dict:
    """{key: f(agent_index) -> value} of world 0 of the core's info; done_worlds is dropped
    (it is all of terminations | truncations)."""
    out = {}
    for key, value in info.items():
        if key == "done_worlds":
            continue
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        if isinstance(value, np.ndarray) and value.ndim >= 1 and value.shape[0] == 1:
            value = value[0]
            if value.ndim >= 1 and value.shape[0] == num_agents:  # per agent [A, ...]
                out[key] = functools.partial(_per_agent, value)
                continue
        out[key] = functools.partial(_constant, _python(value))
    return out


def _python(value):
    if isinstance(value, np.ndarray) and value.ndim == 0:
        return value.item()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _constant(value, _index):
    return value


def _per_agent(value, index):
    return _python(value[index])


def _tensor_to_numpy(agent, action: torch.Tensor, want: str) -> np.ndarray:
    """A tensor action as numpy, or ActionTypeError naming the agent (meta, sparse, bfloat16...)."""
    if action.device.type == "meta" or action.layout != torch.strided or action.is_complex():
        raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}")
    if action.dtype not in (torch.float16, torch.float32, torch.float64) and action.is_floating_point():
        action = action.float()  # bfloat16 / float8 have no numpy twin
    return action.detach().cpu().numpy()


def _discrete_action(agent, action, n: int) -> int:
    want = f"an int in [0, {n}) (Discrete({n}))"
    value = action
    if isinstance(value, torch.Tensor):
        value = _tensor_to_numpy(agent, value, want)
    if isinstance(value, np.ndarray) and value.shape in ((), (1,)):
        value = value.reshape(())[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}")
    if not 0 <= int(value) < n:
        raise ValueError(f"actions[{agent!r}] must be {want}, got {int(value)}")
    return int(value)


def _continuous_action(agent, action, d: int) -> np.ndarray:
    want = f"a float array of shape ({d},) in [-1, 1] (Box(-1, 1, ({d},), float32))"
    if isinstance(action, torch.Tensor):
        array = _tensor_to_numpy(agent, action, want)
    elif isinstance(action, (np.ndarray, list, tuple, float, int, np.number)) and \
            not isinstance(action, (bool, np.bool_)):
        try:
            array = np.asarray(action)
        except (TypeError, ValueError):
            raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}") from None
    else:
        raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}")
    if array.dtype.kind not in "fiu":
        raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}")
    if array.shape == () and d == 1:
        array = array.reshape(1)
    if array.shape != (d,):
        raise ValueError(f"actions[{agent!r}] must be {want}, got shape {array.shape}")
    array = array.astype(np.float32)
    if not np.isfinite(array).all():
        raise ValueError(f"actions[{agent!r}] must be {want}, got non-finite values {array.tolist()}")
    if (np.abs(array) > 1).any():
        raise ValueError(f"actions[{agent!r}] must be {want}, got {array.tolist()} (clip them first)")
    return array


def tile_views(views: list, overview: np.ndarray | None = None) -> np.ndarray:
    """One uint8 image: the agent views (upscaled by an integer factor towards the overview's
    height, nearest neighbour) and then the overview, left to right, 2 px gaps."""
    tiles = list(views)
    if overview is not None:
        H = views[0].shape[0] if views else overview.shape[0]
        scale = max(1, overview.shape[0] // H)
        tiles = [np.repeat(np.repeat(v, scale, 0), scale, 1) for v in views] + [overview]
    height = max(t.shape[0] for t in tiles)
    width = sum(t.shape[1] for t in tiles) + _GAP * (len(tiles) - 1)
    canvas = np.full((height, width, 3), _GAP_COLOR, dtype=np.uint8)
    x = 0
    for tile in tiles:
        canvas[:tile.shape[0], x:x + tile.shape[1]] = tile
        x += tile.shape[1] + _GAP
    return canvas


__all__ = ["MarlRenderParallelEnv", "make_parallel_env", "ActionTypeError", "AgentKeyError", "tile_views",
           "KNOWN_OPTIONS", "RENDER_MODES"]
