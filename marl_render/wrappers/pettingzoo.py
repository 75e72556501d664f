"""PettingZoo front end: one world of a BatchedEnv as a ``pettingzoo.ParallelEnv``::

    from marl_render.wrappers.pettingzoo import make_parallel_env
    env = make_parallel_env("spread", resolution=32, render_mode="rgb_array")
    obs, infos = env.reset(seed=0)           # obs[agent]: uint8 [H, W, 3]
    while env.agents:
        actions = {a: env.action_space(a).sample() for a in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)
    frame = env.render()                     # every agent's view + the overview, side by side
    env.close()

With default arguments it passes PettingZoo's ``parallel_api_test``, ``parallel_seed_test``
and (through ``parallel_to_aec``) ``render_test``.

Spaces (the same for every agent):

* observation: ``Box(0, 255, (H, W, 3), uint8)`` (1 channel with ``grayscale=True``) when the core
  yields only pixels (the default). With ``depth=True``, ``state_obs=True``, ``lidar=rays`` or
  ``action_mask=True`` it is a ``Dict`` with "pixels", "depth" (``Box(0, far, (H, W), float32)``:
  metres, clamped at the camera's far plane), "state" (``Box(-inf, inf, (state_dim,), float32)``),
  "lidar" (``Box(0, 1, (rays,), float32)``, arena tasks: envs/sight.py) and
  "action_mask" (``MultiBinary(num_actions)``, int8: the dtype gymnasium's
  ``Discrete.sample(mask=...)`` requires). Discrete cores always compute an action mask;
  it is exposed only when asked for with ``action_mask=True`` so that the common
  pixels-only case stays a plain Box (what image wrappers such as supersuit's expect).
  Observations are arrays the caller owns: writing into them changes nothing in the env.
* action: ``Discrete(num_actions)`` or ``Box(-1, 1, (action_dim,), float32)``.
* global state for centralised critics: ``state()`` is float32 ``[A * state_dim]``, every
  agent's state observation (the env's ``state_obs``, see its docstring) in
  ``possible_agents`` order, as PettingZoo's MPE envs concatenate their agents'
  observations; ``state_space`` is ``Box(-inf, inf, (A * state_dim,), float32)``. Agents
  that left the episode keep their rows (they describe where the agent left).

Episode semantics follow PettingZoo: ``agents`` holds the agents still in the episode; an
agent that leaves (caught prey, time limit) appears once more in the returned dicts with
terminated / truncated True and is then gone; when every agent is done ``agents == []``
and ``reset()`` starts a new episode. The core is built with ``autoreset=False``.

Infos: ``reset`` returns ``{agent: {}}``; ``step`` returns, per agent, the core's info
entries of this world as Python scalars (or numpy arrays): ``step_count`` and the env's
own statistics of the step (spread's ``collisions`` and ``coverage``, forage's ``collected``
and ``team_score``, tag's ``caught`` and ``prey_left``, push's ``goal``).

Levels (built with ``levels=``, envs/levels.py): ``reset(options={"level": k})`` starts level k
(an int in [0, 2**62); the core's ``reset_to_level``), ``reset()`` one the level sampler picks;
infos (reset's too) then carry ``level``, the level being played.

Rendering (``render_mode``): ``"rgb_array"``: ``render()`` returns uint8 [H, W, 3], every
agent's last view (upscaled) and the top-down overview side by side. ``"human"``: that
frame is shown in a matplotlib window after every ``reset`` and ``step`` (and by
``render()``, which returns None), paced at ``metadata["render_fps"]`` = 1 / the env's
simulated seconds per step (10 for the arena envs, 100 for cartpole). Where no window can
be opened (a headless machine) the first frame gives one warning and nothing is shown.

``black_death=True`` keeps the agent set fixed for vectorising wrappers that need one
(supersuit's ``pettingzoo_env_to_vec_env_v1``): an agent that leaves before its world's
episode ends (tag's caught prey) stays in ``agents``, sees zeros (not the action mask) with
reward 0 and is neither terminated nor truncated, its actions ignored, until the episode
ends for every agent at once (then ``agents == []`` as usual). It changes nothing in envs
whose agents never leave.

Input checks (every call checks all of its input before it changes anything):

* ``step(actions)``: a dict with one action for every agent in ``agents``. Unknown agent
  names raise KeyError; a missing action raises KeyError. Actions for agents that already
  left are ignored (torchrl's ``PettingZooWrapper(use_mask=True)`` sends an action for every
  agent, alive or not); ``departed_actions="raise"`` makes them a KeyError. A wrongly typed
  action raises ``ActionTypeError`` (a TypeError and a ValueError): a discrete action must
  be an integer (Python, numpy or torch, 0-d or shape (1,)), a continuous one a float array
  (integer arrays are refused, as the core refuses them). Out-of-range, NaN or wrongly
  shaped actions raise ValueError; a continuous action is checked in its own precision
  before it is converted to float32 (float64 ``1.00000001`` is out of range, not 1.0).
  Every message names the agent.
* ``reset(seed, options)``: ``options`` must be None or a dict. This env knows the key
  "level" and ignores unknown ones, as PettingZoo and gymnasium envs do
  (``parallel_api_test`` passes ``options={"options": 1}``), with one UserWarning per env for
  an unknown key close to a known one (``"levle"``: a typo, not a key of another tool);
  ``unknown_options="raise"`` makes them a ValueError.
"""
from __future__ import annotations

