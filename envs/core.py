"""The batched environment core: W worlds x A agents, stepped and rendered as one batch.

Every environment of the suite subclasses ``BatchedEnv``. The core owns everything that
is the same for all of them: argument checks, seeding, step counters, the alive mask,
truncation, auto-reset, the renderer(s) and the observation dict. A subclass writes
only its world: state tensors, a reset, a step, a scene and the instance poses.

Data contract (W worlds, A agents, H x Wpx pixels)::

    obs = env.reset(seed=0)          # dict of tensors, all [W, A, ...]
      "pixels"       uint8   [W, A, H, Wpx, C]   always; C = 3, or 1 with grayscale=True (BT.601
                                                  luma drawn by the renderer, a third of the
                                                  bytes read back)
      "depth"        float32 [W, A, H, Wpx]      depth=True (metres along the view axis;
                                                  background = the camera's far plane)
      "state"        float32 [W, A, state_dim]   state_obs=True
      "action_mask"  bool    [W, A, num_actions] discrete envs (all True where no action
                                                  can be invalid)
    obs, reward, terminated, truncated, info = env.step(actions)
      actions: discrete  integer [W, A] in [0, num_actions)
               continuous float  [W, A, action_dim] in [-1, 1]
      reward float32 [W, A]; terminated, truncated bool [W, A]
      info: "step_count" int64 [W] (steps of the episode just stepped),
            "done_worlds" bool [W] (every agent terminated or truncated), plus the env's
            own ``info_keys`` (episode statistics, each [W] of the declared dtype).

Agents that left the episode (``alive`` False, e.g. caught prey) stay in every tensor:
their actions are ignored (they must still be valid values, e.g. 0), their reward is 0
and they are reported terminated until their world is reset. ``truncated`` is True for
the agents still alive when the world's step count reaches ``max_steps``.

Auto-reset (the ``autoreset`` keyword) follows gymnasium 1.x's vector autoreset modes,
per world (a world is done when every agent is terminated or truncated):

* ``False`` (the default): nothing resets inside ``step``; done worlds keep stepping
  (their agents reported terminated / truncated) until ``reset`` or ``reset_worlds``.
* ``"next_step"`` (gymnasium's ``AutoresetMode.NEXT_STEP``, its default): the step that
  ends an episode returns that episode's final obs. The *next* step resets those worlds
  instead of stepping them: their actions are ignored (they must still be valid values),
  their obs are the first obs of the new episode, reward 0, terminated and truncated
  False, ``info["step_count"]`` 0. One render per step.
* ``"same_step"`` (``AutoresetMode.SAME_STEP``): the step that ends an episode resets
  those worlds at its end. The returned obs are the first obs of the new episode;
  reward / terminated / truncated / info describe the step that ended the episode, and
  ``info["final_obs"]`` holds the obs that step produced before the reset (a dict with
  the same keys: the final obs of the ended episode in the done worlds, the returned obs
  elsewhere; the very same dict contents when no world was done). Two renders on a step
  where some world is done (the final frame and the new one), one otherwise.
* ``True`` means ``"same_step"`` (what ``True`` always did, now with the final obs).

With auto-reset on, ``info["autoreset_worlds"]`` bool [W] says which worlds were reset by
this step (their returned obs start a new episode). In ``"next_step"`` mode the env's own
info keys (e.g. spread's ``coverage``) of those worlds describe the discarded step of the
ended episode, taken with all of its agents absent; ignore them there.

Every call validates all of its input before it changes anything, so a rejected call
leaves the state (bodies, counters, RNG) exactly as it was.

Actions (and a reset mask) are detached from autograd where they enter, and the calls run
under ``torch.no_grad()``: a policy output that still requires grad steps the env like
its detached copy, and no tensor the env returns or keeps requires grad.

The batch is checked against this machine's memory before the state and the renderer are
allocated (views, pixels, instances and env state; see marl_render/memory.py): a batch
that cannot fit is a ValueError naming num_worlds, the bytes needed and the bytes
available. ``render_overview`` checks its renderer the same way before it replaces the
previous one. ``device`` is 'cpu' (or 'cpu:0') or a CUDA device; ``torch_threads`` is at
most 1024 (marl_render/threads.py says why).

``get_state`` needs a ``reset()`` first, like ``step``. An env belongs to the process that
made it: in a child forked from that process, ``reset``, ``reset_worlds``, ``step`` and
``render_overview`` raise ForkedContextError before anything changes (``get_state`` still
reads the inherited state).

The state is explicit (envs/state.py): an env's simulation lives in one frozen dataclass of
tensors, ``env.sim``; ``get_state()`` copies it out with the step counters, the alive mask and
the RNG state, and ``set_state(state)`` restores all of it exactly.
"""
from __future__ import annotations

