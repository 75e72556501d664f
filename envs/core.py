"""The driver: W worlds x A agents of one task, stepped and rendered as one batch.

Every environment is a ``BatchedEnv`` driving a scenario (envs/scenario.py: the task's rules
and scene binding, pure functions of an explicit state). The driver owns everything that is
the same for all tasks: seeding, step counters, the alive mask, truncation, auto-reset and
the observation dict. It leans on one module per job: the options and their resolution
(envs/options.py), the checks of the scenario's hooks (envs/contract.py), of the caller's
actions (envs/actions.py) and masks (envs/masking.py), all-or-nothing calls (envs/atomic.py),
the renderers (envs/rendering.py) and the spec the front ends translate (envs/spec.py).

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
      "agent_id"     float32 [W, A, A + teams]   agent_ids=True: the agent's one-hot index, then its
                                                  team's (one policy playing several roles)
      <task's key>   float32 [W, A, width]       the task's own vectors (Scenario.vector_obs), always:
                                                  matrix's "inventory"
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
leaves the state (bodies, counters, RNG) exactly as it was; a call that fails later (a hook
raises) leaves it so too (envs/atomic.py). ``needs_reset`` says whether the env must be reset
before it can step.

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
tensors (``env.sim`` hands out a copy of it); ``get_state()`` copies it out with the step counters, the alive mask and
the RNG state, and ``set_state(state)`` restores all of it exactly.
"""
from __future__ import annotations

import dataclasses
import threading

import torch

from marl_render.util.threads import limited_threads
from marl_render.util.validation import describe, unpicklable

from . import episodes as episode_book
from . import levels as level_sets
from . import masking
from . import options as check
from . import spec as env_spec
from . import state as explicit_state
from .actions import checked as checked_actions
from .actions import from_user, world_mask
from .atomic import AllOrNothing, env_call
from .contract import HookContract
from .options import EnvOptions
from .rendering import EnvRenderer
from .scenario import MAX_COUNT, BatchShape, Scenario
from .spec import OBS_KEYS  # noqa: F401 (marl_render.envs.core.OBS_KEYS, as before)


