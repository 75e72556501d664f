"""The arena: agents on capsule bodies on a walled floor, each seeing through its own camera.

spread, forage, tag, push and the newer tasks are scenarios over this one arena, in the way of
MPE's and VMAS's scenarios. ``ArenaScenario`` supplies what they share: teams of agents, their
bodies and planar physics (envs/planar.py), egocentric movement (envs/egomotion.py), the body
and nose meshes with the mounted cameras, and the scene binding. A task declares the rest of
its scene as data, so its file holds only rules:

    def setup(self):                         # once
        self.setup_arena({"agents": numbered("agent", self.num_agents)}, state_dim=..., radius=0.15,
                         max_speed=2.0)
    def initial_state(self): return self.at_rest(zeros [W, A, 2], zeros [W, A], landmarks=zeros [W, L, 2])
    def spawn_level(self, draws): ...        # a new episode in every world, e.g. by at_rest(...)
    def rules(self, before, moved, actions, alive, generator):  # -> (state, reward, terminated, info)
    def props(self):                         # what else is drawn, and which state field it follows
        return [Prop("landmarks", disc_mesh(), count=L, position="landmarks", height=0.02, ...)]

``rules`` gets the state before the step, the state once the bodies moved (``moved``: new
pos, vel, yaw; the task's own fields unchanged) and the actions (a task's own actions beyond
movement, declared with ``setup_arena(extra_actions=...)``, are read there). Bodies 0 .. A-1
are the agents; a task may add more after them (push's ball) with ``setup_arena(bodies=...)``.
The state is an ``ArenaState`` subclass with the task's own fields (envs/state.py).
"""
from __future__ import annotations

import abc
import dataclasses
import math

import torch
from torch import Tensor

import marl_render as mr
from marl_render.util.validation import describe, positive_float, positive_int

from . import egomotion, planar, scenery, sight
from .scenario import Scenario, Step, numbered

__all__ = ["ArenaScenario", "ArenaState", "Prop", "Static", "numbered"]

AGENT_HEIGHT = 0.5
EYE_HEIGHT = 0.4  # the mounted camera's height above the floor (m)
CAMERA_PITCH = -0.2  # rad, looking slightly down
NOSE_HEIGHT = 0.3  # a small dark "nose" box shows others which way a body faces
NOOP = 0  # egomotion.ACTION_MEANINGS[0]: the action a "lazy" bot plays
NOSE_SIZE = (0.08, 0.12, 0.08)
NOSE_COLOR = (0.1, 0.1, 0.12)


@dataclasses.dataclass(frozen=True)
class ArenaState:
    """The arena's part of the simulation state; a task subclasses it with its own fields."""

    pos: Tensor  # [W, B, 2] body centres (m): the agents, then the task's other bodies
    vel: Tensor  # [W, B, 2] body velocities (m/s)
    active: Tensor  # [W, B] bool: bodies that move and collide (agents still in the episode)
    yaw: Tensor  # [W, A] the agents' headings (rad; 0 faces +y, as their cameras do)


@dataclasses.dataclass(frozen=True)
class Prop:
    """Objects drawn at places the state says: one instance group of `count` per world.

    position, yaw and active name a field of the state (or are functions of the state):
    position [W, count, 2] planar centres (m), yaw [W, count] (rad), active [W, count] bool (shown).
    scale and color are (3,) for all or [count, 3] each (full sizes in m; RGB in [0, 1]), or name a
    field [W, count, 3] of the state (or are functions of it) where they differ between worlds or
    change during an episode (then sent every step, unless moves=False).
    moves=False: the fields change only when an episode starts, so they are sent only then."""

    name: str
    mesh: object  # a mesh name ("box", "sphere", ...) or a marl_render.MeshData
    count: int
    position: object
    height: float  # z of the centres (m)
    scale: object = (1.0, 1.0, 1.0)
    color: object = (0.8, 0.8, 0.8)
    yaw: object = None
    active: object = None
    moves: bool = True
    hidden_from: int | None = None  # an agent whose camera does not see these objects (all others do)
    role: str | None = None  # "floor" or "wall": takes each world's floor / wall look (appearance effect)