import difflib
import functools
import warnings

import gymnasium
import numpy as np
import pettingzoo
import torch
from gymnasium import spaces
from pettingzoo.utils.conversions import parallel_to_aec_wrapper
from pettingzoo.utils.wrappers import OrderEnforcingWrapper

from marl_render.envs.levels import check_level_ids
from marl_render.envs.registry import make_env
from marl_render.validation import describe
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
from marl_render.wrappers.window import Window

RENDER_MODES = ("human", "rgb_array")
KNOWN_OPTIONS: frozenset = frozenset({"level"})  # reset(options=...) keys this env understands
_POLICIES = ("raise", "ignore")  # the default is "ignore"; the strict "raise" is opt-in
_GAP = 2  # pixels between the tiles of render()
_GAP_COLOR = 40


class ActionTypeError(TypeError, ValueError):
    """An action of the wrong type (e.g. a float for a Discrete space); both a TypeError and a ValueError."""


class AgentKeyError(KeyError):
    """KeyError about an agent name, printed without KeyError's extra quotes."""

    def __str__(self):
        return str(self.args[0]) if self.args else ""


def make_parallel_env(name, *, render_mode: str | None = None, action_mask: bool = False,
                      departed_actions: str = "ignore", unknown_options: str = "ignore",
                      black_death: bool = False, **kwargs) -> MarlRenderParallelEnv:
    """A PettingZoo ParallelEnv of the registered environment `name` (or a Scenario subclass), one world.

    kwargs go to ``marl_render.envs.registry.make_env`` (resolution, num_agents, max_steps,
    continuous, state_obs, depth, seed, device and the env's own arguments); num_worlds
    (always 1) and autoreset (always False) are set here and may not be passed."""
    refuse_num_processes("make_parallel_env", kwargs)
    for key in ("num_worlds", "autoreset"):
        if key in kwargs:
            raise TypeError(f"make_parallel_env() does not accept {key!r}: a PettingZoo env is one world "
                            f"(num_worlds=1) and resets only when reset() is called (autoreset=False); "
                            f"use make_torchrl_env or marl_render.envs.make_env for batched worlds")
    # Check the wrapper's own arguments before building the (GL-backed) core.
    _check_arguments(render_mode, action_mask, departed_actions, unknown_options, black_death)
    with closed_on_error(make_env(name, num_worlds=1, **kwargs)) as core:
        env = MarlRenderParallelEnv(core, render_mode=render_mode, action_mask=action_mask,
                                    departed_actions=departed_actions, unknown_options=unknown_options,
                                    black_death=black_death)
    # How to build this env again: pickling (vectorising wrappers copy envs that way) makes
    # a fresh env of the same configuration in the receiving process, not a GL state copy. The
    # task goes by its Scenario class (module and name), so a worker that never called
    # register_env rebuilds a user's task too.
    env._recipe = (type(core.scenario), dict(render_mode=render_mode, action_mask=action_mask,
                                             departed_actions=departed_actions, unknown_options=unknown_options,
                                             black_death=black_death, **kwargs))
    return env


def make_aec_env(name: str, **kwargs) -> pettingzoo.AECEnv:
    """A PettingZoo AECEnv of the registered environment `name`, one world: the agents act in
    turn (PettingZoo's ``parallel_to_aec`` of ``make_parallel_env(name, **kwargs)``; the world
    steps once every live agent has acted). kwargs as make_parallel_env's."""
    return OrderEnforcingWrapper(_CheckedAEC(make_parallel_env(name, **kwargs)))