class BatchedEnv(AllOrNothing):
    """The driver of a task: see the module docstring for the contract.

    ``BatchedEnv(scenario, options=None, params=None)``: `scenario` is a Scenario subclass,
    `options` an EnvOptions (the options every env takes; EnvOptions lists them) and `params` an
    instance of the scenario's Params (None: its defaults).

    Attributes: scenario, spec (the EnvSpec every front end translates), name, num_worlds (W),
    num_agents (A), agent_names, groups (team -> agent names, in agent-index order), resolution
    (H, W), continuous, num_actions (discrete, else None), action_dim (continuous, else None),
    action_meanings, obs_keys, info_keys, state_dim, max_steps, dt, device, readback, seed, generator,
    renderer, physics (PhysicsConfig or None), physics_compiled (compile_physics took effect),
    lidar_rays, lidar_range, enforce_action_mask,
    sim (the simulation state), alive [W, A] bool,
    step_count [W] int64, appearance (None or the Appearance), appearance_ids ([W] int64 or None),
    levels (None or the level sampler, envs/levels.py), level_ids ([W] int64 or None), needs_reset; and
    the scenario's camera settings (background, fov_y, near, far,
    overview_resolution, overview_fov_y, arena_half_extent) and agent_range.
    Methods: reset, reset_worlds, reset_to_level, step, check_actions, episode_over, action_mask,
    random_actions, heuristic_actions, render_overview, state_observation, get_state, set_state, close.
    """

    # What a call replaces at its end, once every hook and the render have succeeded (envs/atomic.py): a
    # call that raises before then leaves these, the generator and the renderer's looks as they were.
    _committed = {"sim": "_sim", "alive": "_alive", "step_count": "_step_count", "looks": "_appearance_ids",
                  "levels": "_level_ids", "seed": "seed", "needs_reset": "_needs_reset"}

    def __init__(self, scenario: type[Scenario], options: EnvOptions | None = None, params=None):
        with torch.inference_mode(False), torch.no_grad():  # what the env keeps are normal tensors: env_call
            self._build(scenario, options, params)

    def _build(self, scenario, options, params) -> None:
        self._lock = threading.RLock()  # see envs/atomic.py
        self._closed = True  # until fully built: close() and __del__ then do nothing
        if not (isinstance(scenario, type) and issubclass(scenario, Scenario)):
            raise TypeError(f"scenario must be a Scenario subclass (envs/scenario.py), got {describe(scenario)}")
        options = EnvOptions() if options is None else options
        if not isinstance(options, EnvOptions):
            raise TypeError(f"options must be an EnvOptions, got {describe(options)}")
        params = scenario.Params() if params is None else params
        if not isinstance(params, scenario.Params):
            raise TypeError(f"params must be a {scenario.__name__}.Params, got {describe(params)}")
        settings = check.resolve(options, scenario, params)
        for name in check.PUBLISHED:  # num_worlds, device, resolution, seed, ...: the attributes listed above
            setattr(self, name, getattr(settings, name))
        self.generator = torch.Generator().manual_seed(self.seed)

        self._batch = BatchShape(self.num_worlds, self.num_agents, self.continuous, self.device)
        self.scenario = scenario(params, self._batch)
        if settings.physics_substeps is not None:
            self.scenario.physics = check.physics_substeps(settings.physics_substeps, self.scenario)
        self._describe(self.scenario)
        self._sim = self.scenario.initial_state()  # the simulation state (a frozen dataclass of tensors)
        self._contract = HookContract(self.scenario, self._batch, self._sim, self.state_obs)
        team_index = torch.tensor([t for t, names in enumerate(self.groups.values()) for _ in names])
        self._ids = torch.cat((torch.eye(self.num_agents), torch.nn.functional.one_hot(team_index, len(self.groups))),
                              -1).to(self.device, torch.float32)  # [A, A + teams]: see "agent_id"
        W, A = self.num_worlds, self.num_agents
        self._alive = torch.ones(W, A, dtype=torch.bool, device=self.device)
        self._step_count = torch.zeros(W, dtype=torch.int64, device=self.device)
        # [W] int64 (CPU): the id each world's look is drawn from (appearance on): its level id with
        # levels on, else drawn from the env's generator at every reset of the world.
        self._appearance_ids = torch.zeros(W, dtype=torch.int64) if self.appearance is not None else None
        # [W] int64 (CPU): the level each world plays (levels on), else None.
        self._level_ids = torch.zeros(W, dtype=torch.int64) if self.levels is not None else None
        if self.levels is not None:  # the driver's info entry, after the task's were checked
            self.info_keys["level"] = torch.int64
        self.episodes = episode_book.for_env(options, scenario, params, self.info_keys, self._batch, self.max_steps)
        self.info_keys.update(self.episodes.info_keys)
        self.spec = env_spec.build(self)
        self.obs_keys = self.spec.obs_keys
        self._needs_reset = True
        with limited_threads(self.torch_threads):
            self.views = EnvRenderer(self.scenario, resolution=self.resolution, effects=settings.effects,
                                     shadows=self.shadows, grayscale=self.grayscale, context=self.context,
                                     device=self.device, multisamples=settings.multisamples,
                                     supersample=settings.supersample, appearance=self.appearance,
                                     readback=self.readback, layered=settings.layered,
                                     exact_tiles=settings.exact_tiles,
                                     impostors=settings.impostors)
        self.renderer = self.views.renderer
        # Last: compiling takes seconds, so every other option has been checked by now.
        if settings.compile_physics:
            try:
                with limited_threads(self.torch_threads):
                    self.scenario.compile_physics()
            except BaseException:
                self.views.close()
                raise
        self._closed = False

    @property
    def sim(self):
        """The simulation state, a frozen dataclass of [W, ...] tensors (a copy, so writing into it
        changes nothing; bots and scripted policies read it once per call, a few small tensors)."""
        return dataclasses.replace(self._sim, **{name: value.clone() if isinstance(value, torch.Tensor) else value
                                                 for name, value in explicit_state.fields(self._sim).items()})

    @property
    def alive(self) -> torch.Tensor:
        """Which agents take part in each world's episode, bool [W, A] (a copy)."""
        return self._alive.clone()

    @property
    def step_count(self) -> torch.Tensor:
        """The steps of each world's episode so far, int64 [W] (a copy)."""
        return self._step_count.clone()

    @property
    def appearance_ids(self) -> torch.Tensor | None:
        """The id each world's look is drawn from, int64 [W] (a copy), with appearance on; else None."""
        return None if self._appearance_ids is None else self._appearance_ids.clone()

    @property
    def level_ids(self) -> torch.Tensor | None:
        """The level each world plays, int64 [W] (a copy), with levels on (envs/levels.py); else None."""
        return None if self._level_ids is None else self._level_ids.clone()

    @property
    def needs_reset(self) -> bool:
        """True while the env must be reset before it can step, as it must until the first reset() or
        set_state() and again after a call failed in a way that cannot be undone (a hook wrote into the
        state it was given). While it is True, step, reset_worlds, get_state and the like raise RuntimeError."""
        return self._needs_reset

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
        self.vector_obs = dict(s.vector_obs)  # key -> VectorObs: the task's own per-agent vectors (obs keys)
        # The cameras' and the scene's settings, read by tools that draw the same scene (bench floor).
        for name in ("agent_range", "background", "fov_y", "near", "overview_resolution", "overview_fov_y",
                     "arena_half_extent"):
            setattr(self, name, getattr(s, name))

    # ================================================================== public API
    @env_call
    def reset(self, seed: int | None = None) -> dict:
        """Reset every world; `seed` (optional) re-seeds the env's generator first.

        Returns the observations {key: tensor}: "pixels" uint8 [W, A, H, Wpx, 3] (1 channel with
        grayscale), "action_mask" bool [W, A, num_actions] (discrete actions), and where asked for
        "depth" float32 [W, A, H, Wpx], "state" float32 [W, A, state_dim], "lidar" float32
        [W, A, rays]. Each task's card (docs/envs/NAME.md) lists its keys, shapes and values."""
        self._check_open(process=True)
        seed = check.seed("seed", seed)
        return self._reset_some(torch.ones(self.num_worlds, dtype=torch.bool, device=self.device), seed, None)

    @env_call
    def reset_worlds(self, mask, seed: int | None = None) -> dict:
        """Reset only the worlds where mask [W] (bool) is True; returns obs of all worlds.

        `seed` (optional) re-seeds the env's generator before sampling."""
        self._check_open(process=True)
        self._check_started()
        mask = world_mask(mask, self.num_worlds, self.device)
        seed = check.seed("seed", seed)
        return self._reset_some(mask, seed, None)

    @env_call
    def reset_to_level(self, mask, level_ids, seed: int | None = None) -> dict:
        """Reset the worlds where mask [W] (bool) is True to the levels level_ids [W] (int64, read
        where mask is True; each in [0, 2**62)); returns obs of all worlds. Needs levels= (any set:
        the ids given need not be in it, so a curriculum or an evaluation may pick any level).
        `seed` (optional) re-seeds the env's generator (the step-time draws that follow)."""
        self._check_open(process=True)
        self._check_started()
        level_sets.require_levels(self, "reset_to_level")
        mask = world_mask(mask, self.num_worlds, self.device)
        chosen = level_sets.check_level_ids("level_ids", from_user("level_ids", level_ids), self.num_worlds,
                                            where=mask.cpu())
        return self._reset_some(mask, check.seed("seed", seed), chosen)

    def _reset_some(self, mask: torch.Tensor, seed: int | None, chosen: torch.Tensor | None) -> dict:
        """A new episode in the worlds of mask [W] (with levels on, the levels `chosen` there, None: drawn)."""
        with limited_threads(self.torch_threads), self._all_or_nothing():
            if seed is not None:
                self.seed = seed
                self.generator.manual_seed(seed)
            sim, step_count, alive, looks, levels = self._respawned(mask, self._sim, self._step_count, self._alive,
                                                                    self._appearance_ids, self._level_ids, chosen)
            obs = self._observe(sim, alive, full=True)
            self._commit(sim=sim, alive=alive, step_count=step_count, looks=looks, levels=levels, needs_reset=False)
            return obs

    @env_call
    def step(self, actions):
        """Advance all worlds one step: (obs, reward, terminated, truncated, info).

        `actions`: int64 [W, A] in [0, num_actions) (discrete), or float32 [W, A, action_dim] in
        [-1, 1] (``continuous=True``); a bad one raises before anything changes. Returns obs as
        reset's, reward float32 [W, A], terminated and truncated bool [W, A], and info {name: [W]
        tensor} (the step count, ``done_worlds`` and the task's episode statistics)."""
        self._check_open(process=True)
        self._check_started()
        with limited_threads(self.torch_threads):
            actions = self.check_actions(actions)
            if self.enforce_action_mask:  # the agents this step acts for take actions their mask allows
                mask = self._contract.action_mask(self._sim, self._alive)
                masking.check_allowed(mask, actions, masking.acting(self), self.agent_names, self.action_meanings)
            with self._all_or_nothing():
                return self._step(actions)

    def _step(self, actions):
        """One step worked out in locals (the state, counters, frames and outputs) and committed only
        at the end, once every hook has succeeded (see _all_or_nothing)."""
        W = self.num_worlds
        # next_step: the worlds whose episode ended at the previous step start a new one now;
        # their agents sit this step out (actions ignored, reward 0) and are then reset.
        if self.autoreset == "next_step":
            restart = self.episode_over()
        else:
            restart = torch.zeros(W, dtype=torch.bool, device=self.device)
        alive_before = self._alive & ~restart[:, None]
        sim, reward, terminated, task_info = self._contract.checked_step(
            self.scenario.step(self._sim, actions, alive_before, self.generator))
        reward = torch.where(alive_before, reward.to(torch.float32), torch.zeros((), device=self.device))
        alive = alive_before & ~terminated
        step_count = self._step_count + 1
        tagged = self._contract.tagged_out(sim) if self.episodes.social else None
        task_info = {**task_info, **self.episodes.record(reward, alive_before, tagged, step_count)}
        restarted, looks, levels = bool(restart.any()), self._appearance_ids, self._level_ids
        if restarted:  # alive again, step_count 0: not terminated, not truncated
            sim, step_count, alive, looks, levels = self._respawned(restart, sim, step_count, alive, looks, levels)
        terminated = ~alive
        truncated = (step_count >= self.episodes.limit(self.max_steps))[:, None] & alive
        done_worlds = (terminated | truncated).all(dim=1)
        # The task's info values may be its state's own tensors: the caller gets copies.
        info = {"step_count": step_count.clone(), "done_worlds": done_worlds,
                **{key: value.clone() for key, value in task_info.items()}}
        if self.autoreset == "next_step":
            info["autoreset_worlds"] = restart
        if self.autoreset != "same_step":
            obs = self._observe(sim, alive, full=restarted)
        else:  # the final frame of the ended episodes, then the reset and the new frame
            obs = self._observe(sim, alive, full=False)
            info["final_obs"] = dict(obs)
            info["autoreset_worlds"] = done_worlds.clone()
            if bool(done_worlds.any()):
                if levels is not None:
                    info["final_level"] = levels.to(self.device)
                sim, step_count, alive, looks, levels = self._respawned(done_worlds, sim, step_count, alive, looks,
                                                                        levels)
                obs = self._observe(sim, alive, full=True)
        if levels is not None:  # the level of the episode the returned obs belong to
            info["level"] = levels.to(self.device, copy=True)
        self._commit(sim=sim, alive=alive, step_count=step_count, looks=looks, levels=levels)
        return obs, reward, terminated, truncated, info

    def episode_over(self) -> torch.Tensor:
        """bool [W]: worlds whose episode has ended (every agent terminated or truncated). The
        front ends ask this rather than work it out."""
        return (~self._alive).all(dim=1) | (self._step_count >= self.episodes.limit(self.max_steps))

    @env_call
    def action_mask(self) -> torch.Tensor:
        """bool [W, A, num_actions]: the actions the current state allows (obs key "action_mask"; a copy),
        for discrete envs; what enforce_action_mask=True checks a step's actions against."""
        self._check_open()
        self._check_started()
        if self.continuous:
            raise ValueError(f"action_mask applies to discrete actions, and this {type(self.scenario).__name__} "
                             f"env has continuous=True")
        with limited_threads(self.torch_threads):
            return self._contract.action_mask(self._sim, self._alive).clone(memory_format=torch.contiguous_format)

    def random_actions(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """Uniformly random valid actions for every agent of every world (the action space's
        sample): discrete int64 [W, A], continuous float32 [W, A, action_dim] in [-1, 1]."""
        W, A = self.num_worlds, self.num_agents
        if self.continuous:
            return torch.rand(W, A, self.action_dim, generator=generator) * 2 - 1
        if self.enforce_action_mask:  # among the allowed actions only (envs/masking.py)
            with self._lock, torch.no_grad(), limited_threads(self.torch_threads):  # a committed state's mask
                return masking.sample_allowed(self._contract.action_mask(self._sim, self._alive), generator)
        return torch.randint(self.num_actions, (W, A), generator=generator)

    def check_actions(self, actions) -> torch.Tensor:
        """Validated actions on self.device (long [W, A] or float32 [W, A, action_dim]); raises
        TypeError / ValueError naming `actions`, the expected and the given, else changes nothing."""
        return checked_actions(actions, self.spec, self.device)

    @env_call
    def render_overview(self, resolution=None) -> torch.Tensor:
        """uint8 [W, H2, W2, 3]: one camera per world that sees the whole arena, for humans.

        Built on the first call (a second renderer with the same groups and free cameras);
        `resolution` (int or (H, W)) defaults to `overview_resolution` and rebuilds it if changed."""
        self._check_open(process=True)
        self._check_started()
        with limited_threads(self.torch_threads):
            return self.views.overview(self._sim, resolution)

    @env_call
    def state_observation(self) -> torch.Tensor:
        """float32 [W, A, state_dim]: the low-dimensional observation of the current state (obs
        key "state"), whether or not the env was built with state_obs=True."""
        self._check_open()
        self._check_started()
        if not self.state_dim:
            raise NotImplementedError(f"{type(self.scenario).__name__} has no state observation")
        with limited_threads(self.torch_threads):
            return self._state_obs(self._sim, self._alive)

    @env_call
    def heuristic_actions(self) -> torch.Tensor:
        """The scenario's scripted policy's actions for the current state (valid actions, as
        random_actions gives them): a reference that reads the state and beats random."""
        self._check_open()
        self._check_started()
        with limited_threads(self.torch_threads):
            actions = self.scenario.heuristic(self._sim, self._alive)
            try:
                return self.check_actions(actions)
            except (TypeError, ValueError) as error:
                raise type(error)(f"{type(self.scenario).__name__}.heuristic must return valid actions: "
                                  f"{error}") from error

    @env_call
    def get_state(self) -> dict:
        """Copies of the whole state as {name: tensor}: the fields of `sim` (the simulation),
        "step_count" [W] int64, "alive" [W, A] bool, "rng" (the generator's state, uint8, CPU) and,
        with appearance on, "appearance_ids" [W] int64 (CPU). set_state(state) restores it exactly:
        the steps that follow are bit-identical."""
        self._check_open()
        self._check_started()
        fields = {**explicit_state.fields(self._sim), **self._counters()}
        state = {name: value.clone() for name, value in fields.items()}
        state["rng"] = self.generator.get_state()
        return state

    @env_call
    def set_state(self, state: dict) -> None:
        """Restore a state from get_state() (of this env or one built with the same arguments),
        RNG included; the env then continues from it as if it had never left it.

        Every key must be there, each tensor of the current shape, dtype and device, floats
        finite, "step_count" >= 0 (and <= max_steps with autoreset on: past it a world would have
        been reset), and the fields of `sim` within the scenario's ``state_bounds()`` (positions
        inside the arena's walls, indices within their range) and its ``check_state`` rules; else
        TypeError / ValueError naming the key, and nothing changes."""
        self._check_open()
        template = {**explicit_state.fields(self._sim), **self._counters(), "rng": self.generator.get_state()}
        state = explicit_state.checked(state, template)
        steps = state["step_count"]
        most = self.max_steps if self.autoreset else MAX_COUNT  # without autoreset done worlds keep stepping
        if bool(((steps < 0) | (steps > most)).any()):
            bound = f"max_steps={self.max_steps} (autoreset={self.autoreset!r})" if self.autoreset else f"{most}"
            raise ValueError(f"state['step_count'] must be >= 0 and <= {bound}, got values in "
                             f"[{int(steps.min())}, {int(steps.max())}]")
        rng = state.pop("rng")
        step_count, alive = state.pop("step_count"), state.pop("alive")
        looks = state.pop("appearance_ids", None)  # with appearance on: any int64 is an id
        levels = state.pop("level_ids", None)
        book = self.episodes.checked(state)  # its keys out of `state`, checked
        if levels is not None:
            levels = level_sets.check_level_ids("state['level_ids']", levels, self.num_worlds)
            if looks is not None and not torch.equal(looks, levels):
                raise ValueError("state['appearance_ids'] must equal state['level_ids'] with levels on (a level "
                                 "fixes the look of its world)")
        self._contract.check_values(state, "state[{key!r}]")
        try:
            torch.Generator().set_state(rng)
        except RuntimeError as exc:
            raise ValueError(f"state['rng'] must be a torch.Generator state (from get_state()), got an invalid one: "
                             f"{exc}") from exc
        sim = type(self._sim)(**state)
        with limited_threads(self.torch_threads), self._all_or_nothing():
            if looks is not None:
                self.views.set_appearance(looks)
            self.views.sync(sim, full=True)  # per-episode instance data (landmarks, ...) changed too
            self.generator.set_state(rng)
            self._commit(sim=sim, alive=alive, step_count=step_count, looks=looks, levels=levels, needs_reset=False)
            self.episodes.restore(book)

    def close(self) -> None:
        """Release the renderers; safe to call twice. Any later use raises RuntimeError."""
        with self._lock:  # not env_call: finalisers at interpreter exit may find torch's modules gone
            if self._closed:
                return
            self._refuse_reentry()
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
        counters = {"step_count": self._step_count, "alive": self._alive}
        if self.appearance is not None:
            counters["appearance_ids"] = self._appearance_ids
        if self.levels is not None:
            counters["level_ids"] = self._level_ids
        return {**counters, **self.episodes.counters()}

    # ------------------------------------------------------------------ all or nothing (envs/atomic.py)
    def _generators(self) -> list:
        return [self.generator]

    def _save_more(self):
        return self.episodes.snapshot()  # the random ends and social tallies (envs/episodes.py)

    def _restore_more(self, saved) -> None:
        """The episode book as it was; the renderer may hold the undone state's instances: its next sync
        sends all; and the undone worlds' looks: the committed ones are put back."""
        self.episodes.restore(saved)
        self.views.invalidate()
        if self.appearance is not None and not self._needs_reset:  # before the first reset: none to keep
            self.views.set_appearance(self._appearance_ids)

    def _hooks_owner(self) -> str:
        return type(self.scenario).__name__

    def _held(self) -> dict:
        """{name: tensor} of the state the env has committed (what a failed call must leave as it was)."""
        return {**{f"state.{name}": value for name, value in explicit_state.fields(self._sim).items()},
                "alive": self._alive, "step_count": self._step_count}

    def _respawned(self, mask: torch.Tensor, sim, step_count: torch.Tensor, alive: torch.Tensor,
                   looks: torch.Tensor | None, levels: torch.Tensor | None, chosen=None) -> tuple:
        """(sim, step_count, alive, looks, levels) with a new episode in the worlds of mask [W] (spawn's
        state, checked; with levels on, the levels `chosen` [W] there (None: the level sampler's); with
        appearance on, new appearance ids there, which the renderer takes now)."""
        if levels is None:
            where = f"{type(self.scenario).__name__}.spawn"
            fresh = self.scenario.spawn(self.generator)
        else:
            where = f"{type(self.scenario).__name__}.spawn_level"
            if chosen is None:
                chosen = level_sets.check_level_ids(f"levels={self.levels!r}'s sample({self.num_worlds}, generator)",
                                                    self.levels.sample(self.num_worlds, self.generator),
                                                    self.num_worlds)
            levels = torch.where(mask.cpu(), chosen, levels)
            keys = level_sets.level_keys(levels, self.name, self.scenario.params, self.num_agents)
            fresh = self.scenario.spawn_level(level_sets.KeyedDraws(keys))
        fresh = self._contract.checked_state(where, fresh)
        self._contract.check_values(explicit_state.fields(fresh), where + "'s state.{key}")
        if looks is not None:  # drawn after spawn: the first layouts match those with appearance off
            fresh_ids = levels if levels is not None else torch.randint(
                -2 ** 63, 2 ** 63 - 1, (self.num_worlds,), generator=self.generator)
            looks = torch.where(mask.cpu(), fresh_ids, looks)
            self.views.set_appearance(looks, mask.cpu())
        self.episodes.start(mask, self.generator, levels)  # last: the draws above are those of a fixed end
        return (explicit_state.select_worlds(mask, fresh, sim),
                torch.where(mask, torch.zeros_like(step_count), step_count), alive | mask[:, None], looks, levels)

    def _check_open(self, process: bool = False):
        """Open, and with `process`, in the process that made it: else ForkedContextError now, before
        anything changes (the render at the end of a step would raise only after physics ran)."""
        if self._closed:
            raise RuntimeError(f"this {type(self.scenario).__name__} environment is closed; create a new one")
        if process:
            self.context.check_usable()

    def _check_started(self):
        if self._needs_reset:
            raise RuntimeError(f"call reset() before using this {type(self.scenario).__name__} environment")

    def _observe(self, sim, alive: torch.Tensor, full: bool) -> dict:
        """The observations of state `sim`: a render and the task's observation hooks, as tensors the
        caller owns (a hook may return its state's tensors or a constant; those are copied)."""
        try:
            self.views.sync(sim, full)
        except (TypeError, ValueError, RuntimeError, IndexError) as error:
            self._contract.name_non_finite(sim, error)
            raise
        frame = self.views.render()
        obs = {"pixels": frame.rgb.to(self.device)}  # a new tensor every render (BatchRenderer.render)
        if self.depth:
            obs["depth"] = frame.depth.clamp_(max=self.far).to(self.device)
        if self.state_obs:
            obs["state"] = self._state_obs(sim, alive)
        if self.lidar_rays:
            obs["lidar"] = self._contract.owned("lidar", self.scenario.lidar(sim, self.lidar_rays, self.lidar_range),
                                                self.lidar_rays)
        if self.agent_ids:
            obs["agent_id"] = self._ids.expand(self.num_worlds, -1, -1).clone()
        if self.vector_obs:
            obs.update(self._contract.vector_observations(sim, alive))
        if not self.continuous:
            mask = self._contract.action_mask(sim, alive)
            # The default hook makes a new tensor every call; a task's own may return a constant or a
            # field of its state, so its mask is copied. (Copying the default's too cost cartpole at
            # 1024 worlds hundreds of page faults a step: beside the frame's 12 MB, the extra small
            # allocations kept glibc from reusing the freed frames' memory.)
            fresh = self._contract.fresh_masks
            obs["action_mask"] = mask if fresh else mask.clone(memory_format=torch.contiguous_format)
        return obs

    def _state_obs(self, sim, alive: torch.Tensor) -> torch.Tensor:
        return self._contract.owned("observation", self.scenario.observation(sim, alive), self.state_dim)
