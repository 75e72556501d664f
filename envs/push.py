"""Team ball-pushing (a tiny football) with egocentric cameras.

Two teams push a ball into the other team's goal. Every agent sees the pitch through
its own camera mounted on its body.

* Pitch: |x| <= 1.5 m, |y| <= 2.0 m, walls and floor are static geometry. Each end has
  a goal: a coloured area of the floor ``|x| < GOAL_HALF_WIDTH`` (0.5 m), ``|y| > GOAL_LINE``
  (1.7 m) against the end wall, framed by two posts and a crossbar in the defending
  team's colour. ``team_a`` (red) defends the goal at -y and attacks +y; ``team_b``
  (blue) defends +y and attacks -y.
* Agents: ``num_agents`` (even, 2 to 12, default 4 = 2 vs 2); agents ``0 .. N/2 - 1``
  are ``team_a``, the rest ``team_b``; names ``team_a_i`` / ``team_b_i``, groups
  ``{"team_a": [...], "team_b": [...]}``. Capsules of radius 0.15 m, mass 1.
  The camera sits at 0.4 m, pitched 0.2 rad down; a dark "nose" box shows which way a
  body faces.
* Ball: a physics body (circle) of radius 0.15 m and mass 0.5, drawn as a white sphere.
  Physics from ``envs/physics.py`` with the terms walls + body_collisions + drag
  (MPE-like damping 0.25 per 0.1 s step for agents and ball alike), restitution 0.5.
* Actions, egocentric, as in ``spread``: discrete 5: 0 noop, 1 forward, 2 turn left,
  3 turn right, 4 backward; continuous 2: (thrust in [-1, 1] along the heading, turn
  rate in [-1, 1]). Movement as in envs/egomotion.py (shared by the arena envs).
  There is no kick: agents push the ball with their bodies.
* Goal: scored when, after the physics step, the ball's centre is inside a goal area.
  Every agent of the scoring team gets ``+goal_reward`` (default 1), every agent of the
  other team ``-goal_reward``, and the episode terminates (every agent terminated):
  one goal per episode. Optional shaping (``shaping`` >= 0, default 0, zero-sum):
  ``team_a`` additionally gets ``shaping x`` (the ball's progress along +y in the step,
  metres), ``team_b`` the negative.
* Episode: truncated after ``max_steps`` = 200 if nobody scores.
* Reset: ``team_a`` in its own half (y in [-1.6, -0.45]) facing +y, ``team_b`` mirrored,
  each yaw jittered by up to 0.5 rad; a team's agents in distinct lanes across the
  pitch (in random order) so nobody overlaps; the ball at rest within (0.3, 0.1) m of
  the centre spot.
* action_mask: every action is always valid (all True).
* State obs (10 + 2 (N - 1)), in the agent's **team frame** (``team_b``'s frame is the
  world turned by 180 degrees, so every agent attacks +y): own position (2), velocity
  (2), cos/sin yaw (2), ball position relative to the agent (2), ball velocity (2),
  teammates' positions relative to the agent (2 each), then opponents' (2 each), each
  in agent-index order.
* info: ``"goal"`` int64 [W]: +1 ``team_a`` scored in this step, -1 ``team_b`` scored,
  0 none.
"""
from __future__ import annotations

import math

import torch

import marl_render as mr

from marl_render.validation import positive_float

from . import egomotion, physics, scenery

ARENA = (1.5, 2.0)  # half extents (m)
GOAL_HALF_WIDTH = 0.5
GOAL_LINE = 1.7  # a goal area is |y| > GOAL_LINE, |x| < GOAL_HALF_WIDTH
SPAWN_X = 1.3  # agents spawn in |x| <= SPAWN_X, one lane of 2 SPAWN_X / (N / 2) per agent
SPAWN_Y = (0.45, 1.6)  # |y| range of the spawn area in the own half
SPAWN_CLEARANCE = 0.02
SPAWN_YAW_JITTER = 0.5
AGENT_RADIUS = 0.15
AGENT_HEIGHT = 0.5
EYE_HEIGHT = 0.4
CAMERA_PITCH = -0.2
BALL_RADIUS = 0.15
BALL_MASS = 0.5
BALL_COLOR = (0.95, 0.95, 0.92)
WALL_THICKNESS = 0.1  # scenery.add_arena's default
POST_SIZE = 0.08
POST_HEIGHT = 0.6
TEAM_COLORS = {"team_a": scenery.TEAM_COLORS["red"], "team_b": scenery.TEAM_COLORS["blue"]}

# discrete action -> (thrust, turn), the same set as spread


