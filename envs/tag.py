"""Predator-prey tag (MPE ``simple_tag``) with egocentric cameras.

Slower predators chase faster prey in a walled arena with a few box obstacles.
Every agent sees the arena through its own camera mounted on its body.

* Agents: ``num_predators`` predators (red, default 3) then ``num_prey`` prey (green,
  default 1); agent names ``predator_i`` and ``prey_j`` in that order, groups
  ``{"predator": [...], "prey": [...]}``. Team sizes: give ``num_predators`` and / or
  ``num_prey`` (a missing one defaults to 3 predators / 1 prey, or to the rest of
  ``num_agents`` when that is given); ``num_agents`` alone gives
  ``num_prey = max(1, num_agents // 4)`` and predators for the rest. All three given
  must agree. 2 to 16 agents, at least one of each.
* Arena: |x|, |y| <= 1.5 m, walls and floor are static geometry. ``num_obstacles``
  (default 2, 0 to 8) boxes of 0.4 x 0.4 x 0.4 m block bodies (physics) and views.
* Reset: the arena is cut into a 4 x 4 grid of cells (5 x 5 beyond 16 objects); every
  obstacle and every agent gets a cell of its own, at random, and a random place in it
  that keeps clear of the cell's borders (``cell_spawn``), obstacles a random turn in
  [-45, 45] degrees, agents a random yaw. So nothing overlaps at the start and every
  prey starts at least 0.1 m from touching any predator.
* Bodies: capsules, predators radius 0.15 m, prey 0.12 m, mass 1, physics from
  ``envs/physics.py`` with the terms walls + body_collisions + obstacles (only when
  ``num_obstacles`` > 0) + drag (MPE-like damping 0.25 per 0.1 s step).
  Speeds as in MPE: predators thrust 3 N and at most 1.0 m/s, prey thrust 4 N and at
  most 1.3 m/s (the physics clamps to 1.3; the predators' cap is applied after each
  step, see ``MAX_SPEED``). The camera sits at 0.4 m, pitched 0.2 rad down; a dark
  "nose" box shows which way a body faces.
* Actions, egocentric, as in ``spread``: discrete 5: 0 noop, 1 forward, 2 turn left,
  3 turn right, 4 backward; continuous 2: (thrust in [-1, 1] along the heading, turn
  rate in [-1, 1]). Movement as in envs/egomotion.py, with the thrust per team below.
* Catching: a live prey is caught when a live predator's body comes within
  ``CONTACT_TOLERANCE`` of touching it (after the physics step). A caught prey leaves
  the episode: it is terminated (``alive`` False) and its body stops colliding. The
  frame of the step in which it is caught still shows it beside its catcher (the moment
  worth watching, and the last frame of an episode that ends with the catch); from the
  next step on its instance is inactive, so it is gone from every view and the overview.
* Reward: every predator gets ``+catch_reward`` (default 10) per prey caught in the
  step by any predator (shared, as in MPE); a prey gets ``-catch_reward`` when it is
  caught. Optional shaping (``shaping`` >= 0, default 0): predators additionally get
  ``-shaping x`` (distance to the nearest live prey), live prey ``+shaping x`` (distance
  to the nearest predator).
* Episode: terminates (every agent terminated) when all prey are caught; truncated
  after ``max_steps`` = 100.
* action_mask: agents that left the episode may only take action 0 (noop); live agents
  may take every action.
* State obs (6 + 3 (N - 1) + 2 K): own position (2), velocity (2), cos/sin yaw (2);
  the other agents' positions relative to the agent (2 each, agent-index order
  skipping itself; zeros for agents that left) and their alive flags (1 each); the
  obstacle centres relative to the agent (2 each). World frame.
* info: ``"caught"`` int64 [W] prey caught in this step, ``"prey_left"`` int64 [W] live
  prey after it.
"""
from __future__ import annotations

import math

import torch

import marl_render as mr

from marl_render.validation import positive_float, positive_int

from . import egomotion, physics, scenery

