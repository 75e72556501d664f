"""Cooperative navigation (MPE ``simple_spread``) with egocentric cameras.

N agents (default 3) must cover N landmarks in a walled arena. Every agent sees the
arena through its own camera mounted on its body, so it has to turn to look around.

* Arena: |x|, |y| <= 1.5 m, walls and floor are static geometry.
* Agents: capsules of radius 0.15 m, mass 1, physics from ``envs/planar.py`` with
  the terms walls + body_collisions + drag (MPE-like damping 0.25 per 0.1 s step).
  The camera sits at 0.4 m, pitched 0.2 rad down; a small dark "nose" box shows
  other agents which way a body faces (its own nose is hidden from its own view).
* Landmarks: flat discs of distinct colours; agents drive over them (no collision).
* Actions, egocentric (the body's yaw is where its camera looks):
  discrete 5: 0 noop, 1 forward, 2 turn left, 3 turn right, 4 backward;
  continuous 2: (thrust in [-1, 1] along the heading, turn rate in [-1, 1]).
  Movement as in envs/egomotion.py (shared by the arena envs, envs/arena.py).
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

import dataclasses
import math

import torch

from marl_render.util.validation import positive_int, reward_weight

from . import egomotion, scenery
from .arena import ArenaScenario, ArenaState, Prop, numbered, wander
from .roster import Bot, Card, HeldOut

ARENA = 1.5  # half extent (m)
SPAWN = 1.2  # agents and landmarks spawn in |x|, |y| <= SPAWN
AGENT_RADIUS = 0.15
LANDMARK_RADIUS = 0.15
LANDMARK_HEIGHT = 0.04
CONTACT_TOLERANCE = 0.02  # a pair "collides" while its gap is below this (m)


@dataclasses.dataclass(frozen=True)
class SpreadParams:
    num_landmarks: int | None = None  # 1 to 12; None: one per agent
    collision_penalty: float = 1.0  # per pair of agents touching, per step

    def __post_init__(self):
        if self.num_landmarks is not None:
            positive_int("num_landmarks", self.num_landmarks)
            if self.num_landmarks > 12:
                raise ValueError(f"num_landmarks must be an int in [1, 12], got {self.num_landmarks}")
        reward_weight("collision_penalty", self.collision_penalty, allow_zero=True)


@dataclasses.dataclass(frozen=True)
class SpreadState(ArenaState):
    landmarks: torch.Tensor  # [W, L, 2] landmark centres (m)


# Bot scripts (envs/roster.py): env -> actions of every agent of every world, [W, A].
def nearest_landmark(env) -> torch.Tensor:
    """Each agent drives to its nearest landmark, whoever else takes it."""
    s, state = env.scenario, env.sim
    dist = torch.cdist(state.pos[:, :env.num_agents], state.landmarks)
    target = state.landmarks.gather(1, dist.argmin(-1)[..., None].expand(-1, -1, 2))
    return s.steer_to(state, target)


class Spread(ArenaScenario):
    """Cooperative navigation; see the module docstring."""

    name = "spread"
    Params = SpreadParams
    # Landmarks to cover (medium: one per agent).
    difficulties = {"easy": {"num_landmarks": 2}, "medium": {}, "hard": {"num_landmarks": 6}}
    State = SpreadState
    default_num_agents = 3
    agent_range = (1, 12)
    default_max_steps = 100
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"collisions": torch.int64, "coverage": torch.float32}
    arena_half_extent = (ARENA, ARENA)
    bots = {"noisy0.2": Bot.noisy(0.2, population="train"),
            "nearest_landmark": Bot("drives to its nearest landmark, whoever else takes it", script=nearest_landmark),
            "wanderer": Bot("drives round a circle, ignoring landmarks", script=wander),
            "lazy0.5": Bot.lazy(0.5)}
    heldout = (
        HeldOut("two_with_nearest", "two focal agents with one partner that takes its nearest landmark or idles half "
                "the time", 3, tuple(numbered("agent", 2)), {"agents": ("nearest_landmark", "lazy0.5")}),
        HeldOut("one_among_nearest", "one focal agent among two partners that take their nearest landmark", 3,
                ("agent_0",), {"agents": ("nearest_landmark",)}),
        HeldOut("two_with_wanderer", "two focal agents with one partner that wanders", 3, tuple(numbered("agent", 2)),
                {"agents": ("wanderer",)}),
    )
    card = Card(reward="shared by all agents: -(sum over landmarks of the distance to the closest agent) - "
                       "collision_penalty x (agent pairs touching)",
                episode_end="never terminates; truncated at max_steps", continuous=egomotion.CONTINUOUS_MEANINGS,
                info={"collisions": "agent pairs touching (gap < 0.02 m) after the step",
                      "coverage": "sum over landmarks of the distance to the closest agent (m)"})
    training = {"budget": {"pixels": 573_440, "state": 1_047_552}}  # env steps of the published runs

    def setup(self):
        N = self.num_agents
        L = self.num_landmarks = N if self.params.num_landmarks is None else self.params.num_landmarks
        self.setup_arena({"agents": numbered("agent", N)}, state_dim=6 + 2 * L + 2 * (N - 1), radius=AGENT_RADIUS,
                         max_speed=2.0)
        self._pairs = torch.triu(torch.ones(N, N, dtype=torch.bool, device=self.device), diagonal=1)

    def initial_state(self):
        W, N, L = self.num_worlds, self.num_agents, self.num_landmarks
        return self.at_rest(torch.zeros(W, N, 2), torch.zeros(W, N), landmarks=torch.zeros(W, L, 2))

    def props(self):
        L = self.num_landmarks
        colors = scenery.palette(L + 1)  # index 1 (blue) is the agents' colour
        return [Prop("landmarks", scenery.disc_mesh(), count=L, position="landmarks", height=LANDMARK_HEIGHT / 2,
                     scale=(2 * LANDMARK_RADIUS, 2 * LANDMARK_RADIUS, LANDMARK_HEIGHT),
                     color=torch.cat((colors[:1], colors[2:])), moves=False)]

    def state_bounds(self):
        return {**super().state_bounds(), "landmarks": self.inside_walls()}

    def spawn_level(self, draws):
        W, N, L = self.num_worlds, self.num_agents, self.num_landmarks
        pos = (draws.rand("agents", (W, N, 2)) * 2 - 1) * SPAWN
        yaw = (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi
        landmarks = (draws.rand("landmarks", (W, L, 2)) * 2 - 1) * SPAWN
        return self.at_rest(pos, yaw, landmarks=landmarks)

    def rules(self, before, moved, actions, alive, generator):
        reward, collisions, coverage = self.reward(moved.landmarks, moved.pos)
        info = {"collisions": collisions, "coverage": coverage}
        return moved, reward[:, None].expand(-1, self.num_agents), torch.zeros_like(alive), info

    def reward(self, landmarks: torch.Tensor, pos: torch.Tensor):
        """Shared reward [W], colliding pairs [W] int64 and sum of landmark distances [W]."""
        coverage = torch.cdist(landmarks, pos).amin(dim=-1).sum(-1)  # [W, L, N] -> [W]
        gap = torch.cdist(pos, pos) - 2 * AGENT_RADIUS
        collisions = ((gap < CONTACT_TOLERANCE) & self._pairs).sum((-1, -2))
        return -coverage - self.params.collision_penalty * collisions, collisions, coverage

    def observation(self, state, alive):
        W, N = self.num_worlds, self.num_agents
        return torch.cat((self.own_obs(state), self.relative(state, state.landmarks).reshape(W, N, -1),
                          self.others_obs(state).reshape(W, N, -1)), -1)

    def heuristic(self, state, alive):
        """Each agent drives to its own landmark, assigned greedily by distance in agent order."""
        W, N, L = self.num_worlds, self.num_agents, self.num_landmarks
        dist = torch.cdist(state.pos[:, :N], state.landmarks)  # [W, N, L]
        target = torch.zeros(W, N, 2, device=self.device)
        taken = torch.zeros(W, L, dtype=torch.bool, device=self.device)
        for i in range(N):  # agents, not worlds: a fixed small loop over the task's own slots
            free = torch.where(taken, torch.full_like(dist[:, i], math.inf), dist[:, i])
            pick = free.argmin(-1)  # [W]
            target[:, i] = state.landmarks[torch.arange(W), pick]
            taken[torch.arange(W), pick] = True
        return self.steer_to(state, target, reach=LANDMARK_RADIUS * 0.5)