def add_goals(scene: mr.Scene) -> None:
    """Static goal areas (floor patches) and goal frames (posts + crossbar) at both ends."""
    hy = ARENA[1]
    depth = hy - GOAL_LINE
    area_y, frame_y = (GOAL_LINE + hy) / 2, hy + WALL_THICKNESS / 2
    positions, scales, colors = [], [], []
    area_pos, area_scale, area_color = [], [], []
    for side, team in ((-1.0, "team_a"), (1.0, "team_b")):  # the goal at side * y is team's own
        color = list(TEAM_COLORS[team])
        area_pos.append([0.0, side * area_y, 0.005])
        area_scale.append([2 * GOAL_HALF_WIDTH, depth, 1.0])
        area_color.append([0.5 + 0.5 * c for c in color])  # a lighter shade on the floor
        for x in (-GOAL_HALF_WIDTH, GOAL_HALF_WIDTH):
            positions.append([x, side * frame_y, POST_HEIGHT / 2])
            scales.append([POST_SIZE, POST_SIZE, POST_HEIGHT])
            colors.append(color)
        positions.append([0.0, side * frame_y, POST_HEIGHT - POST_SIZE / 2])
        scales.append([2 * GOAL_HALF_WIDTH + POST_SIZE, POST_SIZE, POST_SIZE])
        colors.append(color)
    scene.add_static("goal_areas", "plane", position=area_pos, scale=area_scale, color=area_color)
    scene.add_static("goal_frames", "box", position=positions, scale=scales, color=colors)