ARENA = 1.5  # half extent (m)
OBSTACLE_HALF = 0.2  # half side of the square obstacles (m)
OBSTACLE_HEIGHT = 0.4
OBSTACLE_COLOR = (0.35, 0.33, 0.30)
PREDATOR_RADIUS = 0.15
PREY_RADIUS = 0.12
AGENT_HEIGHT = 0.5
EYE_HEIGHT = 0.4
CAMERA_PITCH = -0.2
THRUST = {"predator": 3.0, "prey": 4.0}  # N at full forward action
MAX_SPEED = {"predator": 1.0, "prey": 1.3}  # m/s
CONTACT_TOLERANCE = 0.02  # a predator "touches" a prey while their gap is below this (m)
SPAWN_CLEARANCE = 0.05  # spawned bodies keep this much space to their spawn cell's borders

# discrete action -> (thrust, turn), the same set as spread


class Tag(egomotion.EgocentricEnv):
    """Predators and prey; see the module docstring."""

    name = "tag"
    default_num_agents = 4
    agent_range = (2, 16)
    default_max_steps = 100
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "obstacles", "drag"})  # "obstacles" only if K > 0
    info_keys = {"caught": torch.int64, "prey_left": torch.int64}
    arena_half_extent = (ARENA, ARENA)

    def __init__(self, *, num_predators: int | None = None, num_prey: int | None = None, num_obstacles: int = 2,
                 catch_reward: float = 10.0, shaping: float = 0.0, **common):
        """Common kwargs: see BatchedEnv. Team sizes: see the module docstring."""
        if num_predators is not None:
            num_predators = positive_int("num_predators", num_predators)
        if num_prey is not None:
            num_prey = positive_int("num_prey", num_prey)
        if common.get("num_agents") is None and (num_predators is not None or num_prey is not None):
            common["num_agents"] = ((3 if num_predators is None else num_predators)
                                    + (1 if num_prey is None else num_prey))
        self.num_predators, self.num_prey = num_predators, num_prey
        self.num_obstacles = positive_int("num_obstacles", num_obstacles, minimum=0)
        if self.num_obstacles > 8:
            raise ValueError(f"num_obstacles must be an int in [0, 8], got {self.num_obstacles}")
        self.catch_reward = positive_float("catch_reward", catch_reward)
        self.shaping = positive_float("shaping", shaping, allow_zero=True)
        super().__init__(**common)

    # ------------------------------------------------------------------ setup
    def _team_sizes(self, N: int) -> tuple:
        P, Q = self.num_predators, self.num_prey
        if P is not None and Q is not None and P + Q != N:
            raise ValueError(f"num_predators + num_prey must equal num_agents, got {P} + {Q} != {N}")
        if P is None and Q is None:
            Q = max(1, N // 4)
        P = N - Q if P is None else P
        Q = N - P
        if P < 1 or Q < 1:
            raise ValueError(f"tag needs at least one predator and one prey, got num_agents={N} with "
                             f"num_predators={P}, num_prey={Q}")
        return P, Q

    def _setup(self):
        W, N, K = self.num_worlds, self.num_agents, self.num_obstacles
        P, Q = self.num_predators, self.num_prey = self._team_sizes(N)
        self.agent_names = [f"predator_{i}" for i in range(P)] + [f"prey_{j}" for j in range(Q)]
        self.groups = {"predator": self.agent_names[:P], "prey": self.agent_names[P:]}
        egomotion.declare_actions(self)
        self.state_dim = 6 + 3 * (N - 1) + 2 * K
        self.physics_terms = frozenset({"walls", "body_collisions", "drag"} | ({"obstacles"} if K else set()))
        self.physics = egomotion.arena_physics(self.physics_terms, (ARENA, ARENA), max_speed=max(MAX_SPEED.values()),
                                               min_body_radius=PREY_RADIUS)
        dev = self.device
        self.is_predator = torch.arange(N, device=dev) < P  # [N]
        self.is_prey = ~self.is_predator
        team = lambda values: torch.where(self.is_predator, values["predator"], values["prey"])  # noqa: E731
        self.radius = team({"predator": PREDATOR_RADIUS, "prey": PREY_RADIUS})  # [N] float32
        self.thrust = team(THRUST)
        self.max_speed = team(MAX_SPEED)
        self.bodies = physics.BodyState.make(torch.zeros(W, N, 2, device=dev), self.radius)
        self.yaw = torch.zeros(W, N, device=dev)
        self.obstacles = physics.Obstacles(torch.zeros(W, K, 2, device=dev),
                                           torch.full((W, K, 2), OBSTACLE_HALF, device=dev),
                                           torch.zeros(W, K, device=dev))
        self._others = torch.tensor([[j for j in range(N) if j != i] for i in range(N)], dtype=torch.long,
                                    device=dev).reshape(N, N - 1)
        # Spawn: obstacles (their half diagonal) then agents (radius + SPAWN_CLEARANCE), one cell each.
        self._spawn_grid = 4 if K + N <= 16 else 5
        self._spawn_margin = torch.cat((torch.full((K,), OBSTACLE_HALF * math.sqrt(2)),
                                        self.radius.cpu() + SPAWN_CLEARANCE))
        # [N, N] pairs (i, j) with i a predator and j a prey.
        self._hunt = self.is_predator[:, None] & self.is_prey[None, :]
        # Constant instance data (CPU, for the renderer).
        colors = torch.tensor([scenery.TEAM_COLORS["predator"], scenery.TEAM_COLORS["prey"]])
        self._agent_color = colors[self.is_prey.long().cpu()].expand(W, N, 3)
        xy = (self.radius.cpu() / PREDATOR_RADIUS)[:, None]
        self._agent_scale = torch.cat((xy, xy, torch.ones(N, 1)), 1).expand(W, N, 3)
        self._nose_offset = (self.radius.cpu())[:, None]  # [N, 1]
        self._nose_scale = torch.tensor([0.08, 0.12, 0.08]).expand(W, N, 3)
        self._nose_color = torch.tensor([0.1, 0.1, 0.12]).expand(W, N, 3)
        self._owner = torch.arange(N).expand(W, N)
        self._obstacle_color = torch.tensor(OBSTACLE_COLOR).expand(W, K, 3)
        self._obstacle_active = torch.ones(W, K, dtype=torch.bool)
        self._shown = torch.ones(W, N, dtype=torch.bool, device=dev)  # agents drawn in the current frame

    def _build_scene(self, scene: mr.Scene, overview: bool) -> None:
        scenery.add_arena(scene, (ARENA, ARENA))
        N = self.num_agents
        scene.add_group("agents", scenery.agent_mesh(PREDATOR_RADIUS, AGENT_HEIGHT), capacity=N)
        scene.add_group("noses", "box", capacity=N)
        if self.num_obstacles:
            scene.add_group("obstacles", "box", capacity=self.num_obstacles)
        if not overview:
            scene.mount_cameras("agents", instance=range(N), offset=(0.0, 0.0, EYE_HEIGHT - AGENT_HEIGHT / 2),
                                pitch=CAMERA_PITCH)

    # ------------------------------------------------------------------ dynamics
    def _reset_state(self, mask):
        W, N, K, g = self.num_worlds, self.num_agents, self.num_obstacles, self.generator
        # Obstacles and agents each get their own random cell of the grid (see cell_spawn): nothing
        # overlaps at the start and no predator starts within a catch of a prey.
        pos = scenery.cell_spawn(g, W, self._spawn_margin, self._spawn_grid, ARENA).to(self.device)
        angle = ((torch.rand(W, K, generator=g) * 2 - 1) * (math.pi / 4)).to(self.device)
        yaw = ((torch.rand(W, N, generator=g) * 2 - 1) * math.pi).to(self.device)
        center, pos = pos[:, :K], pos[:, K:]
        m2, m3 = mask[:, None], mask[:, None, None]
        b = self.bodies
        self.bodies = b._replace(pos=torch.where(m3, pos, b.pos), vel=torch.where(m3, torch.zeros_like(b.vel), b.vel),
                                 active=b.active | m2)
        self.yaw = torch.where(m2, yaw, self.yaw)
        o = self.obstacles
        self.obstacles = o._replace(center=torch.where(m3, center, o.center), angle=torch.where(m2, angle, o.angle))
        self._shown = self._shown | m2

    def _step_state(self, actions, alive):
        yaw, force = egomotion.drive(self, actions, alive, thrust=self.thrust)
        bodies = physics.step(self.bodies._replace(active=alive), force, self.obstacles, self.physics)
        bodies = bodies._replace(vel=physics.clamp_norm(bodies.vel, self.max_speed[:, None]))

        dist = torch.cdist(bodies.pos, bodies.pos)  # [W, N, N]
        touch = dist < self.radius[:, None] + self.radius[None, :] + CONTACT_TOLERANCE
        hunt = self._hunt & alive[:, :, None] & alive[:, None, :]
        caught = (touch & hunt).any(dim=1)  # [W, N], only prey can be caught
        n_caught = caught.sum(-1)  # [W]
        left = alive & ~caught
        prey_left = (left & self.is_prey).sum(-1)
        zero = torch.zeros((), device=self.device)
        reward = torch.where(self.is_predator, self.catch_reward * n_caught[:, None].to(torch.float32),
                             torch.where(caught, -self.catch_reward, zero))
        if self.shaping:
            inf = torch.full_like(dist, math.inf)
            to_prey = torch.where(self.is_prey & left[:, None, :], dist, inf).amin(-1)  # [W, N]
            to_predator = torch.where(self.is_predator & alive[:, None, :], dist, inf).amin(-1)
            shaping = torch.where(self.is_predator, -to_prey, to_predator)
            shaping = torch.where(torch.isfinite(shaping) & left, shaping, torch.zeros_like(shaping))
            reward = reward + self.shaping * shaping
        terminated = caught | (prey_left == 0)[:, None]

        stopped = torch.where(caught[..., None], torch.zeros_like(bodies.vel), bodies.vel)
        self.bodies = bodies._replace(active=alive & ~terminated, vel=stopped)
        self.yaw = yaw
        self._shown = alive  # this step's frame still shows who was caught in it
        return reward, terminated, {"caught": n_caught, "prey_left": prey_left}

    # ------------------------------------------------------------------ observations
    def _action_mask(self):
        mask = self.alive[:, :, None].expand(-1, -1, self.num_actions).clone()
        mask[..., 0] = True  # noop is always valid
        return mask

    def _instances(self, full: bool) -> dict:
        pos = self.bodies.pos.to("cpu", torch.float32)
        yaw = self.yaw.cpu()
        shown = self._shown.cpu()
        rotation = scenery.yaw_quat(yaw)
        nose = pos + self._nose_offset * scenery.heading(yaw)
        update = {
            "agents": {"position": scenery.planar_to_3d(pos, AGENT_HEIGHT / 2), "rotation": rotation, "active": shown},
            "noses": {"position": scenery.planar_to_3d(nose, 0.3), "rotation": rotation, "active": shown},
        }
        if full:
            update["agents"].update(color=self._agent_color, scale=self._agent_scale)
            update["noses"].update(color=self._nose_color, scale=self._nose_scale, owner=self._owner)
            if self.num_obstacles:
                o = self.obstacles
                scale = torch.cat((2 * o.half_extent, torch.full_like(o.angle[..., None], OBSTACLE_HEIGHT)), -1)
                update["obstacles"] = {"position": scenery.planar_to_3d(o.center.cpu(), OBSTACLE_HEIGHT / 2),
                                       "rotation": scenery.yaw_quat(o.angle.cpu()), "scale": scale.cpu(),
                                       "color": self._obstacle_color, "active": self._obstacle_active}
        return update

    def _state_obs(self):
        pos, vel, yaw, alive = self.bodies.pos, self.bodies.vel, self.yaw, self.alive
        W, N = pos.shape[:2]
        others_alive = alive[:, self._others]  # [W, N, N-1]
        others = (pos[:, self._others] - pos[:, :, None]) * others_alive[..., None]
        obstacles = (self.obstacles.center[:, None] - pos[:, :, None]).reshape(W, N, -1)
        return torch.cat((pos, vel, torch.cos(yaw)[..., None], torch.sin(yaw)[..., None], others.reshape(W, N, -1),
                          others_alive.to(pos.dtype), obstacles), -1)

    def _state_tensors(self):
        b, o = self.bodies, self.obstacles
        return {"pos": b.pos, "vel": b.vel, "active": b.active, "yaw": self.yaw,
                "obstacle_center": o.center, "obstacle_angle": o.angle}