@dataclasses.dataclass(frozen=True)
class Static:
    """Static geometry, the same in every world: positions, scales and colours are [n, 3]."""

    name: str
    mesh: object
    position: object
    scale: object
    color: object
    role: object = None  # None, "floor", "wall" or one per instance: marl_render.Scene.add_static's role


def _from_state(source) -> bool:
    return isinstance(source, str) or callable(source)


def _read(state, source) -> Tensor:
    return source(state) if callable(source) else getattr(state, source)


class ArenaScenario(Scenario):
    """Base of the arena tasks; see the module docstring."""

    State = ArenaState  # the task's state class
    dt = egomotion.DT
    fov_y = math.radians(90.0)
    near = 0.05
    far = 20.0
    thrust = egomotion.THRUST  # N at full forward action (a task may set one per agent, [A])
    team_colors = scenery.TEAM_COLORS
    shown: str | None = None  # a bool [W, A] state field: agents drawn (default: all, always)
    step_hook = "rules"

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "shadow_bounds" not in cls.__dict__:  # shadows=True covers the arena and its walls
            cls.shadow_bounds = scenery.arena_shadow_bounds(cls.arena_half_extent)

    # ------------------------------------------------------------------ declarations
    def setup_arena(self, teams: dict, *, state_dim: int, radius, max_speed: float, substeps: int = 2,
                    bodies: tuple = (), extra_actions: tuple = ()) -> None:
        """Declare who plays and how bodies move (first thing in a task's setup).

        teams: team -> agent names, in agent order. radius: of the agents' bodies (m), a float or
        {team: float}. bodies: (radius, mass) of each further body after the agents.
        extra_actions: names of the task's own actions beyond movement: discrete actions 5, 6, ...
        (they do not move the body), or continuous values 2, 3, ... (in [-1, 1]); rules reads them."""
        where = f"{type(self).__name__}.setup_arena"
        if not (isinstance(teams, dict) and all(isinstance(team, str) and not isinstance(names, str)
                                                 and all(isinstance(n, str) for n in names)
                                                 for team, names in teams.items())):
            raise TypeError(f"{where}: teams must be a dict {{team name: [agent names]}}, got {teams!r}")
        count = sum(len(names) for names in teams.values())
        if count != self.num_agents:
            raise ValueError(f"{where}: teams hold {count} agents but the env is built for num_agents="
                             f"{self.num_agents}; a task whose own keywords set its team sizes must also say so "
                             f"in num_agents_for (see envs/tag.py), so that the env is built for that count")
        self.teams = teams
        self._team_of = [team for team, names in teams.items() for _ in names]
        self.discrete_actions(egomotion.ACTION_MEANINGS + tuple(extra_actions))
        self.continuous_actions(2 + len(extra_actions))
        still = ((0.0, 0.0),) * len(extra_actions)
        self.action_table = torch.tensor(egomotion.DISCRETE_ACTIONS + still, device=self.device)
        self.state_dim = state_dim
        W, N = self.num_worlds, self.num_agents
        agent_radius = [radius[team] if isinstance(radius, dict) else radius for team in self._team_of]
        radii = agent_radius + [r for r, _ in bodies]
        self.physics = planar.PhysicsConfig(
            dt=egomotion.DT, substeps=substeps, terms=self.physics_terms, restitution=0.5, drag=egomotion.DRAG,
            arena_half_extent=self.arena_half_extent, max_speed=max_speed, min_body_radius=min(radii))
        self.radius = torch.tensor(radii, device=self.device)  # [B]
        self.mass = torch.tensor([1.0] * N + [m for _, m in bodies], device=self.device)
        # The other agents of each agent [A, A-1], in the order of the state observation.
        self.others = torch.tensor([[j for j in range(N) if j != i] for i in range(N)],
                                   dtype=torch.long, device=self.device).reshape(N, N - 1)
        # Constant instance data (CPU, for the renderer): bodies are one mesh scaled to each radius.
        self._mesh_radius = max(agent_radius)
        xy = torch.tensor(agent_radius)[:, None] / self._mesh_radius
        self._agent_scale = torch.cat((xy, xy, torch.ones(N, 1)), 1).expand(W, N, 3)
        # A team without a colour in team_colors takes the palette's, in team order.
        fallback = dict(zip(teams, scenery.palette(len(teams)).tolist(), strict=True))
        colors = [self.team_colors.get(team, fallback[team]) for team in self._team_of]
        self._agent_color = torch.tensor(colors, dtype=torch.float32).expand(W, N, 3)
        self._nose_offset = torch.tensor(agent_radius)[:, None]  # [N, 1]
        self._nose_scale = torch.tensor(NOSE_SIZE).expand(W, N, 3)
        self._nose_color = torch.tensor(NOSE_COLOR).expand(W, N, 3)
        self._owner = torch.arange(N).expand(W, N)
        self._all_agents = torch.ones(W, N, dtype=torch.bool)
        self._props = None  # the declared props and statics, read on the first scene build

    def per_agent(self, values: dict) -> Tensor:
        """[A] float32 on the env's device: each agent's value of its team in {team: value}."""
        return torch.tensor([values[team] for team in self._team_of], device=self.device)

    def at_rest(self, pos: Tensor, yaw: Tensor, **extra) -> ArenaState:
        """A state (of class State) with the bodies at pos [W, B, 2], still and active, the agents
        facing yaw [W, A], and the task's own fields `extra`; all on the env's device."""
        unknown = sorted(set(extra) - {field.name for field in dataclasses.fields(self.State)})
        if unknown:
            raise TypeError(f"{type(self).__name__}.State is {self.State.__name__}, which has no field(s) {unknown}: "
                            f"declare State = your dataclass subclass of ArenaState with them (envs/arena.py)")
        pos = pos.to(self.device)
        return self.State(pos=pos, vel=torch.zeros_like(pos), active=torch.ones_like(pos[..., 0], dtype=torch.bool),
                          yaw=yaw.to(self.device), **{name: value.to(self.device) for name, value in extra.items()})

    def props(self) -> list:
        """The task's Prop and Static declarations, drawn in this order after the agents."""
        return []

    def state_bounds(self) -> dict:
        """Body centres inside the walls (the step clamps them there anyway); see Scenario."""
        return {**super().state_bounds(), "pos": self.inside_walls()}

    def inside_walls(self) -> tuple:
        """(low, high) per axis of a point inside the arena's walls, for state_bounds."""
        hx, hy = self.arena_half_extent
        return (-hx, -hy), (hx, hy)

    # ------------------------------------------------------------------ rules (the task's)
    @abc.abstractmethod
    def rules(self, before: ArenaState, moved: ArenaState, actions: Tensor, alive: Tensor,
              generator: torch.Generator):
        """(state, reward [W, A], terminated [W, A] bool, info) of the step, given the state before
        it, the state once the bodies moved, the validated actions, who took part (alive [W, A]) and
        the env's generator (for anything random in the step)."""

    def obstacles(self, state: ArenaState) -> planar.Obstacles | None:
        """Static boxes of the physics (none unless the task has some)."""
        return None

    def frozen(self, state: ArenaState) -> Tensor | None:
        """[W, A] bool: agents held where they are for the coming step, e.g. seekers while hiders hide.
        A frozen agent neither turns nor moves whatever its action, keeps no velocity, and others bump
        into it as into a wall; rules still gets its action (mask what it may not do with action_mask).
        None (the default): nobody is frozen."""
        return None

    # ------------------------------------------------------------------ dynamics
    def bodies(self, state: ArenaState, active: Tensor) -> planar.BodyState:
        """The physics view of `state`, with `active` [W, B] bodies."""
        W, B = state.pos.shape[:2]
        return planar.BodyState(state.pos, state.vel, self.radius.expand(W, B), self.mass.expand(W, B), active)

    def step(self, state, actions, alive, generator) -> Step:
        command = actions[..., :2] if self.continuous else self.action_table[actions]
        frozen = self._frozen(state)
        moving = alive if frozen is None else alive & ~frozen
        yaw, force = egomotion.drive(state.yaw, command, moving, self.thrust, self.physics.dt)
        active, extra = alive, self.radius.shape[0] - self.num_agents
        if extra:  # further bodies (push's ball) feel no force and always take part
            force = torch.cat((force, force.new_zeros(self.num_worlds, extra, 2)), 1)
            active = torch.cat((alive, alive.new_ones(self.num_worlds, extra)), 1)
        bodies = self.bodies(state, active)
        if frozen is not None:  # an immovable body (planar.py: infinite mass) for this step
            held = torch.cat((frozen, frozen.new_zeros(self.num_worlds, extra)), 1)
            bodies = bodies._replace(mass=torch.where(held, math.inf, bodies.mass))
        obstacles = self.obstacles(state)
        self._check_obstacles(obstacles)
        bodies = planar.step(bodies, force, obstacles, self.physics)
        moved = dataclasses.replace(state, pos=bodies.pos, vel=bodies.vel, active=bodies.active, yaw=yaw)
        result = self.rules(state, moved, actions, alive, generator)
        if not (isinstance(result, tuple) and len(result) == 4):
            raise TypeError(f"{type(self).__name__}.rules must return (state, reward, terminated, info), got "
                            f"{describe(result)}")
        return Step(*result)

    def _check_obstacles(self, obstacles) -> None:
        """Boxes the physics would ignore are refused: drawn (by a Prop) but not solid is a silent bug;
        so are boxes of one world broadcast to all, and negative (or NaN) half extents, which the
        physics takes as no box."""
        if obstacles is None:
            return
        where, W = f"{type(self).__name__}.obstacles", self.num_worlds
        K = obstacles.center.shape[1] if isinstance(obstacles, planar.Obstacles) and obstacles.center.dim() == 3 else 0
        want = f"None or planar.Obstacles(center [{W}, K, 2], half_extent [{W}, K, 2], angle [{W}, K]) of float tensors"
        if not (isinstance(obstacles, planar.Obstacles) and all(
                isinstance(part, Tensor) and part.is_floating_point() and part.device == self.device
                for part in obstacles) and tuple(obstacles.center.shape) == (W, K, 2)
                and tuple(obstacles.half_extent.shape) == (W, K, 2) and tuple(obstacles.angle.shape) == (W, K)):
            given = (", ".join(f"{field}: {describe(part)}" for field, part in obstacles._asdict().items())
                     if isinstance(obstacles, planar.Obstacles) else describe(obstacles))
            raise ValueError(f"{where} must return {want} on {self.device}, got {given}")
        if K and not bool((obstacles.half_extent >= 0).all()):
            raise ValueError(f"{where}'s half_extent must be >= 0 (the box's half sizes along its own x and y), "
                             f"got values in [{obstacles.half_extent.min().item():g}, "
                             f"{obstacles.half_extent.max().item():g}]")
        if "obstacles" not in self.physics.terms and K:
            raise ValueError(f"{type(self).__name__}.obstacles returns {obstacles.center.shape[1]} box(es) but "
                             f"physics_terms {sorted(self.physics.terms)} has no 'obstacles': add it, or the "
                             f"bodies pass through them")

    def check_declarations(self, state) -> None:
        """The physics was declared (setup_arena), its obstacles are solid, and every prop and the
        shown field read fields of the state that exist, with the shapes they need."""
        name = type(self).__name__
        if self.physics is None:
            raise RuntimeError(f"{name}.setup must call setup_arena(teams, ...) (envs/arena.py)")
        self._check_obstacles(self.obstacles(state))
        W, A = self.num_worlds, self.num_agents
        if self.shown is not None:
            _check_source(state, self.shown, (W, A), torch.bool, f"{name}.shown")
        for item in self._declared():
            if not isinstance(item, Prop):
                continue
            where = f"{name}.props: Prop {item.name!r}"
            positive_int(f"{where}'s count", item.count)
            _check_source(state, item.position, (W, item.count, 2), "float", f"{where}'s position")
            if item.yaw is not None:
                _check_source(state, item.yaw, (W, item.count), "float", f"{where}'s yaw")
            if item.active is not None:
                _check_source(state, item.active, (W, item.count), torch.bool, f"{where}'s active")
            for what in ("scale", "color"):
                value = getattr(item, what)
                if _from_state(value):
                    _check_source(state, value, (W, item.count, 3), "float", f"{where}'s {what}")
                else:
                    try:
                        _per_instance(value, W, item.count)
                    except (TypeError, ValueError, RuntimeError) as error:
                        raise ValueError(f"{where}'s {what} must be (3,) for all or [{item.count}, 3] (one per "
                                         f"object), or name a field of the state; got {describe(value)}") from error

    def _frozen(self, state) -> Tensor | None:
        """frozen(state), checked: the hook's mistake is named here, not inside the physics."""
        frozen = self.frozen(state)
        W, A = self.num_worlds, self.num_agents
        if frozen is not None and not (isinstance(frozen, Tensor) and frozen.dtype == torch.bool
                                       and tuple(frozen.shape) == (W, A) and frozen.device == self.device):
            raise ValueError(f"{type(self).__name__}.frozen must return None or a bool tensor of shape [{W}, {A}] "
                             f"on {self.device}, got {describe(frozen)}")
        return frozen

    # ------------------------------------------------------------------ what agents see
    def sees(self, state: ArenaState, targets, *, fov: float | None = None, reach: float | None = None) -> Tensor:
        """[W, A, T] bool: whether each agent sees each target, batched (envs/sight.py): the target lies
        within the horizontal field of view `fov` (rad) of the agent's heading and `reach` metres of its
        centre, and no wall, obstacle box (obstacles(state)) or immovable body (a body of infinite mass:
        a pillar) crosses the line between them. Other agents do not hide a target.

        targets: points [W, T, 2]; the name of a Prop (its instances; inactive ones are never seen); or
        "agents" (T = A; an agent never sees itself, nor agents that are not taking part or not shown).
        fov: default the cameras' at a square resolution, horizontal_fov() (90 degrees); reach: default
        the cameras' far plane. Both are the rules' to choose, independent of the rendering options."""
        A = self.num_agents
        fov = self.horizontal_fov() if fov is None else positive_float("fov", fov)
        reach = self.far if reach is None else positive_float("reach", reach)
        if fov > 2 * math.pi:
            raise ValueError(f"fov must be a finite number in (0, 2 pi] (radians), got {fov}")
        name = targets if isinstance(targets, str) else None
        if name is not None:
            targets, present = self._targets(state, name)
        elif not (isinstance(targets, Tensor) and targets.ndim == 3 and targets.shape[0] == self.num_worlds
                  and targets.shape[2] == 2 and targets.is_floating_point()):
            raise ValueError(f"targets must be float points [{self.num_worlds}, T, 2], 'agents' or a Prop's name, "
                             f"got {describe(targets)}")
        seen = sight.line_of_sight(state.pos[:, :A], state.yaw, targets, fov=fov, reach=reach,
                                   half_extent=self.arena_half_extent, boxes=self.obstacles(state),
                                   circles=self._pillars(state))
        if name is not None:
            seen = seen & present[:, None]
        if name == "agents":
            seen = seen & ~torch.eye(A, dtype=torch.bool, device=self.device)
        return seen

    def horizontal_fov(self, aspect: float = 1.0) -> float:
        """The agents' cameras' horizontal field of view (rad) at a view `aspect` = width / height, for
        points at eye height (envs/sight.py): 90 degrees for the arena's square views."""
        return sight.horizontal_fov(self.fov_y, aspect, CAMERA_PITCH)

    def lidar(self, state: ArenaState, rays: int, reach: float | None) -> Tensor:
        """[W, A, rays] in [0, 1] (the "lidar" observation, EnvOptions.lidar): along `rays` rays from each
        agent's centre, ray 0 along its heading and the others evenly around it counter-clockwise, the
        distance to the first wall, obstacle box or other body taking part (and shown), divided by
        `reach` (default: the arena's diagonal) and capped at 1: 1 means nothing within reach."""
        W, A = self.num_worlds, self.num_agents
        reach = 2 * math.hypot(*self.arena_half_extent) if reach is None else reach
        bodies = self.bodies(state, state.active)
        present = bodies.active.clone()
        if self.shown is not None:
            present[:, :A] &= getattr(state, self.shown)
        bodies = sight.Circles(bodies.pos, bodies.radius, present)
        own = torch.eye(A, self.radius.shape[0], dtype=torch.bool, device=self.device).expand(W, A, -1)
        return sight.lidar(state.pos[:, :A], state.yaw, rays=rays, reach=reach, half_extent=self.arena_half_extent,
                           boxes=self.obstacles(state), circles=bodies, skip=own).to(torch.float32)

    def _pillars(self, state) -> sight.Circles | None:
        """The immovable bodies (infinite mass) taking part, as occluders; None when the task has none."""
        if getattr(self, "_pillar_index", None) is None:  # the masses are constants: found once
            self._pillar_index = torch.isinf(self.mass).nonzero()[:, 0]
        index = self._pillar_index
        if not len(index):
            return None
        bodies = self.bodies(state, state.active)
        return sight.Circles(bodies.pos[:, index], bodies.radius[:, index], bodies.active[:, index])

    def _targets(self, state, name: str) -> tuple:
        """(positions [W, T, 2], present [W, T] bool) of the agents or of the Prop called `name`."""
        A = self.num_agents
        if name == "agents":
            present = state.active[:, :A]
            return state.pos[:, :A], present if self.shown is None else present & getattr(state, self.shown)
        props = {prop.name: prop for prop in self._declared() if isinstance(prop, Prop)}
        if name not in props:
            raise ValueError(f"targets must be points [W, T, 2], 'agents' or the name of a Prop of {self.name} "
                             f"({sorted(props)}), got {name!r}")
        prop = props[name]
        position = _read(state, prop.position)
        if prop.active is None:
            return position, torch.ones_like(position[..., 0], dtype=torch.bool)
        return position, _read(state, prop.active)

    # ------------------------------------------------------------------ scene binding
    def build_scene(self, scene: mr.Scene, overview: bool) -> None:
        scenery.add_arena(scene, self.arena_half_extent)
        N = self.num_agents
        scene.add_group("agents", scenery.agent_mesh(self._mesh_radius, AGENT_HEIGHT), capacity=N)
        scene.add_group("noses", "box", capacity=N)
        if not overview:
            scene.mount_cameras("agents", instance=range(N), offset=(0.0, 0.0, EYE_HEIGHT - AGENT_HEIGHT / 2),
                                pitch=CAMERA_PITCH)
        for item in self._declared():
            if isinstance(item, Static):
                scene.add_static(item.name, item.mesh, position=item.position, scale=item.scale, color=item.color,
                                 role=item.role)
            else:
                scene.add_group(item.name, item.mesh, capacity=item.count, role=item.role)

    def instances(self, state, full: bool) -> dict:
        pos = state.pos[:, :self.num_agents].to("cpu", torch.float32)
        yaw = state.yaw.cpu()
        rotation = scenery.yaw_quat(yaw)
        nose = pos + self._nose_offset * scenery.heading(yaw)
        update = {"agents": {"position": scenery.planar_to_3d(pos, AGENT_HEIGHT / 2), "rotation": rotation},
                  "noses": {"position": scenery.planar_to_3d(nose, NOSE_HEIGHT), "rotation": rotation}}
        if full:
            update["agents"].update(color=self._agent_color, scale=self._agent_scale, active=self._all_agents)
            update["noses"].update(color=self._nose_color, scale=self._nose_scale, active=self._all_agents,
                                   owner=self._owner)
        if self.shown is not None:
            update["agents"]["active"] = update["noses"]["active"] = getattr(state, self.shown).cpu()
        for prop, constant in self._declared_props():
            if not (full or prop.moves):
                continue
            kwargs = {"position": scenery.planar_to_3d(_read(state, prop.position).to("cpu", torch.float32),
                                                       prop.height)}
            if prop.yaw is not None:
                kwargs["rotation"] = scenery.yaw_quat(_read(state, prop.yaw).cpu())
            if prop.active is not None:
                kwargs["active"] = _read(state, prop.active).cpu()
            for what in ("scale", "color"):
                if what not in constant:
                    kwargs[what] = _read(state, getattr(prop, what)).to("cpu", torch.float32)
            if full:
                kwargs = {**constant, **kwargs}
            update[prop.name] = kwargs
        return update

    def _declared(self) -> list:
        if self._props is None:
            self._props = list(self.props())
        return self._props

    def _declared_props(self):
        """(Prop, its constant instance data) of each declared prop, built once."""
        if getattr(self, "_prop_data", None) is None:
            W, data = self.num_worlds, []
            for prop in self._declared():
                if isinstance(prop, Prop):
                    constant = {what: _per_instance(value, W, prop.count) for what, value in
                                (("scale", prop.scale), ("color", prop.color)) if not _from_state(value)}
                    if prop.active is None:
                        constant["active"] = torch.ones(W, prop.count, dtype=torch.bool)
                    if prop.hidden_from is not None:
                        constant["owner"] = torch.full((W, prop.count), prop.hidden_from, dtype=torch.int64)
                    data.append((prop, constant))
            self._prop_data = data
        return self._prop_data

    # ------------------------------------------------------------------ observation helpers
    def own_obs(self, state) -> Tensor:
        """[W, A, 6]: each agent's position (2), velocity (2), cos and sin of its yaw; world frame."""
        N = self.num_agents
        return torch.cat((state.pos[:, :N], state.vel[:, :N], torch.cos(state.yaw)[..., None],
                          torch.sin(state.yaw)[..., None]), -1)

    def relative(self, state, points: Tensor) -> Tensor:
        """[W, A, K, 2]: points [W, K, 2] relative to each agent."""
        return points[:, None] - state.pos[:, :self.num_agents, None]

    def others_obs(self, state) -> Tensor:
        """[W, A, A-1, 2]: the other agents' positions relative to each agent, in `others` order."""
        pos = state.pos[:, :self.num_agents]
        return pos[:, self.others] - pos[:, :, None]

    def steer_to(self, state, target: Tensor, reach: float = 0.0) -> Tensor:
        """Heuristic helper: egocentric actions that drive each agent towards target [W, A, 2]: turn
        until it faces the target within 0.3 rad, then forward (noop within `reach`). Discrete
        int64 [W, A] or continuous float32 [W, A, 2], as the env's actions are."""
        N = self.num_agents
        delta = target - state.pos[:, :N]
        bearing = torch.atan2(-delta[..., 0], delta[..., 1])  # yaw 0 faces +y; yaw > 0 turns left
        error = scenery.wrap_angle(bearing - state.yaw)
        near = torch.linalg.vector_norm(delta, dim=-1) <= reach
        if self.continuous:
            turn = (error / 0.5).clamp(-1, 1)
            thrust = torch.where(error.abs() < 0.6, torch.ones_like(turn), torch.zeros_like(turn))
            thrust = torch.where(near, torch.zeros_like(thrust), thrust)
            return torch.stack((thrust, turn), -1).to(torch.float32)
        action = torch.where(error > 0, 2, 3)  # turn left / right
        action = torch.where(error.abs() < 0.3, 1, action)  # forward
        return torch.where(near, 0, action).to(torch.int64)


