"""The public way to write a task: a scenario (the rules) and its scene binding (the pictures).

A task is a ``Scenario`` subclass. The driver (``BatchedEnv``, envs/core.py) owns everything
else: the renderer, the random generator, the step counters, who is still in the episode,
resets, autoreset, argument checks and the spec every front end reads. A scenario is built
once per env and then only answers questions about states it is handed; it never keeps one:

    class MyTask(Scenario):
        name = "my_task"
        Params = MyParams                     # a dataclass of the task's own keywords

        def setup(self):                      # once: who plays, actions, constants
            self.teams = {"agents": numbered("agent", self.num_agents)}
            self.discrete_actions(("noop", "left", "right"))
            self.state_dim = 4
        def initial_state(self): ...          # a state of the right shapes (zeros will do)
        def spawn_level(self, draws): ...     # a new episode in every world (or spawn(generator))
        def step(self, state, actions, alive, generator): ...  # -> (state, reward, terminated, info)
        def observation(self, state, alive): ...     # the "state" observation [W, A, state_dim]
        def build_scene(self, scene, overview): ...  # static geometry, groups, cameras
        def instances(self, state, full): ...        # {group: renderer.update kwargs}

States are frozen dataclasses of ``[W, ...]`` tensors (envs/state.py). ``step`` and ``spawn``
return new ones; the driver keeps the worlds a partial reset does not touch. Tasks of agents
moving on a floor subclass ``ArenaScenario`` (envs/arena.py) instead: it supplies bodies,
physics, cameras and the whole scene binding from declarations, so such a file holds only
rules. ``register_env`` (envs/registry.py) makes a task known to every front end.
"""
from __future__ import annotations

import abc
import dataclasses
import math
from typing import NamedTuple

import torch

from . import episodes, scenery
from . import state as explicit_state
from .levels import Draws, GeneratorDraws

STATE_LIMIT = 1e6  # default bound of float state fields in set_state: float32 math on them (squares, sums) stays finite
MAX_COUNT = 2 ** 62  # bound of counters that grow while a world keeps stepping without autoreset


@dataclasses.dataclass(frozen=True)
class NoParams:
    """The parameters of a task that has no keywords of its own."""


class BatchShape(NamedTuple):
    """The batch a scenario is built for (fixed for the env's lifetime)."""

    num_worlds: int
    num_agents: int
    continuous: bool
    device: torch.device


# Its name until issue 40, kept for user code ("layout" also names the renderer's packed-buffer table,
# marl_render/layout.py, and the frame's tiling, tiling.TileLayout).
Layout = BatchShape


class Step(NamedTuple):
    """What ``Scenario.step`` returns."""

    state: object  # the state one step later (a frozen dataclass of tensors)
    reward: torch.Tensor  # [W, A] float
    terminated: torch.Tensor  # [W, A] bool: agents whose episode ends with this step
    info: dict  # {name: [W] tensor} for each of the scenario's info_keys


class VectorObs(NamedTuple):
    """A per-agent vector observation a task declares (Scenario.vector_obs): float32 [W, A, width],
    with inclusive bounds (may be infinite)."""

    width: int
    low: float = -math.inf
    high: float = math.inf


def numbered(prefix: str, count: int) -> list:
    """Agent names prefix_0 .. prefix_{count-1} (PettingZoo's naming convention)."""
    return [f"{prefix}_{i}" for i in range(count)]


