"""The driver: W worlds x A agents of one task, stepped and rendered as one batch.

Every environment is a ``BatchedEnv`` driving a scenario (envs/scenario.py: the task's rules
and scene binding, pure functions of an explicit state). The driver owns everything that is
the same for all tasks: option checks (envs/options.py), seeding, step counters, the alive
mask, truncation, auto-reset, the renderers (envs/rendering.py), the observation dict and
the spec the front ends translate (envs/spec.py).

    env = BatchedEnv(Spread, EnvOptions(num_worlds=64), Spread.Params(num_landmarks=4))
    env = make_env("spread", num_worlds=64, num_landmarks=4)     # the same, by name

Data contract (W worlds, A agents, H x Wpx pixels)::

    obs = env.reset(seed=0)          # dict of tensors, all [W, A, ...]
      "pixels"       uint8   [W, A, H, Wpx, C]   always; C = 3, or 1 with grayscale=True (BT.601
                                                  luma drawn by the renderer, a third of the
                                                  bytes read back)
      "depth"        float32 [W, A, H, Wpx]      depth=True (metres along the view axis;
                                                  background = the camera's far plane)
      "state"        float32 [W, A, state_dim]   state_obs=True
      "lidar"        float32 [W, A, rays]        lidar=rays (arena tasks): distance to the first
                                                  wall, box or body along each ray / lidar_range,
                                                  capped at 1 (envs/sight.py)
      "action_mask"  bool    [W, A, num_actions] discrete envs (all True where no action
                                                  can be invalid); advice unless
                                                  enforce_action_mask=True (envs/masking.py)
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

import dataclasses

import numpy as np
import torch

import marl_render as mr
from marl_render.shadows import atlas_layout
from marl_render.threads import limited_threads, thread_count
from marl_render.validation import FLOAT_DTYPES, as_tensor, describe, positive_int, unpicklable

from . import masking
from . import options as check
from . import spec as env_spec
from . import state as explicit_state
from .options import EnvOptions
from .rendering import EnvRenderer, check_memory
from .scenario import Layout, Scenario

OBS_KEYS = ("pixels", "depth", "state", "lidar", "action_mask")


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


class BatchedEnv:
    """The driver of a task: see the module docstring for the contract.

    ``BatchedEnv(scenario, options=None, params=None)``: `scenario` is a Scenario subclass,
    `options` an EnvOptions (the options every env takes: num_worlds, num_agents, resolution
    (int or (H, W)), max_steps, continuous, state_obs, depth, shadows (False, True or a
    marl_render.Shadows; True: Shadows(bounds=the task's shadow_bounds)), device, seed,
    autoreset (False, "next_step", "same_step" or True = "same_step"), grayscale (one-channel
    pixels), torch_threads (default 1, at most 1024: torch intra-op threads used *inside* env
    calls, the caller's setting restored on return; None leaves torch's setting alone) and
    context (a marl_render.GLContext to render on; None: the process's default), and the
    accuracy knobs multisamples (MSAA samples of the agents' views, colour only), supersample
    (k x the resolution, box-filtered down) and physics_substeps (planar physics substeps per
    step; None: the task's own; coarser than the no-tunnelling bound is refused)), and
    compile_physics (torch.compile the task's physics kernel where it has one (cartpole):
    within 1e-12 of the default path, faster at small batches; seconds to compile at construction;
    a RuntimeWarning and the default path where compiling fails), lidar (rays of the "lidar"
    observation, 0: none) and lidar_range (m it is divided by; None: the arena's diagonal),
    enforce_action_mask (refuse forbidden actions: envs/masking.py), and appearance (None: off;
    "train", "heldout" or a marl_render.Appearance: each world's light, sky, floor and wall colours
    and patterns, object colour jitter and camera jitter, drawn at every reset of the world from its
    appearance_ids, see docs/appearance.md), `params` an instance of the scenario's Params (None:
    its defaults).

    Attributes: scenario, spec (the EnvSpec every front end translates), name, num_worlds (W),
    num_agents (A), agent_names, groups (team -> agent names, in agent-index order), resolution
    (H, W), continuous, num_actions (discrete, else None), action_dim (continuous, else None),
    action_meanings, obs_keys, info_keys, state_dim, max_steps, dt, device, seed, generator,
    renderer, physics (PhysicsConfig or None), physics_compiled (compile_physics took effect),
    lidar_rays, lidar_range, enforce_action_mask,
    sim (the simulation state), alive [W, A] bool,
    step_count [W] int64, appearance (None or the Appearance), appearance_ids ([W] int64 or None); and
    the scenario's camera settings (background, fov_y, near, far,
    overview_resolution, overview_fov_y, arena_half_extent) and agent_range.
    Methods: reset, reset_worlds, step, check_actions, episode_over, random_actions,
    heuristic_actions, render_overview, state_observation, get_state, set_state, close.
    """

    def __init__(self, scenario: type[Scenario], options: EnvOptions | None = None, params=None):
        self._closed = True  # until fully built: close() and __del__ then do nothing
        if not (isinstance(scenario, type) and issubclass(scenario, Scenario)):
            raise TypeError(f"scenario must be a Scenario subclass (envs/scenario.py), got {describe(scenario)}")
        options = EnvOptions() if options is None else options
        if not isinstance(options, EnvOptions):
            raise TypeError(f"options must be an EnvOptions, got {describe(options)}")
        params = scenario.Params() if params is None else params
        if not isinstance(params, scenario.Params):
            raise TypeError(f"params must be a {scenario.__name__}.Params, got {describe(params)}")
        self.num_worlds = positive_int("num_worlds", options.num_worlds)
        self.num_agents = check.num_agents(scenario.num_agents_for(params, options.num_agents), scenario)
        context = options.context
        if context is not None and not isinstance(context, mr.GLContext):
            raise TypeError(f"context must be a marl_render.GLContext or None, got {describe(context)}")
        self.context = mr.backend.context() if context is None else context
        self.context.check_usable()
        self.resolution = check.resolution(options.resolution, scenario, self.context.info().max_framebuffer_size)
        self.max_steps = check.max_steps(options.max_steps, scenario)
        self.continuous = check.flag("continuous", options.continuous)
        self.state_obs = check.flag("state_obs", options.state_obs)
        self.depth = check.flag("depth", options.depth)
        self.grayscale = check.flag("grayscale", options.grayscale)
        self.pixel_channels = 1 if self.grayscale else 3
        self.lidar_rays, self.lidar_range = check.lidar(options.lidar, options.lidar_range, scenario)
        self.enforce_action_mask = check.flag("enforce_action_mask", options.enforce_action_mask)
        if self.enforce_action_mask and self.continuous:
            raise ValueError("enforce_action_mask applies to discrete actions (continuous=False), which have an "
                             "action mask; got enforce_action_mask=True with continuous=True")
        self.autoreset = check.autoreset_mode(options.autoreset)  # False, "next_step" or "same_step"
        self.device = check.device(options.device)
        torch_threads = options.torch_threads
        self.torch_threads = None if torch_threads is None else thread_count("torch_threads", torch_threads)
        seed = check.seed("seed", options.seed)
        self.seed = int(torch.Generator().seed() % 2 ** 63) if seed is None else seed
        self.generator = torch.Generator().manual_seed(self.seed)
        self.shadows = check.shadows(options.shadows, scenario.shadow_bounds)
        effects = ("lighting", "depth") if self.depth else ("lighting",)
        effects += ("shadows",) if self.shadows else ()
        self.appearance = check.appearance(options.appearance)  # None, or the Appearance of the worlds' looks
        effects += ("appearance",) if self.appearance is not None else ()
        if self.shadows:  # an atlas GL cannot hold is named as such, not as a memory shortage
            atlas_layout(self.num_worlds, self.shadows.resolution, self.context.info().max_framebuffer_size)
        # Views and pixels alone, before the scenario allocates anything; the whole scene below.
        check_memory(mr.Scene(num_worlds=self.num_worlds, agents_per_world=self.num_agents,
                              resolution=self.resolution, effects=effects),
                     self.num_worlds, self.num_agents, self.resolution)
        self.context.check_usable()  # in a forked child: ForkedContextError now, not a torch deadlock below

        multisamples = check.multisamples(options.multisamples)
        supersample = positive_int("supersample", options.supersample)
        compile_physics = check.flag("compile_physics", options.compile_physics)

        self.scenario = scenario(params, Layout(self.num_worlds, self.num_agents, self.continuous, self.device))
        if options.physics_substeps is not None:
            self.scenario.physics = check.physics_substeps(options.physics_substeps, self.scenario)
        self._describe(self.scenario)
        self.sim = self.scenario.initial_state()  # the simulation state (a frozen dataclass of tensors)
        self._check_scenario()
        self.obs_keys = tuple(k for k, on in (("pixels", True), ("depth", self.depth), ("state", self.state_obs),
                                              ("lidar", self.lidar_rays > 0), ("action_mask", not self.continuous))
                              if on)
        self.spec = env_spec.build(self)
        W, A = self.num_worlds, self.num_agents
        self.alive = torch.ones(W, A, dtype=torch.bool, device=self.device)
        self.step_count = torch.zeros(W, dtype=torch.int64, device=self.device)
        # [W] int64 (CPU): the id each world's look is drawn from (appearance on), from the env's
        # generator at every reset of the world. It will become the world's level id (issue 27).
        self.appearance_ids = torch.zeros(W, dtype=torch.int64) if self.appearance is not None else None
        self._needs_reset = True
        with limited_threads(self.torch_threads):
            self.views = EnvRenderer(self.scenario, resolution=self.resolution, effects=effects,
                                     shadows=self.shadows, grayscale=self.grayscale, context=self.context,
                                     device=self.device, multisamples=multisamples, supersample=supersample,
                                     appearance=self.appearance)
        self.renderer = self.views.renderer
        # Last: compiling takes seconds, so every other option has been checked by now.
        if compile_physics:
            try:
                with limited_threads(self.torch_threads):
                    self.scenario.compile_physics()
            except BaseException:
                self.views.close()
                raise
        self._closed = False

    @property
    def physics_compiled(self) -> bool:
        """Whether steps run the task's compiled physics kernel (compile_physics=True and compiling
        worked; False again if the kernel ever failed at a step and the default path took over)."""
        return self.scenario.physics_compiled

    def _describe(self, s: Scenario) -> None:
        """Copy the scenario's description onto the driver (the names front ends read)."""
        self.name, self.dt, self.far, self.info_keys = s.name, s.dt, s.far, dict(s.info_keys)
        self.groups = {team: list(names) for team, names in s.teams.items()}
        self.agent_names = s.agent_names
        self.num_actions, self.action_meanings, self.action_dim = s.num_actions, s.action_meanings, s.action_dim
        self.state_dim, self.physics, self.physics_terms = s.state_dim, s.physics, s.physics_terms
        # The cameras' and the scene's settings, read by tools that draw the same scene (bench floor).
        for name in ("agent_range", "background", "fov_y", "near", "overview_resolution", "overview_fov_y",
                     "arena_half_extent"):
            setattr(self, name, getattr(s, name))

    # ================================================================== public API
    @torch.no_grad()
    def reset(self, seed: int | None = None) -> dict:
        """Reset every world; `seed` (optional) re-seeds the env's generator first."""
        self._check_open()
        self._check_process()
        seed = check.seed("seed", seed)
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
        seed = check.seed("seed", seed)
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
            actions = self.check_actions(actions)
            if self.enforce_action_mask:
                self._check_allowed(actions)
            return self._step(actions)

    def _step(self, actions):
        W = self.num_worlds
        # next_step: the worlds whose episode ended at the previous step start a new one now;
        # their agents sit this step out (actions ignored, reward 0) and are then reset.
        if self.autoreset == "next_step":
            restart = self.episode_over()
        else:
            restart = torch.zeros(W, dtype=torch.bool, device=self.device)
        alive_before = self.alive & ~restart[:, None]
        result = self.scenario.step(self.sim, actions, alive_before, self.generator)
        self.sim, reward, terminated, info = self._checked_step(result)
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

    def episode_over(self) -> torch.Tensor:
        """bool [W]: worlds whose episode has ended (every agent terminated or truncated). The
        front ends ask this rather than work it out."""
        return (~self.alive).all(dim=1) | (self.step_count >= self.max_steps)

    def random_actions(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """Uniformly random valid actions for every agent of every world (the action space's
        sample): discrete int64 [W, A], continuous float32 [W, A, action_dim] in [-1, 1]."""
        W, A = self.num_worlds, self.num_agents
        if self.continuous:
            return torch.rand(W, A, self.action_dim, generator=generator) * 2 - 1
        if self.enforce_action_mask:  # among the allowed actions only (envs/masking.py)
            with torch.no_grad(), limited_threads(self.torch_threads):
                return masking.sample_allowed(self._action_mask(), generator)
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
        if checked.numel():
            low, high = (value.item() for value in torch.aminmax(checked))
            if low < 0 or high >= self.num_actions:
                raise ValueError(f"actions must be {want}, got values in [{low}, {high}]")
        return tensor.to(device=self.device, dtype=torch.int64)

    @torch.no_grad()
    def render_overview(self, resolution=None) -> torch.Tensor:
        """uint8 [W, H2, W2, 3]: one camera per world that sees the whole arena, for humans.

        Built on the first call (a second renderer with the same groups and free cameras);
        `resolution` (int or (H, W)) defaults to `overview_resolution` and rebuilds it if changed."""
        self._check_open()
        self._check_process()
        self._check_started()
        with limited_threads(self.torch_threads):
            return self.views.overview(self.sim, resolution)

    def state_observation(self) -> torch.Tensor:
        """float32 [W, A, state_dim]: the low-dimensional observation of the current state (obs
        key "state"), whether or not the env was built with state_obs=True."""
        self._check_open()
        self._check_started()
        if not self.state_dim:
            raise NotImplementedError(f"{type(self.scenario).__name__} has no state observation")
        with limited_threads(self.torch_threads):
            return self.scenario.observation(self.sim, self.alive).to(torch.float32)

    @torch.no_grad()
    def heuristic_actions(self) -> torch.Tensor:
        """The scenario's scripted policy's actions for the current state (valid actions, as
        random_actions gives them): a reference that reads the state and beats random."""
        self._check_open()
        self._check_started()
        with limited_threads(self.torch_threads):
            return self.check_actions(self.scenario.heuristic(self.sim, self.alive))

    def get_state(self) -> dict:
        """Copies of the whole state as {name: tensor}: the fields of `sim` (the simulation),
        "step_count" [W] int64, "alive" [W, A] bool, "rng" (the generator's state, uint8, CPU) and,
        with appearance on, "appearance_ids" [W] int64 (CPU). set_state(state) restores it exactly:
        the steps that follow are bit-identical."""
        self._check_open()
        self._check_started()
        state = {name: value.clone() for name, value in {**explicit_state.fields(self.sim), **self._counters()}.items()}
        state["rng"] = self.generator.get_state()
        return state

    def set_state(self, state: dict) -> None:
        """Restore a state from get_state() (of this env or one built with the same arguments),
        RNG included; the env then continues from it as if it had never left it.

        Every key must be there, each tensor of the current shape, dtype and device, floats
        finite, "step_count" in [0, max_steps] and the fields of `sim` within the scenario's
        ``state_bounds()`` (e.g. positions inside the arena's walls); else TypeError / ValueError
        naming the key, and nothing changes."""
        self._check_open()
        template = {**explicit_state.fields(self.sim), **self._counters(), "rng": self.generator.get_state()}
        state = explicit_state.checked(state, template)
        steps = state["step_count"]
        if bool(((steps < 0) | (steps > self.max_steps)).any()):
            raise ValueError(f"state['step_count'] must be >= 0 and <= max_steps={self.max_steps}, got values in "
                             f"[{int(steps.min())}, {int(steps.max())}]")
        explicit_state.check_bounds(state, self.scenario.state_bounds())
        rng = state.pop("rng")
        try:
            torch.Generator().set_state(rng)
        except RuntimeError as exc:
            raise ValueError(f"state['rng'] must be a torch.Generator state (from get_state()), got an invalid one: "
                             f"{exc}") from exc
        self.step_count, self.alive = state.pop("step_count"), state.pop("alive")
        appearance_ids = state.pop("appearance_ids", None)
        self.sim = type(self.sim)(**state)
        self.generator.set_state(rng)
        self._needs_reset = False
        with limited_threads(self.torch_threads):
            if appearance_ids is not None:
                self.appearance_ids = appearance_ids
                self.views.set_appearance(appearance_ids)
            self.views.sync(self.sim, full=True)  # per-episode instance data (landmarks, ...) changed too

    def close(self) -> None:
        """Release the renderers; safe to call twice. Any later use raises RuntimeError."""
        if self._closed:
            return
        self._closed = True
        self.views.close()

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
        """The core's part of the state (get_state / set_state); "appearance_ids" with appearance on."""
        counters = {"step_count": self.step_count, "alive": self.alive}
        if self.appearance is not None:
            counters["appearance_ids"] = self.appearance_ids
        return counters

    def _action_mask(self) -> torch.Tensor:
        """The scenario's action mask [W, A, num_actions] of the current state, checked."""
        mask = self.scenario.action_mask(self.sim, self.alive)
        _check_tensor(f"{type(self.scenario).__name__}.action_mask", mask, (self.num_worlds, self.num_agents,
                                                                           self.num_actions), "bool", self.device)
        return mask

    def _check_allowed(self, actions: torch.Tensor) -> None:
        """enforce_action_mask: a ValueError naming the forbidden actions of the agents this step acts
        for (those of departed agents and of worlds a next_step autoreset restarts are ignored)."""
        acting = self.alive
        if self.autoreset == "next_step":
            acting = acting & ~self.episode_over()[:, None]
        mask = self._action_mask()
        refused = masking.forbidden(mask, actions, acting)
        if bool(refused.any()):
            raise masking.refusal(refused, mask, actions, self.agent_names, self.action_meanings)

    def _check_scenario(self):
        """A scenario whose setup() left its declarations incomplete fails here, naming the hook."""
        s, A, where = self.scenario, self.num_agents, f"{type(self.scenario).__name__}.setup"
        if len(self.agent_names) != A or len(set(self.agent_names)) != A:
            raise RuntimeError(f"{where} must give teams holding {A} distinct agent names, got {self.agent_names}")
        if self.continuous and not (isinstance(self.action_dim, int) and self.action_dim >= 1):
            raise RuntimeError(f"{where} must declare continuous_actions(dim) with dim >= 1 for continuous=True")
        if not self.continuous and not (isinstance(self.num_actions, int) and self.num_actions >= 1):
            raise RuntimeError(f"{where} must declare discrete_actions(meanings) with at least one action")
        if not (dataclasses.is_dataclass(self.sim) and not isinstance(self.sim, type)):
            raise RuntimeError(f"{type(s).__name__}.initial_state must return a dataclass of tensors (envs/state.py), "
                               f"got {describe(self.sim)}")

    def _check_open(self):
        if self._closed:
            raise RuntimeError(f"this {type(self.scenario).__name__} environment is closed; create a new one")

    def _check_process(self):
        """In a process forked from the one that made this env: ForkedContextError now, before
        anything changes (the render at the end of a step would raise only after physics ran)."""
        self.context.check_usable()

    def _check_started(self):
        if self._needs_reset:
            raise RuntimeError(f"call reset() before using this {type(self.scenario).__name__} environment")

    def _checked_step(self, result):
        """Scenario.step's result after checking its form, so that a task's mistake is named at its
        hook rather than deep in the renderer (shape and dtype reads only: no pass over the data)."""
        where = f"{type(self.scenario).__name__}.step"
        if not (isinstance(result, tuple) and len(result) == 4):
            raise TypeError(f"{where} must return (state, reward, terminated, info), got {describe(result)}")
        state, reward, terminated, info = result
        self._check_state(where, state)
        W, A = self.num_worlds, self.num_agents
        _check_tensor(f"{where}'s reward", reward, (W, A), "float", self.device)
        _check_tensor(f"{where}'s terminated", terminated, (W, A), "bool", self.device)
        if not isinstance(info, dict) or set(info) != set(self.info_keys):
            raise ValueError(f"{where}'s info must be a dict with the keys of info_keys {sorted(self.info_keys)}, "
                             f"got {sorted(info) if isinstance(info, dict) else describe(info)}")
        for key, dtype in self.info_keys.items():
            _check_tensor(f"{where}'s info[{key!r}]", info[key], (W,), dtype, self.device)
        return result

    def _check_state(self, where: str, state) -> None:
        if type(state) is not type(self.sim):
            raise TypeError(f"{where} must return a {type(self.sim).__name__} (the class of initial_state()), "
                            f"got {describe(state)}")
        for name, want in explicit_state.fields(self.sim).items():
            _check_tensor(f"{where}'s state.{name}", getattr(state, name), tuple(want.shape), want.dtype, want.device)

    def _reset_masked(self, mask: torch.Tensor) -> None:
        self.views.invalidate()  # before the state changes: an interruption from here on still resyncs
        fresh = self.scenario.spawn(self.generator)
        self._check_state(f"{type(self.scenario).__name__}.spawn", fresh)
        self.sim = explicit_state.select_worlds(mask, fresh, self.sim)
        self.step_count = torch.where(mask, torch.zeros_like(self.step_count), self.step_count)
        self.alive = self.alive | mask[:, None]
        if self.appearance is not None:  # drawn after spawn: the first layouts match those with it off
            fresh_ids = torch.randint(-2 ** 63, 2 ** 63 - 1, (self.num_worlds,), generator=self.generator)
            self.appearance_ids = torch.where(mask.cpu(), fresh_ids, self.appearance_ids)
            self.views.set_appearance(self.appearance_ids, mask.cpu())

    def _observe(self, full: bool) -> dict:
        self.views.sync(self.sim, full)
        frame = self.views.render()
        obs = {"pixels": frame.rgb.to(self.device)}
        if self.depth:
            obs["depth"] = frame.depth.clamp_(max=self.far).to(self.device)
        W, A, s = self.num_worlds, self.num_agents, type(self.scenario).__name__
        if self.state_obs:
            state = self.scenario.observation(self.sim, self.alive)
            _check_tensor(f"{s}.observation", state, (W, A, self.state_dim), "float", self.device)
            obs["state"] = state.to(torch.float32)
        if self.lidar_rays:
            obs["lidar"] = self.scenario.lidar(self.sim, self.lidar_rays, self.lidar_range)
        if not self.continuous:
            mask = self.scenario.action_mask(self.sim, self.alive)
            _check_tensor(f"{s}.action_mask", mask, (W, A, self.num_actions), "bool", self.device)
            obs["action_mask"] = mask
        return obs


def _check_tensor(what: str, value, shape: tuple, dtype, device: torch.device) -> None:
    """A hook's tensor has the declared shape, dtype (a torch.dtype, or "float" / "bool") and device."""
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{what} must be a torch.Tensor of shape {list(shape)}, got {describe(value)}")
    if dtype == "float":
        dtype_ok, want_dtype = value.is_floating_point(), "a float dtype"
    elif dtype == "bool":
        dtype_ok, want_dtype = value.dtype == torch.bool, "torch.bool"
    else:
        dtype_ok, want_dtype = value.dtype == dtype, str(dtype)
    same_device = value.device.type == device.type and (device.index is None or value.device.index == device.index)
    if tuple(value.shape) != shape or not dtype_ok or not same_device:
        raise ValueError(f"{what} must have shape {list(shape)}, {want_dtype}, device {device}; got shape "
                         f"{list(value.shape)}, {value.dtype}, device {value.device}")