import abc
import dataclasses
import math

import numpy as np
import torch

import marl_render as mr
from marl_render import memory
from marl_render.threads import limited_threads, thread_count
from marl_render.validation import FLOAT_DTYPES, as_tensor, describe, positive_int, resolution_hw, unpicklable

from . import scenery
from . import state as explicit_state

OBS_KEYS = ("pixels", "depth", "state", "action_mask")
STATE_LIMIT = 1e6  # default bound of float state fields in set_state: float32 math on them (squares, sums) stays finite


def _flag(name: str, value) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a bool, got {describe(value)}")
    return bool(value)


def _shadows(value, bounds) -> mr.Shadows | None:
    """None (no shadows) or the Shadows settings of the scene."""
    if isinstance(value, mr.Shadows):
        return value
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"shadows must be a bool or a marl_render.Shadows, got {describe(value)}")
    return mr.Shadows(bounds=bounds) if value else None


AUTORESET_MODES = ("next_step", "same_step")


def _autoreset_mode(value) -> bool | str:
    """False, "next_step" or "same_step"; True means "same_step" (see the module docstring)."""
    want = f"False, True (= 'same_step') or one of {list(AUTORESET_MODES)}"
    if isinstance(value, (bool, np.bool_)):
        return "same_step" if value else False
    if not isinstance(value, str):
        raise TypeError(f"autoreset must be {want}, got {describe(value)}")
    if value not in AUTORESET_MODES:
        raise ValueError(f"autoreset must be {want}, got {value!r}")
    return value


def _seed(name: str, value) -> int | None:
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be None or an int in [0, 2**63), got {describe(value)}")
    if not 0 <= int(value) < 2 ** 63:
        raise ValueError(f"{name} must be None or an int in [0, 2**63), got {value}")
    return int(value)


def _device(value) -> torch.device:
    if not isinstance(value, (str, torch.device)):
        raise TypeError(f"device must be a str or torch.device (e.g. 'cpu', 'cuda:0'), got {describe(value)}")
    try:
        device = torch.device(value)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"device must name a torch device (e.g. 'cpu', 'cuda:0'), got {value!r}") from exc
    if device.type == "cpu":  # torch has one CPU device; tensors made on 'cpu:0' report plain 'cpu'
        if device.index not in (None, 0):
            raise ValueError(f"device must be 'cpu' (torch has a single CPU device) or a CUDA device, got {value!r}")
        return torch.device("cpu")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {value!r} was asked for but torch sees no CUDA device; use device='cpu'")
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be a CPU or CUDA device (e.g. 'cpu', 'cuda:0'), got {value!r}")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise ValueError(f"device {value!r} was asked for but torch sees {torch.cuda.device_count()} CUDA device(s)")
    return device


def _from_user(name: str, value):
    """A tensor the user handed in, cut from its autograd graph (a policy output that was not
    detached would otherwise flow into the state, and through torch.where survive every
    reset); nested, sparse and meta tensors, which have no plain data to read, are a TypeError."""
    if not isinstance(value, torch.Tensor):
        return value
    if value.is_nested or value.layout != torch.strided or value.device.type == "meta":
        kind = "a nested tensor" if value.is_nested else f"layout {value.layout}"
        raise TypeError(f"{name} must be a dense tensor with data, got {kind} on {value.device}")
    return value.detach()