class _CheckedAEC(parallel_to_aec_wrapper):
    """PettingZoo's parallel_to_aec, refusing a bad action when its agent gives it: the plain
    wrapper stores it, and the last agent's turn then raises for it, every turn, until a reset."""

    def step(self, action):
        agent = self.agent_selection
        if not (self.terminations[agent] or self.truncations[agent]):
            self.env.check_action(agent, action)
        super().step(action)


def _rebuild(name, kwargs):
    return make_parallel_env(name, **kwargs)


def _check_arguments(render_mode, action_mask, departed_actions, unknown_options, black_death):
    check_render_mode(render_mode, RENDER_MODES)
    check_flag("action_mask", action_mask)
    _check_policy("departed_actions", departed_actions)
    _check_policy("unknown_options", unknown_options)
    check_flag("black_death", black_death)


def _check_policy(name, value):
    if value not in _POLICIES:
        raise ValueError(f"{name} must be one of {list(_POLICIES)}, got {value!r}")


class MarlRenderParallelEnv(pettingzoo.ParallelEnv):
    """One world of a ``BatchedEnv`` (num_worlds=1, autoreset=False) as a PettingZoo ParallelEnv.

    See the module docstring. ``core`` is the wrapped BatchedEnv; the env owns it and
    closes it in ``close()``."""

    metadata = {"name": "marl_render", "render_modes": list(RENDER_MODES), "is_parallelizable": True}
    _recipe = None  # (Scenario subclass, make_parallel_env kwargs) when built by make_parallel_env

    def __reduce__(self):
        if self._recipe is None:
            raise TypeError("only envs built by make_parallel_env can be pickled (they are rebuilt from their "
                            "configuration; GL state itself cannot be copied)")
        name, kwargs = self._recipe
        return _rebuild, (name, kwargs)

    def __init__(self, env, *, render_mode: str | None = None, action_mask: bool = False,
                 departed_actions: str = "ignore", unknown_options: str = "ignore", black_death: bool = False):
        check_core(env, no_autoreset="the PettingZoo env resets only in reset()")
        if env.num_worlds != 1:
            raise ValueError(f"env must have num_worlds=1 for PettingZoo (one world per env), got {env.num_worlds}")
        _check_arguments(render_mode, action_mask, departed_actions, unknown_options, black_death)
        self._obs_keys = observation_keys(env, action_mask)
        self._dict_obs = self._obs_keys != ("pixels",)

        self.core = env
        self.render_mode = render_mode
        self.departed_actions = departed_actions
        self.unknown_options = unknown_options
        self._warned_options: set = set()  # near-misses of a known reset option already warned about
        self.black_death = bool(black_death)
        self.metadata = {**type(self).metadata, "name": env.name, "render_fps": 1.0 / env.dt}
        self.possible_agents = list(env.agent_names)
        self.agents: list[str] = []
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}

        # One space object per agent (seeding one agent's space must not affect another's).
        self.observation_spaces = {agent: spaces_from_spec.observation_space(env.spec, self._obs_keys)
                                   for agent in self.possible_agents}
        self.action_spaces = {agent: spaces_from_spec.action_space(env.spec) for agent in self.possible_agents}
        state_dim = env.state_dim
        if state_dim:  # envs without a state observation keep ParallelEnv's state() (NotImplementedError)
            self.state_space = spaces.Box(-np.inf, np.inf, (len(self.possible_agents) * state_dim,), np.float32)
        self._started = False  # reset() was called
        self._views = None  # uint8 [A, H, W, 3]: render()'s own copy of the last views (rendering modes only)
        self._window = Window(f"marl_render {env.name}", self.metadata["render_fps"]) \
            if render_mode == "human" else None

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
        level = self._level_option(options)
        obs = reset_core(self.core, seed, levels=level, full=True)  # the core checks seed before changing anything
        self._started = True
        self.agents = [a for a, alive in zip(self.possible_agents, self.core.alive[0].tolist(), strict=True) if alive]
        observations = self._observations(obs, self.agents)
        if self.render_mode == "human":
            self.render()
        info = {} if self.core.levels is None else {"level": int(self.core.level_ids[0])}
        return observations, {agent: dict(info) for agent in self.agents}

    def _level_option(self, options) -> torch.Tensor | None:
        """options["level"] as the core's level_ids [1], checked; None if not given."""
        if options is None or "level" not in options:
            return None
        require_levels(self.core, "options['level']")
        level = options["level"]
        if isinstance(level, (bool, np.bool_)) or not isinstance(level, (int, np.integer)):
            raise TypeError(f"options['level'] must be an int level id, got {describe(level)}")
        return check_level_ids("options['level']", torch.tensor([int(level)]), 1)

    def step(self, actions: dict):
        """(observations, rewards, terminations, truncations, infos) of the agents that were
        in the episode before this step; agents that are done are then removed from ``agents``."""
        self._check_started("step()")
        if not self.agents:
            raise RuntimeError("the episode is over (every agent is done, agents == []); "
                               "call reset() to start a new one")
        batch = self._actions_tensor(actions)
        obs, reward, terminated, truncated, info = self.core.step(batch)
        acting = self.agents
        rew = reward[0].tolist()
        term = terminated[0].tolist()
        trunc = truncated[0].tolist()
        if self.black_death and not all(t or u for t, u in zip(term, trunc, strict=True)):
            # A fixed agent set until the world's episode ends: those that left stay in `agents`,
            # seeing zeros with reward 0 (the core's), not done; their actions are ignored.
            departed = ~self.core.alive[0]
            for key in self._obs_keys:
                if key != "action_mask":
                    obs[key][0][departed] = 0
            term = [t and not d for t, d in zip(term, departed.tolist(), strict=True)]
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
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """float32 [A * state_dim]: every agent's state observation, in possible_agents order."""
        if not self.core.state_dim:
            return super().state()  # NotImplementedError: this env has no state observation
        self._check_started("state()")
        state = self.core.state_observation()[0].detach()
        return state.to(device="cpu", dtype=torch.float32).reshape(-1).numpy()

    def render(self):
        """In "rgb_array" mode uint8 [H, W, 3]: every agent's last view (upscaled) and the overview
        side by side. In "human" mode that frame is shown in a window and None is returned.
        Returns None (with a warning) when the env was built with render_mode=None."""
        if self.render_mode is None:
            gymnasium.logger.warn("You are calling render() without a render_mode; pass "
                                  "render_mode='rgb_array' to make_parallel_env.")
            return None
        self._check_started("render()")
        if self.render_mode == "human":
            if self._window.available():  # on a headless machine: one warning, nothing rendered
                self._window.show(self._frame())
            return None
        return self._frame()

    def close(self):
        if self._window is not None:
            self._window.close()
        self.core.close()

    def __repr__(self):
        return f"MarlRenderParallelEnv({self.core!r}, render_mode={self.render_mode!r})"

    # ------------------------------------------------------------------ internals
    def _check_started(self, call: str):
        if self.core.closed:
            raise RuntimeError("this environment is closed; create a new one")
        if not self._started:
            raise RuntimeError(f"call reset() before {call}")

    def _check_options(self, options):
        if options is None:
            return
        if not isinstance(options, dict):
            raise TypeError(f"options must be None or a dict, got {describe(options)}")
        unknown = sorted(map(repr, set(options) - KNOWN_OPTIONS))
        if unknown and self.unknown_options == "raise":
            raise ValueError(f"unknown reset option(s) {', '.join(unknown)} in options; known options: "
                             f"{sorted(KNOWN_OPTIONS)} (this env was built with unknown_options='raise'; "
                             f"the default 'ignore' ignores them)")
        for key in sorted(set(options) - KNOWN_OPTIONS - self._warned_options, key=repr):
            close = difflib.get_close_matches(key, KNOWN_OPTIONS, n=1, cutoff=0.75) if isinstance(key, str) else []
            if close:
                self._warned_options.add(key)
                warnings.warn(f"reset option {key!r} is not one this env knows; did you mean {close[0]!r}? It is "
                              f"ignored (PettingZoo's convention for unknown options; unknown_options='raise' makes "
                              f"it an error)", UserWarning, stacklevel=3)

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
                                    f"(this env was built with departed_actions='raise'; the default 'ignore' "
                                    f"ignores them)")
            raise AgentKeyError(f"actions has an action for unknown agent {agent!r}; "
                                f"possible_agents: {self.possible_agents}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise AgentKeyError(f"actions is missing an action for agent(s) {missing}; every agent in "
                                f"env.agents = {self.agents} must act")
        core = self.core
        # Agents that left keep the value 0, which the core ignores (it must still be valid).
        rows = np.zeros((core.num_agents, core.action_dim) if core.continuous else core.num_agents,
                        np.float32 if core.continuous else np.int64)
        for agent in self.agents:
            rows[self._index[agent]] = self.check_action(agent, actions[agent])
        return torch.from_numpy(rows)[None]

    def check_action(self, agent, action):
        """`agent`'s action as the core takes it, or ActionTypeError naming the agent (the AEC env
        checks each action when it is given, not when the last agent's turn steps the world)."""
        convert = _continuous_action if self.core.continuous else _discrete_action
        return convert(agent, action, self.action_spaces[agent])

    def _observations(self, obs: dict, agents) -> dict:
        arrays = numpy_observations(obs, self._obs_keys, _first_world)  # [A, ...], fresh memory every call
        if self.render_mode is not None:  # render() keeps its own copy: writing into an observation changes nothing
            self._views = arrays["pixels"].copy()
        if not self._dict_obs:
            pixels = arrays["pixels"]
            return {agent: pixels[self._index[agent]] for agent in agents}
        return {agent: {key: value[self._index[agent]] for key, value in arrays.items()} for agent in agents}

    def _frame(self) -> np.ndarray:
        overview = self.core.render_overview()[0].cpu().numpy()
        views = self._views if self._views.shape[-1] == 3 else self._views.repeat(3, axis=-1)  # gray
        return tile_views(list(views), overview)


