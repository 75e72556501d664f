"""Team ball-pushing (a tiny football) with egocentric cameras.

Two teams push a ball into the other team's goal. Every agent sees the pitch through
its own camera mounted on its body.

* Pitch: |x| <= 1.5 m, |y| <= 2.0 m, walls and floor are static geometry. Each end has
  a goal: a coloured area of the floor ``|x| < GOAL_HALF_WIDTH`` (0.5 m), ``|y| > GOAL_LINE``
  (1.7 m) against the end wall, framed by two posts and a crossbar in the defending
  team's colour. ``red`` defends the goal at -y and attacks +y; ``blue`` defends +y
  and attacks -y.
* Agents: ``num_agents`` (even, 2 to 12, default 4 = 2 vs 2); agents ``0 .. N/2 - 1``
  are team ``red``, the rest team ``blue``; names ``red_i`` / ``blue_i`` (PettingZoo's
  ``<team>_<number>``), groups ``{"red": [...], "blue": [...]}`` (formerly
  ``team_a`` / ``team_b``).
  Capsules of radius 0.15 m, mass 1.
  The camera sits at 0.4 m, pitched 0.2 rad down; a dark "nose" box shows which way a
  body faces.
* Ball: a physics body (circle) of radius 0.15 m and mass 0.5, drawn as a white sphere.
  Physics from ``envs/planar.py`` with the terms walls + body_collisions + drag
  (MPE-like damping 0.25 per 0.1 s step for agents and ball alike), restitution 0.5.
* Actions, egocentric, as in ``spread``: discrete 5: 0 noop, 1 forward, 2 turn left,
  3 turn right, 4 backward; continuous 2: (thrust in [-1, 1] along the heading, turn
  rate in [-1, 1]). Movement as in envs/egomotion.py (shared by the arena envs).
  There is no kick: agents push the ball with their bodies.
* Goal: scored when, after the physics step, the ball's centre is inside a goal area.
  Every agent of the scoring team gets ``+goal_reward`` (default 1), every agent of the
  other team ``-goal_reward``, and the episode terminates (every agent terminated):
  one goal per episode. Optional shaping (``shaping`` >= 0, default 0, zero-sum):
  ``red`` additionally gets ``shaping x`` (the ball's progress along +y in the step,
  metres), ``blue`` the negative.
* Episode: truncated after ``max_steps`` = 200 if nobody scores.
* Reset: ``red`` in its own half (y in [-1.6, -0.45]) facing +y, ``blue`` mirrored,
  each yaw jittered by up to 0.5 rad; a team's agents in distinct lanes across the
  pitch (in random order) so nobody overlaps; the ball at rest within (0.3, 0.1) m of
  the centre spot.
* action_mask: every action is always valid (all True).
* State obs (10 + 2 (N - 1)), in the agent's **team frame** (``blue``'s frame is the
  world turned by 180 degrees, so every agent attacks +y): own position (2), velocity
  (2), cos/sin yaw (2), ball position relative to the agent (2), ball velocity (2),
  teammates' positions relative to the agent (2 each), then opponents' (2 each), each
  in agent-index order.
* info: ``"goal"`` int64 [W]: +1 ``red`` scored in this step, -1 ``blue`` scored,
  0 none.
"""
from __future__ import annotations

import dataclasses
import math

import torch

import marl_render as mr
from marl_render.util.validation import reward_weight

from . import egomotion, scenery
from .arena import ArenaScenario, Prop, Static, numbered
from .roster import Bot, Card, HeldOut

ARENA = (1.5, 2.0)  # half extents (m)
GOAL_HALF_WIDTH = 0.5
GOAL_LINE = 1.7  # a goal area is |y| > GOAL_LINE, |x| < GOAL_HALF_WIDTH
SPAWN_X = 1.3  # agents spawn in |x| <= SPAWN_X, one lane of 2 SPAWN_X / (N / 2) per agent
SPAWN_Y = (0.45, 1.6)  # |y| range of the spawn area in the own half
SPAWN_CLEARANCE = 0.02
SPAWN_YAW_JITTER = 0.5
AGENT_RADIUS = 0.15
BALL_RADIUS = 0.15
BALL_MASS = 0.5
BALL_COLOR = (0.95, 0.95, 0.92)
WALL_THICKNESS = 0.1  # scenery.add_arena's default
POST_SIZE = 0.08
POST_HEIGHT = 0.6


