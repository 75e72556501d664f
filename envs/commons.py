"""Commons harvest: a mixed-motive social dilemma over regrowing apples, seen through egocentric cameras.

N agents (default 5) harvest red apples from patches on the floor. An apple regrows only
next to other apples, so a patch picked clean is gone for good: each agent gains from
picking fast, the group from leaving some. Agents can also tag (zap) one another out of
the game for a while. After Melting Pot's commons harvest, on the arena of envs/arena.py.

* Arena: |x|, |y| <= 2 m, walls and floor are static geometry.
* Agents: blue capsules of radius 0.15 m, mass 1, physics terms walls + body_collisions +
  drag, as in ``forage``. Camera at 0.4 m, pitched 0.2 rad down, 90 degree field of view.
* Apples: the same layout in every world and episode: 5 patches (centres (0, 0) and
  (+-1.1, +-1.1)), each a 3 x 3 grid of apples 0.25 m apart (45 apples); spheres of
  radius 0.06 m on the floor; not physics bodies. All present when an episode starts.
* Collecting: an agent in play (not tagged out) whose centre is closer than 0.21 m to a
  present apple (after the physics step) collects it, +1 reward; an apple touched by
  several agents goes to the closest (lowest index on a tie). Agents tagged in this step
  still collect in it.
* Regrowth: after collection, each missing apple comes back with probability
  ``regrowth[min(k, 3)]`` per step, k = present apples within 0.3 m (its grid neighbours up,
  down, left, right): default (0, 0.005, 0.02, 0.05) for k = 0, 1, 2, >= 3 (Melting Pot's
  (0, 0.001, 0.005, 0.025) scaled up for a 300-step episode). Draws from the env's generator.
* Tagging: the extra action "zap" (discrete action 5; continuous: the third value > 0.5)
  tags the nearest other agent in play within 1.5 m whose centre lies within 45 degrees of
  the zapper's heading (the camera's half field of view). Zapping costs nothing. A tagged
  agent is out for ``tag_timeout`` steps (default 25): not drawn, its body inactive (it
  neither moves, collides nor collects; its actions are ignored); then it reappears at
  one of 8 spawn points along the walls (drawn from the generator), facing the centre.
* Actions, egocentric, as in ``spread`` plus zap: discrete 6: 0 noop, 1 forward,
  2 turn left, 3 turn right, 4 backward, 5 zap; continuous 3: (thrust, turn rate, zap).
* action_mask: all valid for an agent in play; only noop while tagged out.
* Reward, per agent: +1 per apple it collected in the step.
* Episode: never terminates; truncated after ``max_steps`` = 300.
* Reset: agents in distinct random cells of a 4 x 4 grid of the arena, random yaw.
* State obs (7 + 3 M + 3 (N - 1), M = 45 apples): own position (2), velocity (2), cos/sin
  yaw (2), own remaining timeout / tag_timeout (1); apple positions relative to the agent
  times their present flag (2 each) and the flags (1 each); the other agents' relative
  positions times their in-play flag (2 each) and the flags (1 each). World frame.
* info (each [W]): ``"collected"`` int64 apples collected in the step, ``"apples_left"`` int64
  apples present after the step, ``"tags"`` int64 agents tagged in the step, ``"depleted_at"``
  int64 the step of the episode (1-based) at which the last apple went, -1 while some remain
  (depletion is final: nothing regrows without neighbours). Per-agent totals of the episode
  are the state field ``collected`` [W, A].
"""
from __future__ import annotations

import dataclasses
import math

import torch

import marl_render as mr
from marl_render.util.validation import COUNT_LIMIT, positive_int

from . import egomotion, scenery
from .arena import NOOP, ArenaScenario, ArenaState, Prop, numbered
from .roster import Bot, Card, HeldOut
from .scenario import MAX_COUNT

ARENA = 2.0  # half extent (m)
SPAWN_GRID = 4
AGENT_RADIUS = 0.15
APPLE_RADIUS = 0.06
APPLE_COLOR = (0.85, 0.08, 0.08)
REACH = AGENT_RADIUS + APPLE_RADIUS
NEIGHBOUR_RADIUS = 0.3  # the 4 grid neighbours (0.25 m) count, the diagonals (0.35 m) do not
PATCH_CENTRES = ((0.0, 0.0), (-1.1, -1.1), (-1.1, 1.1), (1.1, -1.1), (1.1, 1.1))
PATCH_SPACING = 0.25
ZAP_RANGE = 1.5
ZAP_HALF_ANGLE = math.radians(45.0)
RESPAWN_POINTS = ((-1.7, 0.0), (1.7, 0.0), (0.0, -1.7), (0.0, 1.7), (-1.7, -1.7), (-1.7, 1.7), (1.7, -1.7),
                  (1.7, 1.7))


