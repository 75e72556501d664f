"""Cooperative navigation (MPE ``simple_spread``) with egocentric cameras.

N agents (default 3) must cover N landmarks in a walled arena. Every agent sees the
arena through its own camera mounted on its body, so it has to turn to look around.

* Arena: |x|, |y| <= 1.5 m, walls and floor are static geometry.
* Agents: capsules of radius 0.15 m, mass 1, physics from ``envs/physics.py`` with
  the terms walls + body_collisions + drag (MPE-like damping 0.25 per 0.1 s step).
  The camera sits at 0.4 m, pitched 0.2 rad down; a small dark "nose" box shows
  other agents which way a body faces (its own nose is hidden from its own view).
* Landmarks: flat discs of distinct colours; agents drive over them (no collision).
* Actions, egocentric (the body's yaw is where its camera looks):
  discrete 5: 0 noop, 1 forward, 2 turn left, 3 turn right, 4 backward;
  continuous 2: (thrust in [-1, 1] along the heading, turn rate in [-1, 1]).
  Movement as in envs/egomotion.py (shared by the arena envs).
* Reward, shared by all agents: -(sum over landmarks of the distance to the closest
  agent) - ``collision_penalty`` x (number of agent pairs touching).
* Episode: never terminates; truncated after ``max_steps`` = 100.
* info: ``"collisions"`` int64 [W] agent pairs touching after the step, ``"coverage"``
  float32 [W] sum over landmarks of the distance to the closest agent (the reward's term).
* State obs (6 + 2 L + 2 (N - 1)): own position (2), velocity (2), cos/sin yaw (2),
  landmark positions relative to the agent (2 per landmark), other agents' positions
  relative to the agent (2 each, in agent-index order skipping itself), world frame.
"""
from __future__ import annotations

import math

import torch

import marl_render as mr

from marl_render.validation import positive_float, positive_int

from . import egomotion, physics, scenery

ARENA = 1.5  # half extent (m)
SPAWN = 1.2  # agents and landmarks spawn in |x|, |y| <= SPAWN
AGENT_RADIUS = 0.15
AGENT_HEIGHT = 0.5
EYE_HEIGHT = 0.4
CAMERA_PITCH = -0.2
LANDMARK_RADIUS = 0.15
LANDMARK_HEIGHT = 0.04
CONTACT_TOLERANCE = 0.02  # a pair "collides" while its gap is below this (m)