class Push(egomotion.EgocentricEnv):
    """Two teams push a ball into the other team's goal; see the module docstring."""

    name = "push"
    default_num_agents = 4
    agent_range = (2, 12)
    default_max_steps = 200
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"goal": torch.int64}
    arena_half_extent = ARENA

    def __init__(self, *, goal_reward: float = 1.0, shaping: float = 0.0, **common):
        """Common kwargs: see BatchedEnv (num_agents must be even)."""
        self.goal_reward = positive_float("goal_reward", goal_reward)
        self.shaping = positive_float("shaping", shaping, allow_zero=True)
        super().__init__(**common)

    def _setup(self):
        W, N = self.num_worlds, self.num_agents
        if N % 2:
            raise ValueError(f"num_agents must be even for push (two equal teams), got {N}")
        T = N // 2
        self.agent_names = [f"team_a_{i}" for i in range(T)] + [f"team_b_{i}" for i in range(T)]
        self.groups = {"team_a": self.agent_names[:T], "team_b": self.agent_names[T:]}
        egomotion.declare_actions(self)
        self.state_dim = 10 + 2 * (N - 1)
        self.physics = egomotion.arena_physics(self.physics_terms, ARENA, max_speed=3.0, substeps=3,
                                               min_body_radius=min(AGENT_RADIUS, BALL_RADIUS))
        dev = self.device
        # Bodies 0 .. N-1 are the agents, body N is the ball.
        radius = torch.tensor([AGENT_RADIUS] * N + [BALL_RADIUS], device=dev)
        mass = torch.tensor([1.0] * N + [BALL_MASS], device=dev)
        self.bodies = physics.BodyState.make(torch.zeros(W, N + 1, 2, device=dev), radius, mass=mass)
        self.yaw = torch.zeros(W, N, device=dev)
        self.is_team_a = torch.arange(N, device=dev) < T
        self.side = torch.where(self.is_team_a, 1.0, -1.0)  # +1: attacks +y (team_a), -1: attacks -y
        # Per agent: teammates then opponents, each in index order, [N, N-1].
        self._others = torch.tensor([[j for j in range(N) if j != i and (j < T) == (i < T)]
                                     + [j for j in range(N) if (j < T) != (i < T)] for i in range(N)],
                                    dtype=torch.long, device=dev).reshape(N, N - 1)
        # Constant instance data.
        colors = torch.tensor([TEAM_COLORS["team_a"], TEAM_COLORS["team_b"]])
        self._agent_color = colors[(~self.is_team_a).long().cpu()].expand(W, N, 3)
        self._nose_scale = torch.tensor([0.08, 0.12, 0.08]).expand(W, N, 3)
        self._nose_color = torch.tensor([0.1, 0.1, 0.12]).expand(W, N, 3)
        self._owner = torch.arange(N).expand(W, N)
        self._ball_scale = torch.full((W, 1, 3), 2 * BALL_RADIUS)
        self._ball_color = torch.tensor(BALL_COLOR).expand(W, 1, 3)
        self._all = {"agents": torch.ones(W, N, dtype=torch.bool), "ball": torch.ones(W, 1, dtype=torch.bool)}

    def _build_scene(self, scene: mr.Scene, overview: bool) -> None:
        scenery.add_arena(scene, ARENA, wall_thickness=WALL_THICKNESS)
        add_goals(scene)
        scene.add_group("agents", scenery.agent_mesh(AGENT_RADIUS, AGENT_HEIGHT), capacity=self.num_agents)
        scene.add_group("noses", "box", capacity=self.num_agents)
        scene.add_group("ball", mr.sphere(segments=10, rings=5), capacity=1)
        if not overview:
            scene.mount_cameras("agents", instance=range(self.num_agents),
                                offset=(0.0, 0.0, EYE_HEIGHT - AGENT_HEIGHT / 2), pitch=CAMERA_PITCH)

    @property
    def ball(self) -> tuple:
        """(position [W, 2], velocity [W, 2]) of the ball."""
        return self.bodies.pos[:, -1], self.bodies.vel[:, -1]

    def _reset_state(self, mask):
        W, N, g = self.num_worlds, self.num_agents, self.generator
        T = N // 2
        # Each team's agents take the T lanes across the pitch in a random order (so they never
        # overlap), with a random x inside the lane that keeps SPAWN_CLEARANCE to its borders.
        lane = torch.rand(W, 2, T, generator=g).argsort(-1).reshape(W, N).to(self.device)
        u = torch.rand(W, N, 3, generator=g).to(self.device)
        width = 2 * SPAWN_X / T
        x = (lane + 0.5) * width - SPAWN_X + (u[..., 0] * 2 - 1) * max(0.0, width / 2 - AGENT_RADIUS - SPAWN_CLEARANCE)
        y = -self.side * (SPAWN_Y[0] + u[..., 1] * (SPAWN_Y[1] - SPAWN_Y[0]))  # own half
        yaw = torch.where(self.is_team_a, 0.0, math.pi) + (u[..., 2] * 2 - 1) * SPAWN_YAW_JITTER
        ball = ((torch.rand(W, 1, 2, generator=g) * 2 - 1) * torch.tensor([0.3, 0.1])).to(self.device)
        pos = torch.cat((torch.stack((x, y), -1), ball), 1)
        m2, m3 = mask[:, None], mask[:, None, None]
        b = self.bodies
        self.bodies = b._replace(pos=torch.where(m3, pos, b.pos), vel=torch.where(m3, torch.zeros_like(b.vel), b.vel),
                                 active=b.active | m2)
        self.yaw = torch.where(m2, scenery.wrap_angle(yaw), self.yaw)

    def _step_state(self, actions, alive):
        yaw, force = egomotion.drive(self, actions, alive)
        force = torch.cat((force, torch.zeros_like(force[:, :1])), 1)  # no force on the ball
        active = torch.cat((alive, torch.ones_like(alive[:, :1])), 1)
        bodies = physics.step(self.bodies._replace(active=active), force, None, self.physics)

        ball_before, ball = self.bodies.pos[:, -1], bodies.pos[:, -1]
        in_mouth = ball[:, 0].abs() < GOAL_HALF_WIDTH
        goal = ((in_mouth & (ball[:, 1] > GOAL_LINE)).long() - (in_mouth & (ball[:, 1] < -GOAL_LINE)).long())  # [W]
        reward = self.goal_reward * goal[:, None].to(torch.float32) * self.side  # [W, N]
        if self.shaping:
            reward = reward + self.shaping * (ball[:, 1] - ball_before[:, 1])[:, None] * self.side
        terminated = (goal != 0)[:, None].expand(-1, self.num_agents)
        self.bodies, self.yaw = bodies, yaw
        return reward, terminated, {"goal": goal}

    def _instances(self, full: bool) -> dict:
        pos = self.bodies.pos.to("cpu", torch.float32)
        agents, ball = pos[:, :-1], pos[:, -1:]
        yaw = self.yaw.cpu()
        rotation = scenery.yaw_quat(yaw)
        update = {
            "agents": {"position": scenery.planar_to_3d(agents, AGENT_HEIGHT / 2), "rotation": rotation},
            "noses": {"position": scenery.planar_to_3d(agents + AGENT_RADIUS * scenery.heading(yaw), 0.3),
                      "rotation": rotation},
            "ball": {"position": scenery.planar_to_3d(ball, BALL_RADIUS)},
        }
        if full:
            update["agents"].update(color=self._agent_color, active=self._all["agents"])
            update["noses"].update(color=self._nose_color, scale=self._nose_scale, active=self._all["agents"],
                                   owner=self._owner)
            update["ball"].update(scale=self._ball_scale, color=self._ball_color, active=self._all["ball"])
        return update

    def _state_obs(self):
        s = self.side[None, :, None]  # team frame: team_b's coordinates turned by 180 degrees
        agents, vel = self.bodies.pos[:, :-1], self.bodies.vel[:, :-1]
        ball, ball_vel = self.ball
        W, N = agents.shape[:2]
        yaw = self.yaw + torch.where(self.is_team_a, 0.0, math.pi)
        others = (agents[:, self._others] - agents[:, :, None]) * s[..., None]  # [W, N, N-1, 2]
        return torch.cat((agents * s, vel * s, torch.cos(yaw)[..., None], torch.sin(yaw)[..., None],
                          (ball[:, None] - agents) * s, ball_vel[:, None] * s, others.reshape(W, N, -1)), -1)

    def _state_tensors(self):
        b = self.bodies
        return {"pos": b.pos, "vel": b.vel, "active": b.active, "yaw": self.yaw}