def apple_layout() -> torch.Tensor:
    """[M, 2] apple places: a 3 x 3 grid around each patch centre."""
    offsets = torch.tensor([-PATCH_SPACING, 0.0, PATCH_SPACING])
    grid = torch.stack(torch.meshgrid(offsets, offsets, indexing="ij"), -1).reshape(9, 2)
    return (torch.tensor(PATCH_CENTRES)[:, None] + grid[None]).reshape(-1, 2)


@dataclasses.dataclass(frozen=True)
class CommonsParams:
    regrowth: tuple = (0.0, 0.005, 0.02, 0.05)  # probability per step for 0, 1, 2, >= 3 neighbours
    tag_timeout: int = 25  # steps a zapped agent stays out of the game

    def __post_init__(self):
        r = self.regrowth
        if not (isinstance(r, tuple) and len(r) == 4 and all(isinstance(p, (int, float)) and not isinstance(p, bool)
                                                             and 0 <= p <= 1 for p in r)):
            raise ValueError(f"regrowth must be a tuple of 4 probabilities in [0, 1], got {r!r}")
        positive_int("tag_timeout", self.tag_timeout, maximum=COUNT_LIMIT)


@dataclasses.dataclass(frozen=True)
class CommonsState(ArenaState):
    present: torch.Tensor  # [W, M] bool: apples there (drawn, collectable)
    timeout: torch.Tensor  # [W, A] int64: steps an agent stays tagged out; 0: in play
    shown: torch.Tensor  # [W, A] bool: agents drawn (in play)
    collected: torch.Tensor  # [W, A] int64: apples each agent collected this episode
    steps: torch.Tensor  # [W] int64: steps of the episode so far
    depleted_at: torch.Tensor  # [W] int64: step the last apple went, -1 while some remain


# Bot scripts (envs/roster.py): env -> actions of every agent of every world, [W, A].
def greedy(env) -> torch.Tensor:
    """Each harvester drives to the nearest present apple, ripe or not (it strips patches bare)."""
    s, state = env.scenario, env.sim
    W, N = env.num_worlds, env.num_agents
    dist = torch.cdist(state.pos[:, :N], s.apples.expand(W, -1, -1))
    dist = torch.where(state.present[:, None, :], dist, math.inf)
    target = torch.where(torch.isinf(dist.amin(-1))[..., None], state.pos[:, :N], s.apples[dist.argmin(-1)])
    return torch.where(state.timeout > 0, NOOP, s.steer_to(state, target))


def tagger(env) -> torch.Tensor:
    """A greedy harvester that zaps (action 5) every fourth step."""
    zap = (env.step_count[:, None] % 4 == 0) & (env.sim.timeout == 0)
    return torch.where(zap, 5, greedy(env))