class Scenario(abc.ABC):
    """Base of every task; see the module docstring.

    Class attributes declare the task: ``name``, ``Params`` (a dataclass of its keywords with
    their defaults, validated in its ``__post_init__``), the default and allowed agent counts,
    episode length, resolution, the simulated seconds per step ``dt``, the physics terms it
    computes, its ``info_keys`` ({name: dtype}, each [W]) and its camera settings.

    After ``setup()`` these instance attributes describe it: ``teams`` (team -> agent names, in
    agent order), ``num_actions`` and ``action_meanings`` (discrete) or ``action_dim``
    (continuous), ``state_dim`` (0: no state observation) and ``physics`` (a
    planar.PhysicsConfig, or None).
    """

    name: str = "scenario"
    Params: type = NoParams
    default_num_agents: int = 1
    agent_range: tuple = (1, 64)  # allowed num_agents (inclusive)
    default_max_steps: int = 100
    # Named presets, difficulty="easy" | "medium" | "hard": make_env keywords (the task's Params or
    # the env's options) that explicit keywords override; "medium" is the defaults. {}: none.
    difficulties: dict = {}
    default_resolution = 64
    dt: float = 0.1  # simulated seconds per step (a front end plays episodes back at 1 / dt frames/s)
    physics_terms: frozenset = frozenset()  # envs/planar.py terms this task computes
    info_keys: dict = {}
    background: tuple = scenery.SKY_COLOR
    fov_y: float = math.radians(70.0)
    near: float = 0.05
    far: float = 50.0
    arena_half_extent: tuple = (1.5, 1.5)  # what the default overview camera frames
    overview_resolution: tuple = (128, 128)
    overview_fov_y: float = math.radians(60.0)
    shadow_bounds = None  # the box shadows=True covers; None: fitted to the static geometry
    opponents: tuple = ()  # teams that play against the others (random in the reference evaluation)
    step_hook: str = "step"  # the hook that holds the task's rules (what the driver's messages name)
    # Who plays besides the learners, and how the task is documented and trained (envs/roster.py):
    # data that the populations layer, the evaluation CLI, the trainer and the docs generator read.
    bots: dict = {}  # bot name -> roster.Bot (the heuristic itself is always in the "train" population)
    heldout: tuple = ()  # roster.HeldOut scenarios, named "<task>/<name>", played by "test" bots only
    sides: tuple = ()  # (team A, team B) of a competitive task: cross-play puts A's policies against B's
    card = ""  # the docs card's words: a roster.Card (prose, reward, episode end, meanings) or a str of prose
    training: dict = {}  # trainer defaults: Hyperparameters overrides, and "budget": {"pixels": N, "state": M}
    # A mixed-motive game (social dilemmas: commons, matrix, ...): its episodes report social outcomes
    # (envs/episodes.py; tagged_out says who is out of play) and end at random (episode_end).
    mixed_motive: bool = False
    episode_end: tuple | None = None  # (min_steps, interval, probability) of its random end; None: from max_steps
    schelling: tuple = ()  # (cooperator bot, defector bot) a Schelling diagram plays (baselines/schelling.py)

    def __init__(self, params, batch: BatchShape):
        self.params = params
        self.num_worlds, self.num_agents, self.continuous, self.device = batch
        self.teams: dict = {"agents": numbered("agent", self.num_agents)}
        self.num_actions: int | None = None
        self.action_meanings: tuple | None = None
        self.action_dim: int | None = None
        self.state_dim: int = 0
        # Small per-agent vectors every env gives beside the pixels (obs keys, float32 [W, A, width]),
        # declared in setup as {key: VectorObs(width, low, high)} and given by vector_observations.
        self.vector_obs: dict = {}
        self.physics = None
        self.setup()

    @classmethod
    def num_agents_for(cls, params, num_agents: int | None) -> int | None:
        """The agent count to build for, given the user's num_agents (None: not given). A task whose
        own keywords imply it (tag's team sizes) overrides this; None means the default."""
        return num_agents

    # ------------------------------------------------------------------ declarations
    def discrete_actions(self, meanings) -> None:
        """Declare the discrete actions by their names; continuous envs ignore this."""
        if not self.continuous:
            self.num_actions, self.action_meanings = len(meanings), tuple(meanings)

    def continuous_actions(self, dim: int) -> None:
        """Declare a continuous action of `dim` values in [-1, 1]; discrete envs ignore this."""
        if self.continuous:
            self.action_dim = dim

    @property
    def agent_names(self) -> list:
        """Every agent's name, team after team in the order of ``teams``."""
        return [name for names in self.teams.values() for name in names]

    # ------------------------------------------------------------------ rules
    @abc.abstractmethod
    def setup(self) -> None:
        """Declare teams, actions, state_dim and the task's constants (once, at construction)."""

    @abc.abstractmethod
    def initial_state(self):
        """A state of the right shapes and dtypes, before any episode (zeros will do): it is the
        template set_state checks against."""

    def spawn(self, generator: torch.Generator):
        """A new episode in every world, sampled with `generator` (the driver keeps it only in the
        worlds being reset). By default spawn_level's draws from the generator; a task may override
        this instead of spawn_level (it then has no levels: see envs/levels.py)."""
        if type(self).spawn_level is Scenario.spawn_level:
            raise NotImplementedError(f"{type(self).__name__} must implement spawn_level(draws) or spawn(generator)")
        return self.spawn_level(GeneratorDraws(generator))

    def spawn_level(self, draws: Draws):
        """A new episode in every world, every random number drawn from `draws` (envs/levels.py:
        draws.rand / randn / randint(stream, ...), the worlds first, one stream name per purpose).
        With levels= the draws of world w are a pure function of its level id; without, they are
        the env's generator's, in call order."""
        raise NotImplementedError(f"{type(self).__name__} has no spawn_level(draws), so no levels")

    @classmethod
    def episode_end_description(cls) -> str:
        """Which end the task's episodes have by default, for its card: "fixed: ..." or "random ..."."""
        return episodes.describe_end(cls)

    @classmethod
    def has_levels(cls) -> bool:
        """Whether the task draws its resets from a Draws (spawn_level), as levels= needs: the most
        derived of spawn / spawn_level is spawn_level (a subclass that overrides spawn(generator)
        of a task with levels has none: its spawn would be bypassed)."""
        for klass in cls.__mro__:
            if "spawn_level" in vars(klass):
                return klass is not Scenario
            if "spawn" in vars(klass):
                return False
        return False

    @abc.abstractmethod
    def step(self, state, actions: torch.Tensor, alive: torch.Tensor, generator: torch.Generator) -> Step:
        """The state one step later for validated actions; agents with alive [W, A] False left the
        episode and must be ignored. Anything random is drawn from `generator` (the env's)."""

    def observation(self, state, alive: torch.Tensor) -> torch.Tensor:
        """[W, A, state_dim] float: the low-dimensional observation (obs key "state")."""
        raise NotImplementedError(f"{type(self).__name__} has no state observation")

    def vector_observations(self, state, alive: torch.Tensor) -> dict:
        """{key: [W, A, width] float} for each key of vector_obs (declared in setup); default none."""
        return {}

    def tagged_out(self, state) -> torch.Tensor:
        """[W, A] bool: agents out of play (tagged, zapped) in `state`, for the social outcome "peace"
        of mixed-motive tasks (envs/episodes.py); default: nobody."""
        return torch.zeros(self.num_worlds, self.num_agents, dtype=torch.bool, device=self.device)

    def action_mask(self, state, alive: torch.Tensor) -> torch.Tensor:
        """[W, A, num_actions] bool; default: every action valid."""
        return torch.ones(self.num_worlds, self.num_agents, self.num_actions, dtype=torch.bool, device=self.device)

    def state_bounds(self) -> dict:
        """{field of the state: (low, high)} that set_state enforces (low / high: a number, or one per
        index of the field's last axis). Default: every floating field within +-STATE_LIMIT (1e6), so
        that nothing overflows float32; a task narrows the fields that have a meaning (positions
        within its walls, timers within their delay)."""
        return {name: (-STATE_LIMIT, STATE_LIMIT) for name, value in explicit_state.fields(self.initial_state()).items()
                if value.is_floating_point()}

    def check_state(self, state: dict) -> None:
        """Raise ValueError naming the field where `state` ({field: tensor}) breaks a rule of the task
        that the ranges of state_bounds cannot say (which team may carry which flag, a counter that
        must agree with another). set_state and every spawn are checked with it; default: no rule."""
        return None

    def check_declarations(self, state) -> None:
        """Raise naming the declaration where the task's declarations disagree with each other, once
        when the env is built, given initial_state() (ArenaScenario checks its obstacles against
        physics_terms and its props against the state's fields); default: nothing to check."""
        return None

    def heuristic(self, state, alive: torch.Tensor) -> torch.Tensor:
        """Actions of a scripted policy that reads the state: a reference that beats random."""
        raise NotImplementedError(f"{type(self).__name__} has no scripted heuristic")

    def lidar(self, state, rays: int, reach: float | None) -> torch.Tensor:
        """[W, A, rays] float in [0, 1]: the "lidar" observation (EnvOptions.lidar), distances to the
        first hit along `rays` rays divided by `reach`. Arena tasks have it (envs/arena.py)."""
        raise ValueError(f"lidar applies to tasks with planar geometry (ArenaScenario); {self.name} has none")

    @classmethod
    def has_lidar(cls) -> bool:
        """Whether the task can give the lidar observation."""
        return cls.lidar is not Scenario.lidar

    @property
    def physics_compiled(self) -> bool:
        """Whether step() runs a compiled kernel now (see compile_physics)."""
        return False

    def compile_physics(self) -> bool:
        """Switch step() to a compiled kernel (EnvOptions.compile_physics, envs/compiled.py) whose
        results stay within 1e-12 of the default path's; returns whether compiling succeeded
        (False: the default path stays). A task that has such a kernel overrides this."""
        raise ValueError(f"compile_physics applies to tasks with a compiled physics kernel; {self.name} has none")

    # ------------------------------------------------------------------ scene binding
    @abc.abstractmethod
    def build_scene(self, scene, overview: bool) -> None:
        """Add static geometry and instance groups to `scene`; mount the agents' cameras unless
        `overview` (one free camera per world, placed by place_cameras)."""

    @abc.abstractmethod
    def instances(self, state, full: bool) -> dict:
        """{group: renderer.update kwargs} of `state`. full=False: only what a step can change
        (poses); full=True: everything (after a reset, for a new renderer)."""

    def place_cameras(self, renderer, overview: bool) -> None:
        """Place free cameras once, after the renderer is built. Default: nothing for mounted
        agent cameras, overview_camera() for the overview."""
        if overview:
            eye, target = self.overview_camera()
            W = self.num_worlds
            renderer.set_cameras(position=eye.expand(W, 1, 3), look_at=target.expand(W, 1, 3))

    def overview_camera(self):
        """(eye [3], target [3]) float64 of the overview camera (the same in every world)."""
        return scenery.top_down_camera(self.arena_half_extent, self.overview_fov_y)
