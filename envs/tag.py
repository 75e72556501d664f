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
  ``envs/planar.py`` with the terms walls + body_collisions + obstacles (only when
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

import dataclasses
import math

import torch

from marl_render.util.validation import positive_int, reward_weight

from . import egomotion, planar, scenery
from .arena import NOOP, ArenaScenario, ArenaState, Prop, numbered, wander
from .roster import Bot, Card, HeldOut

ARENA = 1.5  # half extent (m)
OBSTACLE_HALF = 0.2  # half side of the square obstacles (m)
OBSTACLE_HEIGHT = 0.4
OBSTACLE_COLOR = (0.35, 0.33, 0.30)
RADIUS = {"predator": 0.15, "prey": 0.12}  # m
THRUST = {"predator": 3.0, "prey": 4.0}  # N at full forward action
MAX_SPEED = {"predator": 1.0, "prey": 1.3}  # m/s
CONTACT_TOLERANCE = 0.02  # a predator "touches" a prey while their gap is below this (m)
SPAWN_CLEARANCE = 0.05  # spawned bodies keep this much space to their spawn cell's borders


@dataclasses.dataclass(frozen=True)
class TagParams:
    num_predators: int | None = None  # team sizes: see the module docstring
    num_prey: int | None = None  # team size of the prey (None: the default split)
    num_obstacles: int = 2  # 0 to 8
    catch_reward: float = 10.0  # to each predator per prey caught; minus it for the caught prey
    shaping: float = 0.0  # weight of the distance shaping: predators nearer prey, prey farther (0: off)

    def __post_init__(self):
        if self.num_predators is not None:
            positive_int("num_predators", self.num_predators)
        if self.num_prey is not None:
            positive_int("num_prey", self.num_prey)
        if positive_int("num_obstacles", self.num_obstacles, minimum=0) > 8:
            raise ValueError(f"num_obstacles must be an int in [0, 8], got {self.num_obstacles}")
        reward_weight("catch_reward", self.catch_reward)
        reward_weight("shaping", self.shaping, allow_zero=True)


@dataclasses.dataclass(frozen=True)
class TagState(ArenaState):
    obstacle_center: torch.Tensor  # [W, K, 2] (m)
    obstacle_angle: torch.Tensor  # [W, K] rad
    shown: torch.Tensor  # [W, A] bool: agents drawn in the current frame (those caught in it still are)


# Bot scripts (envs/roster.py): env -> actions of every agent of every world, [W, A].
def interceptor(env) -> torch.Tensor:
    """Predators aim where the nearest live prey will be in half a second; prey as the heuristic."""
    s, state, alive = env.scenario, env.sim, env.alive
    N = env.num_agents
    pos, vel = state.pos[:, :N], state.vel[:, :N]
    dist = torch.where(s.is_prey & alive[:, None, :], torch.cdist(pos, pos), math.inf)
    prey = dist.argmin(-1)[..., None].expand(-1, -1, 2)
    ahead = pos.gather(1, prey) + 0.5 * vel.gather(1, prey)
    chase = s.steer_to(state, ahead)
    return torch.where(s.is_predator, chase, s.heuristic(state, alive))


def lazy_predator(env) -> torch.Tensor:
    """Predators chase only prey within 1 m, else wait; prey as the heuristic."""
    s, state, alive = env.scenario, env.sim, env.alive
    N = env.num_agents
    pos = state.pos[:, :N]
    near = (torch.where(s.is_prey & alive[:, None, :], torch.cdist(pos, pos), math.inf).amin(-1) < 1.0)
    actions = s.heuristic(state, alive)
    return torch.where(s.is_predator & ~near, NOOP, actions)


def wandering_prey(env) -> torch.Tensor:
    """Prey wander round the arena, ignoring predators; predators as the heuristic."""
    s = env.scenario
    return torch.where(s.is_prey, wander(env), s.heuristic(env.sim, env.alive))


def corner_prey(env) -> torch.Tensor:
    """Prey hide in the corner nearest to where they are; predators as the heuristic."""
    s, state = env.scenario, env.sim
    hx, hy = s.arena_half_extent
    pos = state.pos[:, :env.num_agents]
    corner = torch.stack((torch.sign(pos[..., 0]) * 0.85 * hx, torch.sign(pos[..., 1]) * 0.85 * hy), -1)
    return torch.where(s.is_prey, s.steer_to(state, corner), s.heuristic(state, env.alive))


class Tag(ArenaScenario):
    """Predators and prey; see the module docstring."""

    name = "tag"
    Params = TagParams
    # Obstacles block the predators' view and path.
    difficulties = {"easy": {"num_obstacles": 0}, "medium": {}, "hard": {"num_obstacles": 6}}
    State = TagState
    default_num_agents = 4
    agent_range = (2, 16)
    default_max_steps = 100
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "obstacles", "drag"})  # "obstacles" only if K > 0
    info_keys = {"caught": torch.int64, "prey_left": torch.int64}
    arena_half_extent = (ARENA, ARENA)
    opponents = ("prey",)
    shown = "shown"  # caught prey are drawn in the frame of their catch, then no more
    sides = ("predator", "prey")  # cross-play: predator policies (rows) against prey policies (columns)
    bots = {"noisy0.2": Bot.noisy(0.2, population="train"),
            "interceptor": Bot("predators aim half a second ahead of the prey", script=interceptor),
            "lazy_predator": Bot("predators chase only prey within 1 m", script=lazy_predator),
            "wandering_prey": Bot("prey wander round the arena, ignoring predators", script=wandering_prey),
            "corner_prey": Bot("prey hide in their nearest corner", script=corner_prey)}
    heldout = (
        HeldOut("prey_vs_interceptors", "one focal prey against predators that aim ahead or wait", 4, ("prey_0",),
                {"predator": ("interceptor", "lazy_predator")}),
        HeldOut("predators_vs_wanderers", "focal predators hunt prey that wander or hide in corners", 4,
                tuple(numbered("predator", 3)), {"prey": ("wandering_prey", "corner_prey")}),
        HeldOut("pair_with_interceptor",
                "two focal predators with an interceptor teammate, against a wandering or hiding prey", 4,
                tuple(numbered("predator", 2)),
                {"predator": ("interceptor",), "prey": ("wandering_prey", "corner_prey")}),
    )
    card = Card(reward="predators: +catch_reward (10) each per prey caught by any predator; a caught prey: "
                       "-catch_reward; optional distance shaping",
                episode_end="a caught prey terminates (leaves the episode); every agent terminates when all prey are "
                            "caught; truncated at max_steps",
                continuous=egomotion.CONTINUOUS_MEANINGS,
                info={"caught": "prey caught in this step", "prey_left": "live prey after the step"})
    training = {"budget": {"pixels": 542_720, "state": 702_464}}  # env steps of the published runs

    @classmethod
    def num_agents_for(cls, params, num_agents):
        P, Q = params.num_predators, params.num_prey
        if num_agents is None and (P is not None or Q is not None):
            return (3 if P is None else P) + (1 if Q is None else Q)
        return num_agents

    def _team_sizes(self, N: int) -> tuple:
        P, Q = self.params.num_predators, self.params.num_prey
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

    def setup(self):
        N, K = self.num_agents, self.params.num_obstacles
        self.num_obstacles = K
        P, Q = self.num_predators, self.num_prey = self._team_sizes(N)
        self.physics_terms = frozenset({"walls", "body_collisions", "drag"} | ({"obstacles"} if K else set()))
        self.setup_arena({"predator": numbered("predator", P), "prey": numbered("prey", Q)},
                         state_dim=6 + 3 * (N - 1) + 2 * K, radius=RADIUS, max_speed=max(MAX_SPEED.values()))
        self.thrust, self.max_speed = self.per_agent(THRUST), self.per_agent(MAX_SPEED)
        self.is_predator = torch.arange(N, device=self.device) < P  # [N]
        self.is_prey = ~self.is_predator
        self._hunt = self.is_predator[:, None] & self.is_prey[None, :]  # [N, N] pairs (predator, prey)
        self._obstacle_half = torch.full((self.num_worlds, K, 2), OBSTACLE_HALF, device=self.device)
        # Spawn: obstacles (their half diagonal) then agents (radius + SPAWN_CLEARANCE), one cell each.
        self._spawn_grid = 4 if K + N <= 16 else 5
        self._spawn_margin = torch.cat((torch.full((K,), OBSTACLE_HALF * math.sqrt(2)),
                                        self.radius.cpu() + SPAWN_CLEARANCE))

    def initial_state(self):
        W, N, K = self.num_worlds, self.num_agents, self.num_obstacles
        return self.at_rest(torch.zeros(W, N, 2), torch.zeros(W, N), obstacle_center=torch.zeros(W, K, 2),
                            obstacle_angle=torch.zeros(W, K), shown=torch.ones(W, N, dtype=torch.bool))

    def props(self):
        if not self.num_obstacles:
            return []
        return [Prop("obstacles", "box", count=self.num_obstacles, position="obstacle_center",
                     height=OBSTACLE_HEIGHT / 2, yaw="obstacle_angle", color=OBSTACLE_COLOR,
                     scale=(2 * OBSTACLE_HALF, 2 * OBSTACLE_HALF, OBSTACLE_HEIGHT), moves=False, role="wall")]

    def obstacles(self, state):
        return planar.Obstacles(state.obstacle_center, self._obstacle_half, state.obstacle_angle)

    def state_bounds(self):
        return {**super().state_bounds(), "obstacle_center": self.inside_walls()}

    def spawn_level(self, draws):
        # Obstacles and agents each get their own random cell of the grid (see cell_spawn): nothing
        # overlaps at the start and no predator starts within a catch of a prey.
        W, N, K = self.num_worlds, self.num_agents, self.num_obstacles
        pos = scenery.cell_spawn(draws, W, self._spawn_margin, self._spawn_grid, ARENA)
        angle = (draws.rand("obstacle_angle", (W, K)) * 2 - 1) * (math.pi / 4)
        yaw = (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi
        return self.at_rest(pos[:, K:], yaw, obstacle_center=pos[:, :K], obstacle_angle=angle,
                            shown=torch.ones(W, N, dtype=torch.bool))

    def rules(self, before, moved, actions, alive, generator):
        moved = dataclasses.replace(moved, vel=planar.clamp_norm(moved.vel, self.max_speed[:, None]))
        dist = torch.cdist(moved.pos, moved.pos)  # [W, N, N]
        touch = dist < self.radius[:, None] + self.radius[None, :] + CONTACT_TOLERANCE
        hunt = self._hunt & alive[:, :, None] & alive[:, None, :]
        caught = (touch & hunt).any(dim=1)  # [W, N], only prey can be caught
        n_caught = caught.sum(-1)  # [W]
        left = alive & ~caught
        prey_left = (left & self.is_prey).sum(-1)
        zero = torch.zeros((), device=self.device)
        reward = torch.where(self.is_predator, self.params.catch_reward * n_caught[:, None].to(torch.float32),
                             torch.where(caught, -self.params.catch_reward, zero))
        if self.params.shaping:
            inf = torch.full_like(dist, math.inf)
            to_prey = torch.where(self.is_prey & left[:, None, :], dist, inf).amin(-1)  # [W, N]
            to_predator = torch.where(self.is_predator & alive[:, None, :], dist, inf).amin(-1)
            shaping = torch.where(self.is_predator, -to_prey, to_predator)
            shaping = torch.where(torch.isfinite(shaping) & left, shaping, torch.zeros_like(shaping))
            reward = reward + self.params.shaping * shaping
        terminated = caught | (prey_left == 0)[:, None]
        # Caught prey stop and leave; this step's frame still shows them (shown = alive before the step).
        stopped = torch.where(caught[..., None], torch.zeros_like(moved.vel), moved.vel)
        state = dataclasses.replace(moved, vel=stopped, active=alive & ~terminated, shown=alive)
        return state, reward, terminated, {"caught": n_caught, "prey_left": prey_left}

    def action_mask(self, state, alive):
        mask = alive[:, :, None].expand(-1, -1, self.num_actions).clone()
        mask[..., 0] = True  # noop is always valid
        return mask

    def observation(self, state, alive):
        W, N = self.num_worlds, self.num_agents
        others_alive = alive[:, self.others]  # [W, N, N-1]
        others = self.others_obs(state) * others_alive[..., None]
        return torch.cat((self.own_obs(state), others.reshape(W, N, -1), others_alive.to(state.pos.dtype),
                          self.relative(state, state.obstacle_center).reshape(W, N, -1)), -1)

    def heuristic(self, state, alive):
        """Predators chase the nearest live prey; prey run to the point of the arena farthest from
        the nearest predator (a corner pull, so they do not pin themselves to a wall)."""
        N = self.num_agents
        pos = state.pos[:, :N]
        dist = torch.cdist(pos, pos)
        inf = torch.full_like(dist, math.inf)
        to_prey = torch.where((self.is_prey & alive[:, None, :]), dist, inf).argmin(-1)  # [W, N]
        chase = pos.gather(1, to_prey[..., None].expand(-1, -1, 2))
        to_predator = torch.where(self.is_predator & alive[:, None, :], dist, inf).argmin(-1)
        threat = pos.gather(1, to_predator[..., None].expand(-1, -1, 2))
        away = pos - threat
        away = away / torch.linalg.vector_norm(away, dim=-1, keepdim=True).clamp_min(1e-6)
        flee = (pos + away).clamp(-ARENA * 0.8, ARENA * 0.8)
        target = torch.where(self.is_predator[None, :, None], chase, flee)
        return self.steer_to(state, target)