class Commons(ArenaScenario):
    """Harvest regrowing apples, tag rivals; see the module docstring."""

    name = "commons"
    Params = CommonsParams
    # How fast apples regrow (by present neighbours): a forgiving or an unforgiving commons.
    difficulties = {"easy": {"regrowth": (0.0, 0.01, 0.04, 0.1)}, "medium": {},
                    "hard": {"regrowth": (0.0, 0.0025, 0.01, 0.025)}}
    State = CommonsState
    default_num_agents = 5
    agent_range = (2, 12)
    default_max_steps = 300
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"collected": torch.int64, "apples_left": torch.int64, "tags": torch.int64,
                 "depleted_at": torch.int64}
    arena_half_extent = (ARENA, ARENA)
    shown = "shown"
    mixed_motive = True  # social outcomes in info, Melting Pot's random episode ends (envs/episodes.py)
    bots = {"noisy0.1": Bot.noisy(0.1, population="train"),
            "greedy": Bot("harvests the nearest apple, ripe or not", script=greedy),
            "tagger": Bot("greedy, and zaps every fourth step", script=tagger),
            "lazy0.5": Bot.lazy(0.5)}
    heldout = (
        HeldOut("resident_with_greedy", "four focal harvesters with one greedy or tagging visitor", 5,
                tuple(numbered("agent", 4)), {"agents": ("greedy", "tagger")}),
        HeldOut("visitor_among_taggers", "one focal harvester among four greedy harvesters that zap", 5, ("agent_0",),
                {"agents": ("tagger", "greedy")}),
        HeldOut("resident_with_lazy", "three focal harvesters with two that idle half the time", 5,
                tuple(numbered("agent", 3)), {"agents": ("lazy0.5",)}),
    )
    card = Card(reward="per agent: +1 per apple it collects; apples regrow only next to present ones; zapping tags "
                       "another agent out for tag_timeout (25) steps",
                episode_end="never terminates; truncated at the episode's end (random by default: mixed motive)",
                continuous=egomotion.CONTINUOUS_MEANINGS + ("zap (> 0.5: tag the nearest agent in view within 1.5 m)",),
                info={"collected": "items (forage) or apples (commons) collected in this step",
                      "apples_left": "apples present after the step",
                      "tags": "agents tagged in this step (commons: out for a while; capture_flag: sent home)",
                      "depleted_at": "step of the episode at which the last apple went; -1 while some remain"})
    training = {"budget": {"pixels": 92_160, "state": 403_456}}  # env steps of the published runs

    def setup(self):
        N, self.apples = self.num_agents, apple_layout().to(self.device)
        M = self.num_apples = self.apples.shape[0]
        self.setup_arena({"agents": numbered("agent", N)}, state_dim=7 + 3 * M + 3 * (N - 1), radius=AGENT_RADIUS,
                         max_speed=2.0, extra_actions=("zap",))
        self.neighbours = (torch.cdist(self.apples, self.apples) < NEIGHBOUR_RADIUS) & ~torch.eye(M, dtype=torch.bool,
                                                                                                  device=self.device)
        self.regrowth = torch.tensor(self.params.regrowth, device=self.device)
        self.respawn_points = torch.tensor(RESPAWN_POINTS, device=self.device)
        self._agent_index = torch.arange(N, device=self.device)

    def _fresh(self, pos, yaw):
        W, N = self.num_worlds, self.num_agents
        return self.at_rest(pos, yaw, present=torch.ones(W, self.num_apples, dtype=torch.bool),
                            timeout=torch.zeros(W, N, dtype=torch.int64), shown=torch.ones(W, N, dtype=torch.bool),
                            collected=torch.zeros(W, N, dtype=torch.int64), steps=torch.zeros(W, dtype=torch.int64),
                            depleted_at=torch.full((W,), -1, dtype=torch.int64))

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self._fresh(torch.zeros(W, N, 2), torch.zeros(W, N))

    def state_bounds(self):
        # Counters of the episode grow while a world keeps stepping without autoreset.
        return {**super().state_bounds(), "timeout": (0, self.params.tag_timeout), "collected": (0, MAX_COUNT),
                "steps": (0, MAX_COUNT), "depleted_at": (-1, MAX_COUNT)}

    def check_state(self, state):
        if not torch.equal(state["shown"], state["timeout"] == 0):
            raise ValueError("state['shown'] must be True exactly for the agents in play (state['timeout'] == 0)")
        depleted, steps = state["depleted_at"], state["steps"]
        if bool(((depleted == 0) | (depleted > steps)).any()):
            raise ValueError("state['depleted_at'] must be -1 (apples left) or a step in [1, state['steps']]")

    def spawn_level(self, draws):
        W, N = self.num_worlds, self.num_agents
        pos = scenery.cell_spawn(draws, W, torch.full((N,), AGENT_RADIUS + 0.05), SPAWN_GRID, ARENA)
        return self._fresh(pos, (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi)

    def props(self):
        return [Prop("apples", mr.sphere(segments=10, rings=5), count=self.num_apples, height=APPLE_RADIUS,
                     position=lambda state: self.apples.expand(state.present.shape[0], -1, -1), active="present",
                     scale=(2 * APPLE_RADIUS,) * 3, color=APPLE_COLOR)]

    def bodies(self, state, active):
        return super().bodies(state, active & (state.timeout == 0))  # tagged agents neither move nor collide

    def tagged_out(self, state):
        return state.timeout > 0

    def rules(self, before, moved, actions, alive, generator):
        W, N, g = self.num_worlds, self.num_agents, generator
        playing = alive & (before.timeout == 0)  # [W, N]
        yaw = torch.where(playing, moved.yaw, before.yaw)
        # Collection: the closest agent in play touching a present apple takes it.
        dist = torch.cdist(moved.pos[:, :N], self.apples.expand(W, -1, -1))  # [W, N, M]
        touching = (dist < REACH) & before.present[:, None, :] & playing[:, :, None]
        taken = touching.any(1)
        taker = torch.where(touching, dist, torch.full_like(dist, math.inf)).argmin(1)  # [W, M]
        got = ((taker[:, None, :] == self._agent_index[None, :, None]) & taken[:, None, :]).sum(-1)  # [W, N]
        present = before.present & ~taken
        # Regrowth, by how many grid neighbours are present.
        k = (present.to(torch.float32) @ self.neighbours.to(torch.float32)).long().clamp_max(3)
        present = present | (torch.rand(present.shape, generator=g).to(self.device) < self.regrowth[k])
        # Tagging: each zapper hits the nearest agent in play within range and the view cone.
        zap = actions[..., 2] > 0.5 if self.continuous else actions == 5
        delta = moved.pos[:, None, :N] - moved.pos[:, :N, None]  # [W, zapper, target, 2]
        bearing = torch.atan2(-delta[..., 0], delta[..., 1])
        gap = torch.linalg.vector_norm(delta, dim=-1)
        seen = (scenery.wrap_angle(bearing - yaw[..., None]).abs() <= ZAP_HALF_ANGLE) & (gap <= ZAP_RANGE)
        seen &= (zap & playing)[:, :, None] & playing[:, None, :] & ~torch.eye(N, dtype=torch.bool, device=self.device)
        hit = torch.where(seen, gap, torch.full_like(gap, math.inf)).argmin(-1)  # [W, zapper]
        tagged = (torch.nn.functional.one_hot(hit, N).bool() & seen.any(-1, keepdim=True)).any(1)  # [W, N]
        # Timeouts count down; agents whose timeout ends come back at a random spawn point.
        timeout = (before.timeout - 1).clamp_min(0)
        back = (before.timeout == 1)
        point = self.respawn_points[torch.randint(len(RESPAWN_POINTS), (W, N), generator=g).to(self.device)]
        pos = torch.where(back[..., None], point, moved.pos[:, :N])
        yaw = torch.where(back, torch.atan2(point[..., 0], -point[..., 1]), yaw)  # facing the centre
        timeout = torch.where(tagged, self.params.tag_timeout, timeout)
        steps, left = before.steps + 1, present.sum(-1)
        depleted_at = torch.where((before.depleted_at < 0) & (left == 0), steps, before.depleted_at)
        state = dataclasses.replace(moved, pos=pos, yaw=yaw, vel=moved.vel * (timeout == 0)[..., None],
                                    present=present, timeout=timeout, shown=timeout == 0,
                                    collected=before.collected + got, steps=steps, depleted_at=depleted_at)
        info = {"collected": taken.sum(-1), "apples_left": left, "tags": tagged.sum(-1), "depleted_at": depleted_at}
        return state, got.to(torch.float32), torch.zeros_like(alive), info

    def action_mask(self, state, alive):
        mask = (alive & (state.timeout == 0))[:, :, None].expand(-1, -1, self.num_actions).clone()
        mask[..., 0] = True  # noop is always valid
        return mask

    def observation(self, state, alive):
        W, N = self.num_worlds, self.num_agents
        present = state.present[:, None, :, None].to(state.pos.dtype)  # [W, 1, M, 1]
        apples = (self.relative(state, self.apples.expand(W, -1, -1)) * present).reshape(W, N, -1)
        in_play = state.shown[:, self.others].to(state.pos.dtype)  # [W, N, N-1]
        others = (self.others_obs(state) * in_play[..., None]).reshape(W, N, -1)
        timeout = state.timeout[..., None].to(state.pos.dtype) / self.params.tag_timeout
        return torch.cat((self.own_obs(state), timeout, apples, present[..., 0].expand(W, N, -1), others, in_play), -1)

    def heuristic(self, state, alive):
        """A sustainable harvester: each agent drives to the nearest present apple with at least three
        present neighbours (so patches keep seeds to regrow from at a high rate), holding still when
        there is none (and while tagged, as its action mask says); it never zaps. Over 32 worlds it
        collects about 64 apples per episode to a greedy one's 50 (which strips every world bare)."""
        W, N = self.num_worlds, self.num_agents
        ripe = (state.present.to(torch.float32) @ self.neighbours.to(torch.float32)) >= 3
        dist = torch.cdist(state.pos[:, :N], self.apples.expand(W, -1, -1))  # [W, N, M]
        dist = torch.where((state.present & ripe)[:, None, :], dist, torch.full_like(dist, math.inf))
        target = self.apples[dist.argmin(-1)]  # [W, N, 2]
        target = torch.where(torch.isinf(dist.amin(-1))[..., None], state.pos[:, :N], target)
        action = self.steer_to(state, target)
        if self.continuous:
            return torch.cat((action, torch.zeros_like(action[..., :1])), -1)
        return torch.where(state.timeout > 0, 0, action)  # a tagged agent may only noop (its action mask)
