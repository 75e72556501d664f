"""The arena: agents on capsule bodies in a walled floor, each seeing through its own camera.

spread, forage, tag and push are scenarios over this one arena, in the way of MPE's scenarios.
The arena owns what they share: the teams of agents, the bodies and their planar physics
(envs/planar.py), egocentric movement (envs/egomotion.py), the body and nose meshes with the
mounted cameras, the instance data, and the common part of the state observation. A scenario
file holds only its rules:

    _setup()             setup_arena(...), then its own constants and the zero state `sim`
    spawn() -> state     a new episode in every world (the arena keeps it in the worlds reset)
    rules(moved, alive)  -> (state, reward [W, A], terminated [W, A], info) once the bodies
                         have moved (`moved`; `self.sim` still holds the state before the step)
    _build_scene, _instances, _state_obs: the arena's, plus the scenario's own objects

Bodies 0 .. A-1 are the agents; a scenario may add more after them (push's ball). The state
(``sim``) is an ``ArenaState`` subclass with the scenario's own fields (envs/state.py).
"""
from __future__ import annotations

import abc
import dataclasses
import math

import torch
from torch import Tensor

import marl_render as mr

from . import egomotion, planar, scenery
from . import state as explicit_state
from .core import BatchedEnv

AGENT_HEIGHT = 0.5
EYE_HEIGHT = 0.4  # the mounted camera's height above the floor (m)
CAMERA_PITCH = -0.2  # rad, looking slightly down
NOSE_HEIGHT = 0.3  # a small dark "nose" box shows others which way a body faces
NOSE_SIZE = (0.08, 0.12, 0.08)
NOSE_COLOR = (0.1, 0.1, 0.12)


@dataclasses.dataclass(frozen=True)
class ArenaState:
    """The arena's part of the simulation state; a scenario subclasses it with its own fields."""

    pos: Tensor  # [W, B, 2] body centres (m): the agents, then the scenario's other bodies
    vel: Tensor  # [W, B, 2] body velocities (m/s)
    active: Tensor  # [W, B] bool: bodies that move and collide (agents still in the episode)
    yaw: Tensor  # [W, A] the agents' headings (rad; 0 faces +y, as their cameras do)


def numbered(prefix: str, count: int) -> list:
    """Agent names prefix_0 .. prefix_{count-1}."""
    return [f"{prefix}_{i}" for i in range(count)]