def goals() -> list:
    """Static goal areas (floor patches) and goal frames (posts + crossbar) at both ends."""
    hy = ARENA[1]
    depth = hy - GOAL_LINE
    area_y, frame_y = (GOAL_LINE + hy) / 2, hy + WALL_THICKNESS / 2
    positions, scales, colors = [], [], []
    area_pos, area_scale, area_color = [], [], []
    for side, team in ((-1.0, "red"), (1.0, "blue")):  # the goal at side * y is team's own
        color = list(scenery.TEAM_COLORS[team])
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
    return [Static("goal_areas", "plane", position=area_pos, scale=area_scale, color=area_color),
            Static("goal_frames", "box", position=positions, scale=scales, color=colors)]


@dataclasses.dataclass(frozen=True)
class PushParams:
    goal_reward: float = 1.0  # to every agent of the scoring team; minus it for the other team
    shaping: float = 0.0  # weight of the zero-sum reward for the ball's progress (0: off)

    def __post_init__(self):
        reward_weight("goal_reward", self.goal_reward)
        reward_weight("shaping", self.shaping, allow_zero=True)


# Bot scripts (envs/roster.py): env -> actions of every agent of every world, [W, A].
def ball_chaser(env) -> torch.Tensor:
    """Every agent drives straight at the ball."""
    state = env.sim
    return env.scenario.steer_to(state, state.pos[:, -1:].expand(-1, env.num_agents, 2))


def goalkeeper(env) -> torch.Tensor:
    """Every agent stands on its own goal line, level with the ball."""
    s, state = env.scenario, env.sim
    own_goal_y = -s.side * 0.85 * s.arena_half_extent[1]  # [N]
    ball_x = state.pos[:, -1:, 0].expand(-1, env.num_agents)
    return s.steer_to(state, torch.stack((ball_x, own_goal_y.expand_as(ball_x)), -1))