def _first_world(tensor: torch.Tensor) -> np.ndarray:
    return tensor[0].cpu().numpy()


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
    """A tensor action as numpy, or ActionTypeError naming the agent (meta, sparse, complex...)."""
    if action.device.type == "meta" or action.layout != torch.strided or action.is_complex():
        raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}")
    if action.is_floating_point() and action.dtype not in (torch.float16, torch.float32, torch.float64):
        action = action.float()  # bfloat16 / float8 have no numpy twin; float32 holds their values exactly
    return action.detach().cpu().numpy()


def _discrete_action(agent, action, space: spaces.Discrete) -> int:
    """An integer action (Python, numpy or torch; 0-d or shape (1,)) that `space` contains."""
    n = int(space.n)
    want = f"an int in [0, {n}) (Discrete({n}))"
    value = action
    if isinstance(value, torch.Tensor):
        value = _tensor_to_numpy(agent, value, want)
    if isinstance(value, np.ndarray) and value.shape in ((), (1,)):
        value = value.reshape(())[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}")
    value = int(value)  # exact for every integer dtype, so Discrete.contains sees the value as given
    if not space.contains(value):
        raise ValueError(f"actions[{agent!r}] must be {want}, got {value}")
    return value


def _continuous_action(agent, action, space: spaces.Box) -> np.ndarray:
    """A float action of `space`'s shape within its bounds, checked in the action's own precision
    and only then converted to float32 (float64 1.00000001 is out of range, not rounded to 1.0).

    gymnasium's ``Box.contains`` is not used here: it refuses float64 arrays outright (they
    cannot be cast to float32 safely), and users' numpy actions are often float64."""
    d = space.shape[0]
    want = f"a float array of shape ({d},) in [-1, 1] (Box(-1, 1, ({d},), float32))"
    if isinstance(action, torch.Tensor):
        array = _tensor_to_numpy(agent, action, want)
    elif isinstance(action, (np.ndarray, np.floating, float, list, tuple)):
        try:
            array = np.asarray(action)
        except (TypeError, ValueError):
            raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}") from None
    else:
        raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}")
    if array.dtype.kind != "f":  # integers are refused, as the core refuses them, not converted
        raise ActionTypeError(f"actions[{agent!r}] must be {want}, got {describe(action)}")
    if array.shape == () and d == 1:
        array = array.reshape(1)
    if array.shape != (d,):
        raise ValueError(f"actions[{agent!r}] must be {want}, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"actions[{agent!r}] must be {want}, got non-finite values {array.tolist()}")
    if (array < space.low).any() or (array > space.high).any():
        raise ValueError(f"actions[{agent!r}] must be {want}, got {array.tolist()} (clip them first)")
    return array.astype(np.float32)


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


__all__ = ["MarlRenderParallelEnv", "make_aec_env", "make_parallel_env", "ActionTypeError", "AgentKeyError",
           "tile_views", "KNOWN_OPTIONS", "RENDER_MODES"]