def wander(env) -> Tensor:
    """A bot script (envs/roster.py) of every arena task: each agent drives round a circle of its own
    phase (half the arena's extent), covering the arena without looking at anything."""
    s = env.scenario
    hx, hy = s.arena_half_extent
    phase = torch.arange(env.num_agents) * (2 * math.pi / env.num_agents) + env.step_count[:, None].cpu() * 0.03
    target = torch.stack((0.5 * hx * torch.cos(phase), 0.5 * hy * torch.sin(phase)), -1).to(env.device)
    return s.steer_to(env.sim, target)

def _check_source(state, source, shape: tuple, dtype, what: str) -> None:
    """A Prop's (or shown's) source: a field of `state` (or a function of it) giving `shape` of `dtype`
    ("float": any float dtype)."""
    if isinstance(source, str) and not hasattr(state, source):
        fields = [field.name for field in dataclasses.fields(state)]
        raise ValueError(f"{what} names {source!r}, which is not a field of the state {fields}")
    if not _from_state(source):
        raise TypeError(f"{what} must name a field of the state or be a function of it, got {describe(source)}")
    value = _read(state, source)
    dtype_ok = isinstance(value, Tensor) and (value.is_floating_point() if dtype == "float" else value.dtype == dtype)
    if not dtype_ok or tuple(value.shape) != shape:
        want = "a float" if dtype == "float" else str(dtype)
        raise ValueError(f"{what} must give {want} tensor of shape {list(shape)}, got {describe(value)}")


def _per_instance(value, num_worlds: int, count: int) -> Tensor:
    """[W, count, 3] float32 (a view) of a (3,) or [count, 3] value."""
    return torch.as_tensor(value, dtype=torch.float32).expand(num_worlds, count, 3)