class Push(ArenaScenario):
    """Two teams push a ball into the other team's goal; see the module docstring."""

    name = "push"
    Params = PushParams
    # A shaped reward for moving the ball towards the goal, or half the time to score.
    difficulties = {"easy": {"shaping": 0.5}, "medium": {}, "hard": {"max_steps": 100}}
    default_num_agents = 4
    agent_range = (2, 12)
    default_max_steps = 200
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"goal": torch.int64}
    arena_half_extent = ARENA
    opponents = ("blue",)
    sides = ("red", "blue")  # cross-play: red policies (rows) against blue policies (columns)
    bots = {"noisy0.2": Bot.noisy(0.2, population="train"),
            "ball_chaser": Bot("drives straight at the ball", script=ball_chaser),
            "goalkeeper": Bot("stands on its goal line, level with the ball", script=goalkeeper),
            "lazy0.5": Bot.lazy(0.5)}
    heldout = (
        HeldOut("red_vs_chasers", "focal red team against ball chasers or goalkeepers", 4, tuple(numbered("red", 2)),
                {"blue": ("ball_chaser", "goalkeeper")}),
        HeldOut("blue_vs_chasers", "focal blue team against ball chasers or goalkeepers", 4,
                tuple(numbered("blue", 2)), {"red": ("ball_chaser", "goalkeeper")}),
        HeldOut("with_lazy_teammate", "one focal red player with an idle-half-the-time teammate, against ball chasers",
                4, ("red_0",), {"red": ("lazy0.5",), "blue": ("ball_chaser",)}),
    )
    card = Card(reward="+goal_reward (1) to every agent of the scoring team, -goal_reward to the other team; "
                       "optional zero-sum shaping by the ball's progress",
                episode_end="a goal terminates every agent (one goal per episode); truncated at max_steps",
                continuous=egomotion.CONTINUOUS_MEANINGS,
                info={"goal": "+1: red scored in this step, -1: blue scored, 0: no goal"})
    training = {"budget": {"pixels": 763_904, "state": 939_008}}  # env steps of the published runs

    def setup(self):
        N = self.num_agents
        if N % 2:
            raise ValueError(f"num_agents must be even for push (two equal teams), got {N}")
        T = N // 2
        # Bodies 0 .. N-1 are the agents, body N is the ball.
        self.setup_arena({"red": numbered("red", T), "blue": numbered("blue", T)},
                         state_dim=10 + 2 * (N - 1), radius=AGENT_RADIUS, max_speed=3.0, substeps=3,
                         bodies=((BALL_RADIUS, BALL_MASS),))
        self.is_red = torch.arange(N, device=self.device) < T
        self.side = self.per_agent({"red": 1.0, "blue": -1.0})  # +1: attacks +y (red), -1: attacks -y
        # Per agent: teammates then opponents, each in index order, [N, N-1].
        self.others = torch.tensor([[j for j in range(N) if j != i and (j < T) == (i < T)]
                                    + [j for j in range(N) if (j < T) != (i < T)] for i in range(N)],
                                   dtype=torch.long, device=self.device).reshape(N, N - 1)

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self.at_rest(torch.zeros(W, N + 1, 2), torch.zeros(W, N))

    def props(self):
        return goals() + [Prop("ball", mr.sphere(segments=10, rings=5), count=1, position=ball_position,
                               height=BALL_RADIUS, scale=(2 * BALL_RADIUS,) * 3, color=BALL_COLOR)]

    def spawn_level(self, draws):
        W, N = self.num_worlds, self.num_agents
        T = N // 2
        # Each team's agents take the T lanes across the pitch in a random order (so they never
        # overlap), with a random x inside the lane that keeps SPAWN_CLEARANCE to its borders.
        lane = draws.rand("lanes", (W, 2, T)).argsort(-1).reshape(W, N).to(self.device)
        u = draws.rand("spots", (W, N, 3)).to(self.device)
        width = 2 * SPAWN_X / T
        x = (lane + 0.5) * width - SPAWN_X + (u[..., 0] * 2 - 1) * max(0.0, width / 2 - AGENT_RADIUS - SPAWN_CLEARANCE)
        y = -self.side * (SPAWN_Y[0] + u[..., 1] * (SPAWN_Y[1] - SPAWN_Y[0]))  # own half
        yaw = torch.where(self.is_red, 0.0, math.pi) + (u[..., 2] * 2 - 1) * SPAWN_YAW_JITTER
        ball = ((draws.rand("ball", (W, 1, 2)) * 2 - 1) * torch.tensor([0.3, 0.1])).to(self.device)
        return self.at_rest(torch.cat((torch.stack((x, y), -1), ball), 1), scenery.wrap_angle(yaw))

    def rules(self, before, moved, actions, alive, generator):
        ball_before, ball = before.pos[:, -1], moved.pos[:, -1]
        in_mouth = ball[:, 0].abs() < GOAL_HALF_WIDTH
        goal = ((in_mouth & (ball[:, 1] > GOAL_LINE)).long() - (in_mouth & (ball[:, 1] < -GOAL_LINE)).long())  # [W]
        reward = self.params.goal_reward * goal[:, None].to(torch.float32) * self.side  # [W, N]
        if self.params.shaping:
            reward = reward + self.params.shaping * (ball[:, 1] - ball_before[:, 1])[:, None] * self.side
        terminated = (goal != 0)[:, None].expand(-1, self.num_agents)
        return moved, reward, terminated, {"goal": goal}

    def observation(self, state, alive):
        s = self.side[None, :, None]  # team frame: blue's coordinates turned by 180 degrees
        agents, vel = state.pos[:, :-1], state.vel[:, :-1]
        ball, ball_vel = state.pos[:, -1], state.vel[:, -1]
        W, N = agents.shape[:2]
        yaw = state.yaw + torch.where(self.is_red, 0.0, math.pi)
        others = self.others_obs(state) * s[..., None]  # [W, N, N-1, 2]
        return torch.cat((agents * s, vel * s, torch.cos(yaw)[..., None], torch.sin(yaw)[..., None],
                          (ball[:, None] - agents) * s, ball_vel[:, None] * s, others.reshape(W, N, -1)), -1)

    def heuristic(self, state, alive):
        """Every agent goes to the point behind the ball on the line from the goal it attacks, then
        drives through the ball towards that goal."""
        N = self.num_agents
        ball = state.pos[:, -1:].expand(-1, N, 2)
        goal = torch.stack((torch.zeros_like(self.side), self.side * ARENA[1]), -1)  # [N, 2]
        line = goal - ball
        line = line / torch.linalg.vector_norm(line, dim=-1, keepdim=True).clamp_min(1e-6)
        behind = ball - line * (BALL_RADIUS + AGENT_RADIUS + 0.1)
        lined_up = (state.pos[:, :N] - behind).norm(dim=-1, keepdim=True) < 0.15
        return self.steer_to(state, torch.where(lined_up, goal.expand_as(ball), behind))


def ball_position(state) -> torch.Tensor:
    """[W, 1, 2]: the ball is the last body."""
    return state.pos[:, -1:]