class BatchedEnv(abc.ABC):
    """Abstract base of all environments: see the module docstring for the contract.

    Subclasses set the class attributes below and implement the hooks
    ``_setup`` (which also sets ``sim``, the simulation state: a frozen dataclass of
    tensors), ``_build_scene``, ``_reset_state``, ``_step_state``, ``_instances``,
    ``_state_obs`` (and optionally ``_init_cameras``, ``_action_mask``, ``_overview_camera``).

    Constructor keywords (all keyword-only): num_worlds, num_agents, resolution (int or
    (H, W)), max_steps, continuous, state_obs, depth, shadows (False, True or a
    marl_render.Shadows; True: Shadows(bounds=shadow_bounds)), device, seed, autoreset (False,
    "next_step", "same_step" or True = "same_step"; see the module docstring),
    grayscale (one-channel pixels, `pixel_channels`), torch_threads (default 1, at most
    1024): torch intra-op threads used *inside* env calls (the caller's setting is restored
    on return; None leaves torch's setting alone: see marl_render/threads.py), and context
    (a marl_render.GLContext to render on, which closes the env's renderers when it closes;
    None: the default context shared by the process).

    Attributes: name, num_worlds (W), num_agents (A), agent_names, groups (team ->
    agent names, in agent-index order), resolution (H, W), continuous, num_actions
    (discrete, else None), action_dim (continuous, else None), action_meanings,
    obs_keys, state_dim, max_steps, dt, device, seed, generator, renderer, physics
    (PhysicsConfig or None), physics_terms, sim (the simulation state), alive [W, A] bool,
    step_count [W] int64.
    Methods: reset, reset_worlds, step, check_actions, render_overview, state_observation,
    get_state, set_state, close.
    """

    # ---- declared by each environment
    name: str = "batched_env"
    default_num_agents: int = 1
    agent_range: tuple = (1, 64)  # allowed num_agents (inclusive)
    default_max_steps: int = 100
    default_resolution = 64
    dt: float = 0.1  # simulated seconds per step (a front end plays episodes back at 1 / dt frames/s)
    physics_terms: frozenset = frozenset()  # envs/planar.py terms this env computes
    info_keys: dict = {}  # {name: dtype} of the env's own info entries, each [W], in every step's info
    background: tuple = scenery.SKY_COLOR
    fov_y: float = math.radians(70.0)
    near: float = 0.05
    far: float = 50.0
    arena_half_extent: tuple = (1.5, 1.5)  # used by the default overview camera
    overview_resolution: tuple = (128, 128)
    overview_fov_y: float = math.radians(60.0)
    shadow_bounds = None  # the box shadows=True covers; None: fitted to the static geometry

    def __init__(self, *, num_worlds: int = 1, num_agents: int | None = None, resolution=None,
                 max_steps: int | None = None, continuous: bool = False, state_obs: bool = False,
                 depth: bool = False, shadows=False, device="cpu", seed: int | None = None,
                 autoreset: bool | str = False, torch_threads: int | None = 1, grayscale: bool = False,
                 context: mr.GLContext | None = None):
        self._closed = True  # until fully built: close() and __del__ then do nothing
        self.num_worlds = positive_int("num_worlds", num_worlds)
        low, high = self.agent_range
        num_agents = self.default_num_agents if num_agents is None else num_agents
        if isinstance(num_agents, (bool, np.bool_)) or not isinstance(num_agents, (int, np.integer)):
            raise TypeError(f"num_agents must be an int in [{low}, {high}], got {describe(num_agents)}")
        if not low <= num_agents <= high:
            raise ValueError(f"num_agents must be an int in [{low}, {high}] for {self.name}, got {num_agents}")
        self.num_agents = int(num_agents)
        self.resolution = resolution_hw(self.default_resolution if resolution is None else resolution)
        if context is not None and not isinstance(context, mr.GLContext):
            raise TypeError(f"context must be a marl_render.GLContext or None, got {describe(context)}")
        self.context = mr.backend.context() if context is None else context
        self.context.check_usable()
        gl_limit = self.context.info().max_framebuffer_size
        if max(self.resolution) > gl_limit:
            raise ValueError(f"resolution must be at most {gl_limit} pixels per side (GL limit), got {self.resolution}")
        self.max_steps = positive_int("max_steps", self.default_max_steps if max_steps is None else max_steps)
        if self.max_steps >= 2 ** 63:  # compared with the int64 step counters
            raise ValueError(f"max_steps must be an int in [1, 2**63), got {self.max_steps}")
        self.continuous = _flag("continuous", continuous)
        self.state_obs = _flag("state_obs", state_obs)
        self.depth = _flag("depth", depth)
        self.shadows = _shadows(shadows, self.shadow_bounds)
        self.grayscale = _flag("grayscale", grayscale)
        self.pixel_channels = 1 if self.grayscale else 3
        self.autoreset = _autoreset_mode(autoreset)  # False, "next_step" or "same_step"
        self.device = _device(device)
        self.torch_threads = None if torch_threads is None else thread_count("torch_threads", torch_threads)
        seed = _seed("seed", seed)
        self.seed = int(torch.Generator().seed() % 2 ** 63) if seed is None else seed
        self.generator = torch.Generator().manual_seed(self.seed)
        effects = ("lighting", "depth") if self.depth else ("lighting",)
        effects += ("shadows",) if self.shadows else ()
        # Views and pixels alone, before _setup allocates the state; the whole scene below.
        self._check_memory(mr.Scene(num_worlds=self.num_worlds, agents_per_world=self.num_agents,
                                    resolution=self.resolution, effects=effects))

        # Filled in by _setup().
        self.agent_names: list[str] = [f"agent_{i}" for i in range(self.num_agents)]
        self.groups: dict[str, list[str]] = {"agents": list(self.agent_names)}
        self.num_actions: int | None = None
        self.action_dim: int | None = None
        self.action_meanings: tuple | None = None  # discrete: a short name per action
        self.state_dim: int = 0
        self.physics = None  # PhysicsConfig of envs that use envs/planar.py
        self.sim = None  # the simulation state, a frozen dataclass of tensors (envs/state.py)
        self.context.check_usable()  # in a forked child: ForkedContextError now, not a torch deadlock in _setup
        self._setup()
        self._check_setup()

        self.obs_keys = tuple(k for k, on in (("pixels", True), ("depth", self.depth), ("state", self.state_obs),
                                              ("action_mask", not self.continuous)) if on)
        W, A = self.num_worlds, self.num_agents
        self.alive = torch.ones(W, A, dtype=torch.bool, device=self.device)
        self.step_count = torch.zeros(W, dtype=torch.int64, device=self.device)
        self._needs_reset = True
        self._overview = None
        scene = self._make_scene(overview=False, resolution=self.resolution, effects=effects)
        self._check_memory(scene)
        with limited_threads(self.torch_threads):
            self.renderer = self._make_renderer(scene, overview=False)
        self._closed = False

    # ================================================================== hooks
    @abc.abstractmethod
    def _setup(self) -> None:
        """Set agent_names, groups, num_actions / action_dim, state_dim, physics, and `sim`: the
        simulation state (a frozen dataclass of tensors; its shapes are what set_state accepts)."""

    @abc.abstractmethod
    def _build_scene(self, scene: mr.Scene, overview: bool) -> None:
        """Add static geometry and instance groups; mount cameras unless `overview`."""

    def _init_cameras(self, renderer: mr.BatchRenderer, overview: bool) -> None:
        """Place free cameras once after the renderer is built. Default: mounted agent
        cameras (nothing to do) and the `_overview_camera()` for the overview."""
        if overview:
            eye, target = self._overview_camera()
            W = self.num_worlds
            renderer.set_cameras(position=eye.expand(W, 1, 3), look_at=target.expand(W, 1, 3))

    def _overview_camera(self):
        """(eye [3], target [3]) float64 of the overview camera (same in every world)."""
        return scenery.top_down_camera(self.arena_half_extent, self.overview_fov_y)

    @abc.abstractmethod
    def _reset_state(self, mask: torch.Tensor) -> None:
        """Replace `sim` by one with a new episode in the worlds where mask [W] is True, sampled
        with self.generator; the other worlds' tensors stay bit-identical (sample for all worlds,
        then state.select_worlds)."""

    @abc.abstractmethod
    def _step_state(self, actions: torch.Tensor, alive: torch.Tensor):
        """Replace `sim` by the state one step later, for validated actions; agents with alive
        False must be ignored. Returns (reward [W, A] float, terminated [W, A] bool, info dict)."""

    @abc.abstractmethod
    def _instances(self, full: bool) -> dict:
        """{group: renderer.update kwargs} of the current state. full=False: only what can
        change in a step (poses); full=True: everything (after a reset, for a new renderer)."""

    def state_bounds(self) -> dict:
        """{field of `sim`: (low, high)} that set_state enforces (low / high: a number, or one per
        index of the field's last axis). Default: every floating field within +-STATE_LIMIT (1e6),
        so that nothing overflows float32; an env narrows the fields that have a meaning (positions
        within its walls, timers within their delay)."""
        return {name: (-STATE_LIMIT, STATE_LIMIT) for name, value in explicit_state.fields(self.sim).items()
                if value.is_floating_point()}

    def _state_obs(self) -> torch.Tensor:
        """[W, A, state_dim] float32 low-dimensional observation."""
        raise NotImplementedError(f"{type(self).__name__} has no state observation")

    def _action_mask(self) -> torch.Tensor:
        """[W, A, num_actions] bool; default: every action valid."""
        return torch.ones(self.num_worlds, self.num_agents, self.num_actions, dtype=torch.bool, device=self.device)

    # ================================================================== public API
    @torch.no_grad()
    def reset(self, seed: int | None = None) -> dict:
        """Reset every world; `seed` (optional) re-seeds the env's generator first."""
        self._check_open()
        self._check_process()
        seed = _seed("seed", seed)
        if seed is not None:
            self.seed = seed
            self.generator.manual_seed(seed)
        with limited_threads(self.torch_threads):
            self._reset_masked(torch.ones(self.num_worlds, dtype=torch.bool, device=self.device))
            self._needs_reset = False
            return self._observe(full=True)

    @torch.no_grad()
    def reset_worlds(self, mask, seed: int | None = None) -> dict:
        """Reset only the worlds where mask [W] (bool) is True; returns obs of all worlds.

        `seed` (optional) re-seeds the env's generator before sampling."""
        self._check_open()
        self._check_process()
        self._check_started()
        mask = as_tensor("mask", _from_user("mask", mask), dtype_kind="bool")
        if tuple(mask.shape) != (self.num_worlds,):
            raise ValueError(f"mask must be a bool tensor of shape [{self.num_worlds}] (num_worlds), "
                             f"got shape {list(mask.shape)}")
        seed = _seed("seed", seed)
        if seed is not None:
            self.seed = seed
            self.generator.manual_seed(seed)
        with limited_threads(self.torch_threads):
            self._reset_masked(mask.to(self.device))
            return self._observe(full=True)

    @torch.no_grad()
    def step(self, actions):
        """Advance all worlds one step: (obs, reward, terminated, truncated, info)."""
        self._check_open()
        self._check_process()
        self._check_started()
        with limited_threads(self.torch_threads):
            return self._step(self.check_actions(actions))

    def _step(self, actions):
        W = self.num_worlds
        # next_step: the worlds whose episode ended at the previous step start a new one now;
        # their agents sit this step out (actions ignored, reward 0) and are then reset.
        if self.autoreset == "next_step":
            restart = self._episode_over()
        else:
            restart = torch.zeros(W, dtype=torch.bool, device=self.device)
        alive_before = self.alive & ~restart[:, None]
        reward, terminated, info = self._step_state(actions, alive_before)
        reward = torch.where(alive_before, reward.to(torch.float32), torch.zeros((), device=self.device))
        self.alive = alive_before & ~terminated
        self.step_count = self.step_count + 1
        restarted = bool(restart.any())
        if restarted:
            self._reset_masked(restart)  # alive again, step_count 0: not terminated, not truncated
        terminated = ~self.alive
        truncated = (self.step_count >= self.max_steps)[:, None] & self.alive
        done_worlds = (terminated | truncated).all(dim=1)
        info = {"step_count": self.step_count.clone(), "done_worlds": done_worlds, **info}
        if self.autoreset == "next_step":
            info["autoreset_worlds"] = restart
        if self.autoreset != "same_step":
            return self._observe(full=restarted), reward, terminated, truncated, info
        # same_step: the final frame of the ended episodes, then the reset and the new frame.
        obs = self._observe(full=False)
        info["final_obs"] = dict(obs)
        info["autoreset_worlds"] = done_worlds.clone()
        if bool(done_worlds.any()):
            self._reset_masked(done_worlds)
            obs = self._observe(full=True)
        return obs, reward, terminated, truncated, info

    def _episode_over(self) -> torch.Tensor:
        """bool [W]: worlds whose episode has ended (every agent terminated or truncated)."""
        return (~self.alive).all(dim=1) | (self.step_count >= self.max_steps)

    def random_actions(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """Uniformly random valid actions for every agent of every world (the action space's
        sample): discrete int64 [W, A], continuous float32 [W, A, action_dim] in [-1, 1]."""
        W, A = self.num_worlds, self.num_agents
        if self.continuous:
            return torch.rand(W, A, self.action_dim, generator=generator) * 2 - 1
        return torch.randint(self.num_actions, (W, A), generator=generator)

    @torch.no_grad()
    def check_actions(self, actions) -> torch.Tensor:
        """Validated actions on self.device (long [W, A] or float32 [W, A, action_dim]); raises
        TypeError / ValueError naming `actions`, the expected and the given, else changes nothing."""
        W, A = self.num_worlds, self.num_agents
        if not isinstance(actions, (torch.Tensor, np.ndarray, list, tuple)):
            raise TypeError(f"actions must be a torch.Tensor (or array-like), got {describe(actions)}")
        actions = _from_user("actions", actions)
        if self.continuous:
            want = f"a float tensor of shape [{W}, {A}, {self.action_dim}] (worlds, agents, action_dim) in [-1, 1]"
            if isinstance(actions, (torch.Tensor, np.ndarray)) and not (
                    torch.is_tensor(actions) and actions.is_floating_point()
                    or isinstance(actions, np.ndarray) and np.issubdtype(actions.dtype, np.floating)):
                raise TypeError(f"actions must be {want}, got {describe(actions)}")
            tensor = as_tensor("actions", actions, dtype_kind="float")
            tensor = tensor if tensor.dtype in FLOAT_DTYPES else tensor.to(torch.float32)  # float8: no isfinite
            if tuple(tensor.shape) != (W, A, self.action_dim):
                raise ValueError(f"actions must be {want}, got shape {list(tensor.shape)}")
            if not bool(torch.isfinite(tensor).all()):
                raise ValueError(f"actions must be {want}, got non-finite values (NaN/Inf)")
            if bool((tensor.abs() > 1).any()):
                raise ValueError(f"actions must be {want}, got values in "
                                 f"[{tensor.min().item():.4g}, {tensor.max().item():.4g}] (clamp them first)")
            return tensor.to(device=self.device, dtype=torch.float32)
        want = f"an integer tensor of shape [{W}, {A}] (worlds, agents) with values in [0, {self.num_actions})"
        try:
            tensor = as_tensor("actions", actions, dtype_kind="int")
        except TypeError as exc:
            raise TypeError(f"actions must be {want}, got {describe(actions)}") from exc
        if tuple(tensor.shape) != (W, A):
            raise ValueError(f"actions must be {want}, got shape {list(tensor.shape)}")
        checked = tensor.to(torch.float64) if tensor.dtype in (torch.uint16, torch.uint32, torch.uint64) else tensor
        if checked.numel() and (bool((checked < 0).any()) or bool((checked >= self.num_actions).any())):
            raise ValueError(f"actions must be {want}, got values in [{checked.min().item()}, {checked.max().item()}]")
        return tensor.to(device=self.device, dtype=torch.int64)

    @torch.no_grad()
    def render_overview(self, resolution=None) -> torch.Tensor:
        """uint8 [W, H2, W2, 3]: one camera per world that sees the whole arena, for humans.

        Built on the first call (a second renderer with the same groups and free cameras);
        `resolution` (int or (H, W)) defaults to `overview_resolution` and rebuilds it if changed."""
        self._check_open()
        self._check_process()
        self._check_started()
        resolution = resolution_hw(self.overview_resolution if resolution is None else resolution)
        if self._overview is None or self._overview.scene.resolution != resolution:
            effects = ("lighting", "shadows") if self.shadows else ("lighting",)
            scene = self._make_scene(overview=True, resolution=resolution, effects=effects)
            replaced = 0 if self._overview is None else memory.renderer_bytes(self._overview.scene)
            memory.check_fits(memory.renderer_bytes(scene) - replaced,
                              f"render_overview(resolution={resolution}) with num_worlds={self.num_worlds}",
                              "lower the overview's resolution")
            if self._overview is not None:
                self._overview.close()
                self._overview = None
            self._overview = self._make_renderer(scene, overview=True)
        with limited_threads(self.torch_threads):
            self._sync(self._overview, full=True)
            return self._overview.render().rgb[:, 0].to(self.device)

    def state_observation(self) -> torch.Tensor:
        """float32 [W, A, state_dim]: the low-dimensional observation of the current state (obs
        key "state"), whether or not the env was built with state_obs=True."""
        self._check_open()
        self._check_started()
        if not self.state_dim:
            raise NotImplementedError(f"{type(self).__name__} has no state observation")
        with limited_threads(self.torch_threads):
            return self._state_obs().to(torch.float32)

    def get_state(self) -> dict:
        """Copies of the whole state as {name: tensor}: the fields of `sim` (the simulation),
        "step_count" [W] int64, "alive" [W, A] bool and "rng" (the generator's state, uint8, CPU).
        set_state(state) restores it exactly: the steps that follow are bit-identical."""
        self._check_open()
        self._check_started()
        state = {name: value.clone() for name, value in {**explicit_state.fields(self.sim), **self._counters()}.items()}
        state["rng"] = self.generator.get_state()
        return state

    def set_state(self, state: dict) -> None:
        """Restore a state from get_state() (of this env or one built with the same arguments),
        RNG included; the env then continues from it as if it had never left it.

        Every key must be there, each tensor of the current shape, dtype and device, floats
        finite, "step_count" in [0, max_steps] and the fields of `sim` within ``state_bounds()``
        (e.g. positions inside the arena's walls); else TypeError / ValueError naming the key, and
        nothing changes."""
        self._check_open()
        template = {**explicit_state.fields(self.sim), **self._counters(), "rng": self.generator.get_state()}
        state = explicit_state.checked(state, template)
        steps = state["step_count"]
        if bool(((steps < 0) | (steps > self.max_steps)).any()):
            raise ValueError(f"state['step_count'] must be >= 0 and <= max_steps={self.max_steps}, got values in "
                             f"[{int(steps.min())}, {int(steps.max())}]")
        explicit_state.check_bounds(state, self.state_bounds())
        rng = state.pop("rng")
        try:
            torch.Generator().set_state(rng)
        except RuntimeError as exc:
            raise ValueError(f"state['rng'] must be a torch.Generator state (from get_state()), got an invalid one: "
                             f"{exc}") from exc
        self.step_count, self.alive = state.pop("step_count"), state.pop("alive")
        self.sim = type(self.sim)(**state)
        self.generator.set_state(rng)
        self._needs_reset = False
        with limited_threads(self.torch_threads):
            self._sync(self.renderer, full=True)  # per-episode instance data (landmarks, ...) changed too

    def close(self) -> None:
        """Release the renderers; safe to call twice. Any later use raises RuntimeError."""
        if self._closed:
            return
        self._closed = True
        for renderer in (self.renderer, self._overview):
            if renderer is not None:
                renderer.close()
        self._overview = None

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    def __reduce__(self):
        raise unpicklable(f"a marl_render {type(self).__name__} ({self.name!r})", "marl_render.envs.make_env")

    def __repr__(self):
        kind = f"continuous action_dim={self.action_dim}" if self.continuous else f"num_actions={self.num_actions}"
        return (f"{type(self).__name__}(name={self.name!r}, num_worlds={self.num_worlds}, "
                f"num_agents={self.num_agents}, resolution={self.resolution}, {kind}, obs_keys={self.obs_keys}, "
                f"max_steps={self.max_steps})")

    # ================================================================== internals
    def _counters(self) -> dict:
        """The core's part of the state (get_state / set_state)."""
        return {"step_count": self.step_count, "alive": self.alive}

    def _check_setup(self):
        A = self.num_agents
        if not (dataclasses.is_dataclass(self.sim) and not isinstance(self.sim, type)):
            raise RuntimeError(f"{type(self).__name__}._setup must set sim to a dataclass of tensors (envs/state.py)")
        if len(self.agent_names) != A or len(set(self.agent_names)) != A:
            raise RuntimeError(f"{type(self).__name__}._setup must give {A} distinct agent_names")
        grouped = [n for names in self.groups.values() for n in names]
        if sorted(grouped) != sorted(self.agent_names):
            raise RuntimeError(f"{type(self).__name__}.groups must partition agent_names")
        if self.continuous and not (isinstance(self.action_dim, int) and self.action_dim >= 1):
            raise RuntimeError(f"{type(self).__name__}._setup must set action_dim >= 1 for continuous actions")
        if not self.continuous and not (isinstance(self.num_actions, int) and self.num_actions >= 1):
            raise RuntimeError(f"{type(self).__name__}._setup must set num_actions >= 1 for discrete actions")

    def _check_memory(self, scene: mr.Scene) -> None:
        """Refuse a batch whose renderer, observations and env state would not fit in this
        machine's memory before they are allocated (torch would fail late with a raw allocator
        error, or the OOM killer would strike). See marl_render/memory.py for what is counted."""
        height, width = self.resolution
        needed = memory.renderer_bytes(scene) + self.num_worlds * memory.ENV_WORLD_BYTES
        memory.check_fits(needed, f"num_worlds={self.num_worlds} x num_agents={self.num_agents} at resolution "
                                  f"{height}x{width}", "lower num_worlds, num_agents or resolution")

    def _check_open(self):
        if self._closed:
            raise RuntimeError(f"this {type(self).__name__} environment is closed; create a new one")

    def _check_process(self):
        """In a process forked from the one that made this env: ForkedContextError now, before
        anything changes (the render at the end of a step would raise only after physics ran)."""
        self.context.check_usable()

    def _check_started(self):
        if self._needs_reset:
            raise RuntimeError(f"call reset() before using this {type(self).__name__} environment")

    def _make_scene(self, overview: bool, resolution, effects) -> mr.Scene:
        scene = mr.Scene(num_worlds=self.num_worlds, agents_per_world=1 if overview else self.num_agents,
                         resolution=resolution, effects=effects, background=self.background,
                         fov_y=self.overview_fov_y if overview else self.fov_y, near=self.near, far=self.far,
                         shadows=self.shadows or mr.Shadows())
        self._build_scene(scene, overview)
        return scene

    def _make_renderer(self, scene: mr.Scene, overview: bool) -> mr.BatchRenderer:
        renderer = mr.BatchRenderer(scene, color="gray" if self.grayscale and not overview else "rgb",
                                    context=self.context)
        try:
            self._init_cameras(renderer, overview)
        except BaseException:
            renderer.close()
            raise
        return renderer

    def _reset_masked(self, mask: torch.Tensor) -> None:
        self._reset_state(mask)
        self.step_count = torch.where(mask, torch.zeros_like(self.step_count), self.step_count)
        self.alive = self.alive | mask[:, None]

    def _sync(self, renderer: mr.BatchRenderer, full: bool) -> None:
        on_cpu = self.device.type == "cpu"
        overview = renderer is not self.renderer
        for group, kwargs in self._instances(full).items():
            if overview and "owner" in kwargs:  # owners hide bodies from agent views; the overview has none
                kwargs = {k: v for k, v in kwargs.items() if k != "owner"}
            if not on_cpu:
                kwargs = {k: v.cpu() for k, v in kwargs.items()}
            renderer.update(group, **kwargs)

    def _observe(self, full: bool) -> dict:
        self._sync(self.renderer, full)
        frame = self.renderer.render()
        obs = {"pixels": frame.rgb.to(self.device)}
        if self.depth:
            obs["depth"] = frame.depth.clamp_(max=self.far).to(self.device)
        if self.state_obs:
            obs["state"] = self._state_obs().to(torch.float32)
        if not self.continuous:
            obs["action_mask"] = self._action_mask()
        return obs