class ArenaEnv(BatchedEnv):
    """Base of the arena scenarios; see the module docstring."""

    State = ArenaState  # the scenario's state class
    dt = egomotion.DT
    fov_y = math.radians(90.0)
    near = 0.05
    far = 20.0
    thrust = egomotion.THRUST  # N at full forward action (a scenario may set one per agent, [A])
    team_colors = scenery.TEAM_COLORS

    @property
    def shadow_bounds(self):
        """shadows=True covers the arena and its walls, not the floor's far margin."""
        return scenery.arena_shadow_bounds(self.arena_half_extent)

    def state_bounds(self) -> dict:
        """Body centres inside the walls (the step clamps them there anyway); see BatchedEnv."""
        return {**super().state_bounds(), "pos": self.inside_walls()}

    def inside_walls(self) -> tuple:
        """(low, high) per axis of a point inside the arena's walls, for state_bounds."""
        hx, hy = self.arena_half_extent
        return (-hx, -hy), (hx, hy)

    def setup_arena(self, teams: dict, *, state_dim: int, radius, max_speed: float, substeps: int = 2,
                    bodies: tuple = ()) -> None:
        """Declare who plays and how bodies move (first thing in a scenario's _setup).

        teams: team -> agent names, in agent order. radius: of the agents' bodies (m), a float or
        {team: float}. bodies: (radius, mass) of each further body after the agents."""
        self.groups = teams
        self.agent_names = [name for names in teams.values() for name in names]
        self._team_of = [team for team, names in teams.items() for _ in names]
        if self.continuous:
            self.action_dim = 2
        else:
            self.num_actions, self.action_meanings = len(egomotion.DISCRETE_ACTIONS), egomotion.ACTION_MEANINGS
        self.action_table = torch.tensor(egomotion.DISCRETE_ACTIONS, device=self.device)
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
        self._agent_color = torch.tensor([self.team_colors[team] for team in self._team_of]).expand(W, N, 3)
        self._nose_offset = torch.tensor(agent_radius)[:, None]  # [N, 1]
        self._nose_scale = torch.tensor(NOSE_SIZE).expand(W, N, 3)
        self._nose_color = torch.tensor(NOSE_COLOR).expand(W, N, 3)
        self._owner = torch.arange(N).expand(W, N)
        self._all_agents = torch.ones(W, N, dtype=torch.bool)

    def per_agent(self, values: dict) -> Tensor:
        """[A] float32 on the env's device: each agent's value of its team in {team: value}."""
        return torch.tensor([values[team] for team in self._team_of], device=self.device)

    def at_rest(self, pos: Tensor, yaw: Tensor, **extra) -> ArenaState:
        """A state (of class State) with the bodies at pos [W, B, 2], still and active, the agents
        facing yaw [W, A], and the scenario's own fields `extra`; all on the env's device."""
        pos = pos.to(self.device)
        return self.State(pos=pos, vel=torch.zeros_like(pos), active=torch.ones_like(pos[..., 0], dtype=torch.bool),
                          yaw=yaw.to(self.device), **{name: value.to(self.device) for name, value in extra.items()})

    # ------------------------------------------------------------------ rules (the scenario's)
    @abc.abstractmethod
    def spawn(self) -> ArenaState:
        """A new episode in every world (sampled with self.generator), e.g. by at_rest(...)."""

    @abc.abstractmethod
    def rules(self, moved: ArenaState, alive: Tensor):
        """(state, reward [W, A], terminated [W, A] bool, info) of the step, given the state once the
        bodies moved (`moved`) and who took part (alive [W, A]); self.sim is still the state before."""

    def obstacles(self) -> planar.Obstacles | None:
        """Static boxes of the physics (none unless the scenario has some)."""
        return None

    # ------------------------------------------------------------------ dynamics
    def bodies(self, active: Tensor) -> planar.BodyState:
        """The physics view of the current state, with `active` [W, B] bodies."""
        s = self.sim
        W, B = s.pos.shape[:2]
        return planar.BodyState(s.pos, s.vel, self.radius.expand(W, B), self.mass.expand(W, B), active)

    def _reset_state(self, mask):
        self.sim = explicit_state.select_worlds(mask, self.spawn(), self.sim)

    def _step_state(self, actions, alive):
        command = actions if self.continuous else self.action_table[actions]
        yaw, force = egomotion.drive(self.sim.yaw, command, alive, self.thrust, self.physics.dt)
        active, extra = alive, self.radius.shape[0] - self.num_agents
        if extra:  # further bodies (push's ball) feel no force and always take part
            force = torch.cat((force, force.new_zeros(self.num_worlds, extra, 2)), 1)
            active = torch.cat((alive, alive.new_ones(self.num_worlds, extra)), 1)
        bodies = planar.step(self.bodies(active), force, self.obstacles(), self.physics)
        moved = dataclasses.replace(self.sim, pos=bodies.pos, vel=bodies.vel, active=bodies.active, yaw=yaw)
        self.sim, reward, terminated, info = self.rules(moved, alive)
        return reward, terminated, info

    # ------------------------------------------------------------------ scene and observations
    def _build_scene(self, scene: mr.Scene, overview: bool) -> None:
        scenery.add_arena(scene, self.arena_half_extent)
        N = self.num_agents
        scene.add_group("agents", scenery.agent_mesh(self._mesh_radius, AGENT_HEIGHT), capacity=N)
        scene.add_group("noses", "box", capacity=N)
        if not overview:
            scene.mount_cameras("agents", instance=range(N), offset=(0.0, 0.0, EYE_HEIGHT - AGENT_HEIGHT / 2),
                                pitch=CAMERA_PITCH)

    def _instances(self, full: bool) -> dict:
        pos = self.sim.pos[:, :self.num_agents].to("cpu", torch.float32)
        yaw = self.sim.yaw.cpu()
        rotation = scenery.yaw_quat(yaw)
        nose = pos + self._nose_offset * scenery.heading(yaw)
        update = {"agents": {"position": scenery.planar_to_3d(pos, AGENT_HEIGHT / 2), "rotation": rotation},
                  "noses": {"position": scenery.planar_to_3d(nose, NOSE_HEIGHT), "rotation": rotation}}
        if full:
            update["agents"].update(color=self._agent_color, scale=self._agent_scale, active=self._all_agents)
            update["noses"].update(color=self._nose_color, scale=self._nose_scale, active=self._all_agents,
                                   owner=self._owner)
        return update

    def own_obs(self) -> Tensor:
        """[W, A, 6]: each agent's position (2), velocity (2), cos and sin of its yaw; world frame."""
        s, N = self.sim, self.num_agents
        return torch.cat((s.pos[:, :N], s.vel[:, :N], torch.cos(s.yaw)[..., None], torch.sin(s.yaw)[..., None]), -1)

    def relative(self, points: Tensor) -> Tensor:
        """[W, A, K, 2]: points [W, K, 2] relative to each agent."""
        return points[:, None] - self.sim.pos[:, :self.num_agents, None]

    def others_obs(self) -> Tensor:
        """[W, A, A-1, 2]: the other agents' positions relative to each agent, in `others` order."""
        pos = self.sim.pos[:, :self.num_agents]
        return pos[:, self.others] - pos[:, :, None]