class Spread(egomotion.EgocentricEnv):
    """Cooperative navigation; see the module docstring."""

    name = "spread"
    default_num_agents = 3
    agent_range = (1, 12)
    default_max_steps = 100
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"collisions": torch.int64, "coverage": torch.float32}
    arena_half_extent = (ARENA, ARENA)

    def __init__(self, *, num_landmarks: int | None = None, collision_penalty: float = 1.0, **common):
        """Common kwargs: see BatchedEnv. num_landmarks defaults to num_agents."""
        if num_landmarks is not None:
            num_landmarks = positive_int("num_landmarks", num_landmarks)
            if num_landmarks > 12:
                raise ValueError(f"num_landmarks must be an int in [1, 12], got {num_landmarks}")
        self.num_landmarks = num_landmarks
        self.collision_penalty = positive_float("collision_penalty", collision_penalty, allow_zero=True)
        super().__init__(**common)

    def _setup(self):
        W, N = self.num_worlds, self.num_agents
        L = self.num_landmarks = N if self.num_landmarks is None else self.num_landmarks
        self.agent_names = [f"agent_{i}" for i in range(N)]
        self.groups = {"agents": list(self.agent_names)}
        egomotion.declare_actions(self)
        self.state_dim = 6 + 2 * L + 2 * (N - 1)
        self.physics = egomotion.arena_physics(self.physics_terms, (ARENA, ARENA), max_speed=2.0,
                                               min_body_radius=AGENT_RADIUS)
        dev = self.device
        self.bodies = physics.BodyState.make(torch.zeros(W, N, 2, device=dev), AGENT_RADIUS)
        self.yaw = torch.zeros(W, N, device=dev)
        self.landmarks = torch.zeros(W, L, 2, device=dev)
        # Index of the other agents of each agent, [N, N-1], for the state obs.
        self._others = torch.tensor([[j for j in range(N) if j != i] for i in range(N)], dtype=torch.long,
                                    device=dev).reshape(N, N - 1)
        self._pairs = torch.triu(torch.ones(N, N, dtype=torch.bool, device=dev), diagonal=1)
        # Constant instance data.
        self._agent_color = torch.tensor(scenery.TEAM_COLORS["agents"]).expand(W, N, 3)
        landmark_colors = scenery.palette(L + 1)  # index 1 (blue) is the agents' colour
        landmark_colors = torch.cat((landmark_colors[:1], landmark_colors[2:]))
        self._landmark_color = landmark_colors.expand(W, L, 3)
        self._landmark_scale = torch.tensor([2 * LANDMARK_RADIUS, 2 * LANDMARK_RADIUS, LANDMARK_HEIGHT]).expand(W, L, 3)
        self._nose_scale = torch.tensor([0.08, 0.12, 0.08]).expand(W, N, 3)
        self._nose_color = torch.tensor([0.1, 0.1, 0.12]).expand(W, N, 3)
        self._owner = torch.arange(N).expand(W, N)
        self._all = {"agents": torch.ones(W, N, dtype=torch.bool), "landmarks": torch.ones(W, L, dtype=torch.bool)}

    def _build_scene(self, scene: mr.Scene, overview: bool) -> None:
        scenery.add_arena(scene, (ARENA, ARENA))
        scene.add_group("agents", scenery.agent_mesh(AGENT_RADIUS, AGENT_HEIGHT), capacity=self.num_agents)
        scene.add_group("noses", "box", capacity=self.num_agents)
        scene.add_group("landmarks", scenery.disc_mesh(), capacity=self.num_landmarks)
        if not overview:
            scene.mount_cameras("agents", instance=range(self.num_agents),
                                offset=(0.0, 0.0, EYE_HEIGHT - AGENT_HEIGHT / 2), pitch=CAMERA_PITCH)

    def _reset_state(self, mask):
        W, N, L, g = self.num_worlds, self.num_agents, self.num_landmarks, self.generator
        pos = (torch.rand(W, N, 2, generator=g) * 2 - 1) * SPAWN
        yaw = (torch.rand(W, N, generator=g) * 2 - 1) * math.pi
        landmarks = (torch.rand(W, L, 2, generator=g) * 2 - 1) * SPAWN
        pos, yaw, landmarks = (t.to(self.device) for t in (pos, yaw, landmarks))
        m2, m3 = mask[:, None], mask[:, None, None]
        b = self.bodies
        self.bodies = b._replace(pos=torch.where(m3, pos, b.pos), vel=torch.where(m3, torch.zeros_like(b.vel), b.vel),
                                 active=b.active | m2)
        self.yaw = torch.where(m2, yaw, self.yaw)
        self.landmarks = torch.where(m3, landmarks, self.landmarks)

    def _step_state(self, actions, alive):
        yaw, force = egomotion.drive(self, actions, alive)
        bodies = physics.step(self.bodies._replace(active=alive), force, None, self.physics)
        reward, collisions, coverage = self.reward(bodies.pos)
        self.bodies, self.yaw = bodies, yaw
        terminated = torch.zeros_like(alive)
        return reward[:, None].expand(-1, self.num_agents), terminated, {"collisions": collisions,
                                                                         "coverage": coverage}

    def reward(self, pos: torch.Tensor):
        """Shared reward [W], colliding pairs [W] int64 and sum of landmark distances [W]."""
        coverage = torch.cdist(self.landmarks, pos).amin(dim=-1).sum(-1)  # [W, L, N] -> [W]
        gap = torch.cdist(pos, pos) - 2 * AGENT_RADIUS
        collisions = ((gap < CONTACT_TOLERANCE) & self._pairs).sum((-1, -2))
        return -coverage - self.collision_penalty * collisions, collisions, coverage

    def _instances(self, full: bool) -> dict:
        pos = self.bodies.pos.to("cpu", torch.float32)
        yaw = self.yaw.cpu()
        rotation = scenery.yaw_quat(yaw)
        update = {
            "agents": {"position": scenery.planar_to_3d(pos, AGENT_HEIGHT / 2), "rotation": rotation},
            "noses": {"position": scenery.planar_to_3d(pos + AGENT_RADIUS * scenery.heading(yaw), 0.3),
                      "rotation": rotation},
        }
        if full:
            update["agents"].update(color=self._agent_color, active=self._all["agents"])
            update["noses"].update(color=self._nose_color, scale=self._nose_scale, active=self._all["agents"],
                                   owner=self._owner)
            update["landmarks"] = {"position": scenery.planar_to_3d(self.landmarks.cpu(), LANDMARK_HEIGHT / 2),
                                   "scale": self._landmark_scale, "color": self._landmark_color,
                                   "active": self._all["landmarks"]}
        return update

    def _state_obs(self):
        pos, vel, yaw = self.bodies.pos, self.bodies.vel, self.yaw
        W, N = pos.shape[:2]
        rel_landmarks = (self.landmarks[:, None] - pos[:, :, None]).reshape(W, N, -1)
        others = pos[:, self._others] - pos[:, :, None]  # [W, N, N-1, 2]
        return torch.cat((pos, vel, torch.cos(yaw)[..., None], torch.sin(yaw)[..., None], rel_landmarks,
                          others.reshape(W, N, -1)), -1)

    def _state_tensors(self):
        b = self.bodies
        return {"pos": b.pos, "vel": b.vel, "active": b.active, "yaw": self.yaw, "landmarks": self.landmarks}
