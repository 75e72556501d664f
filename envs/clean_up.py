"""Clean up: a public-good dilemma. Apples grow only while someone cleans a river far from them.

N agents (default 7) share an arena with a river along one wall and an orchard along the
opposite one. Dirt piles up in the river; the dirtier it is, the slower apples regrow, and at a
threshold they stop. Eating an apple pays +1; cleaning pays nothing and takes an agent away
from the apples. So each agent gains from eating while others clean, and the group starves if
nobody cleans. Agents can also zap one another out of the game for a while. After Melting Pot's
clean_up, on the arena of envs/arena.py, written on the public task API (docs/authoring.md).

* Arena: |x|, |y| <= 2 m. River: the band 1.1 <= y <= 1.9 (drawn blue), split into 16 dirt
  cells (2 rows at y = 1.3, 1.7; 8 columns at x = -1.75, -1.25, ..., 1.75). Orchard: the band
  -1.9 <= y <= -0.55 (drawn green) with 32 apple places (4 rows at y = -1.75, -1.4, -1.05, -0.7;
  the same 8 columns). Agents walk everywhere; apples and dirt are not physics bodies.
* Agents: capsules of radius 0.15 m (purple), physics walls + body_collisions + drag, as in
  ``commons``.
* Dirt: each clean cell becomes dirty with probability ``dirt_rate`` per step (default 0.01).
* Regrowth: each missing apple comes back with probability ``apple_regrowth * max(0, 1 - d /
  dirt_threshold)`` per step (defaults 0.05 and 0.4), d = the river's dirt fraction after the
  step's cleaning and new dirt: the full rate in a clean river, half of it at half the threshold,
  none from the threshold up. Draws from the env's generator.
* Eating: an agent in play whose centre is closer than 0.21 m to a present apple eats it, +1; an
  apple touched by several goes to the closest (lowest index on a tie).
* Cleaning: the extra action "clean" (discrete 6; continuous: the fourth value > 0.5) removes
  the dirt of every cell whose centre lies in the beam in front of the agent: 0 < forward <= 1 m
  along its heading and |sideways| <= 0.25 m (one column of cells, both rows from the bank).
  It pays nothing.
* Zapping: the extra action "zap" (discrete 5; continuous: the third value > 0.5) tags the
  nearest other agent in play within 1.5 m and 45 degrees of the zapper's heading. A tagged agent
  is out for ``tag_timeout`` steps (default 25): not drawn, its body inactive, its actions ignored;
  then it reappears at one of 7 points across the middle of the arena (y = 0.3).
* Actions: discrete 7: 0 noop, 1 forward, 2 turn left, 3 turn right, 4 backward, 5 zap,
  6 clean; continuous 4: (thrust, turn rate, zap, clean). action_mask: only noop while tagged.
* Episode: never terminates; truncated after ``max_steps`` = 300.
* Reset (levels): agents in distinct random cells of a 7 x 2 grid of the middle band
  (-0.45 <= y <= 1.05), random yaw; each dirt cell dirty with probability ``initial_dirt``
  (default 0.25), each apple present with probability 0.5.
* State obs (7 + 3 D + 3 M + 3 (N - 1), D = 16, M = 32): own position, velocity, cos/sin yaw,
  remaining timeout / tag_timeout; dirt cells relative to the agent times their dirty flag and
  the flags; apples relative times their present flag and the flags; the other agents relative
  times their in-play flag and the flags. World frame.
* info (each [W]): ``"eaten"`` int64 apples eaten in the step, ``"cleaned"`` int64 dirt cells
  cleaned in the step, ``"dirt_fraction"`` float32 after the step, ``"apples_left"`` int64,
  ``"tags"`` int64 agents tagged in the step.
"""
from __future__ import annotations

import dataclasses
import math

import torch

import marl_render as mr
from marl_render.envs import ArenaScenario, ArenaState, Prop, Static, egomotion, numbered
from marl_render.envs.roster import Bot, Card, HeldOut
from marl_render.envs.scenario import MAX_COUNT
from marl_render.envs.scenery import heading, wrap_angle
from marl_render.util.validation import COUNT_LIMIT, finite_float, positive_int

ARENA = 2.0  # half extent (m)
AGENT_RADIUS = 0.15
AGENT_COLOR = (0.6, 0.35, 0.85)
APPLE_RADIUS = 0.06
APPLE_COLOR = (0.85, 0.08, 0.08)
REACH = AGENT_RADIUS + APPLE_RADIUS
COLUMNS = tuple(-1.75 + 0.5 * k for k in range(8))
DIRT_ROWS = (1.3, 1.7)
APPLE_ROWS = (-1.75, -1.4, -1.05, -0.7)
RIVER = (1.1, 1.9)  # y extent of the river band
ORCHARD = (-1.9, -0.55)  # y extent of the orchard band
RIVER_COLOR = (0.15, 0.45, 0.8)
ORCHARD_COLOR = (0.25, 0.5, 0.2)
DIRT_COLOR = (0.42, 0.3, 0.12)
DIRT_SIZE = (0.42, 0.34)
CLEAN_RANGE = 1.0  # the beam reaches this far ahead (m)
CLEAN_HALF_WIDTH = 0.25  # and this far to each side
ZAP_RANGE = 1.5
ZAP_HALF_ANGLE = math.radians(45.0)
SPAWN_BAND = (-0.45, 1.05)  # agents spawn in a 7 x 2 grid of cells of this y band
SPAWN_COLUMNS, SPAWN_ROWS = 7, 2
RESPAWN_POINTS = tuple((-ARENA + (k + 0.5) * 2 * ARENA / 7, 0.3) for k in range(7))
APPLE_START = 0.5  # each apple is present at a reset with this probability
ORCHARD_WAIT = (0.0, -1.2)  # where eaters wait while no apple is left
BANK_Y = 0.85  # where cleaners wait while the river is clean
CLEANER_SHARE = 2 / 7  # the heuristic's share of cleaners (at least one)
NOOP, ZAP, CLEAN = 0, 5, 6


def grid(xs, ys) -> torch.Tensor:
    """[len(ys) * len(xs), 2] points, row after row."""
    return torch.tensor([(x, y) for y in ys for x in xs])


def probability(name: str, value) -> float:
    value = finite_float(name, value)
    if not 0 <= value <= 1:
        raise ValueError(f"{name} must be a probability in [0, 1], got {value}")
    return value


@dataclasses.dataclass(frozen=True)
class CleanUpParams:
    dirt_rate: float = 0.01  # probability per step that a clean river cell becomes dirty
    dirt_threshold: float = 0.4  # dirt fraction at which apples stop regrowing
    apple_regrowth: float = 0.05  # probability per step that a missing apple regrows in a clean river
    initial_dirt: float = 0.25  # probability that a river cell is dirty when an episode starts
    tag_timeout: int = 25  # steps a zapped agent stays out of the game

    def __post_init__(self):
        for name in ("dirt_rate", "apple_regrowth", "initial_dirt"):
            probability(name, getattr(self, name))
        if not 0 < probability("dirt_threshold", self.dirt_threshold):
            raise ValueError(f"dirt_threshold must be a fraction in (0, 1], got {self.dirt_threshold}")
        positive_int("tag_timeout", self.tag_timeout, maximum=COUNT_LIMIT)


@dataclasses.dataclass(frozen=True)
class CleanUpState(ArenaState):
    dirt: torch.Tensor  # [W, D] bool: dirty river cells
    present: torch.Tensor  # [W, M] bool: apples there
    timeout: torch.Tensor  # [W, A] int64: steps an agent stays tagged out; 0: in play
    shown: torch.Tensor  # [W, A] bool: agents drawn (in play)
    eaten: torch.Tensor  # [W, A] int64: apples each agent ate this episode
    cleaned: torch.Tensor  # [W, A] int64: dirt cells each agent's beam cleaned this episode
    steps: torch.Tensor  # [W] int64: steps of the episode so far


# ---------------------------------------------------------------------- the test bots (roster.Bot scripts)
def cleaner(env) -> torch.Tensor:
    """Every slot cleans the river and never eats."""
    return env.scenario.scripted(env.sim, torch.ones_like(env.alive))


def free_rider(env) -> torch.Tensor:
    """Every slot eats the nearest apple and never cleans."""
    return env.scenario.scripted(env.sim, torch.zeros_like(env.alive))


def zapper(env) -> torch.Tensor:
    """A free rider that zaps whoever is in its zap cone."""
    return env.scenario.scripted(env.sim, torch.zeros_like(env.alive), zap=True)


def cooperator(env) -> torch.Tensor:
    """Every slot cleans while the river is dirty (its dirt fraction at least half of dirt_threshold,
    where apples regrow at half the rate) and eats the nearest apple otherwise; never zaps."""
    scenario = env.scenario
    dirty = env.sim.dirt.to(torch.float32).mean(-1) >= scenario.params.dirt_threshold / 2  # [W]
    return scenario.scripted(env.sim, dirty[:, None].expand_as(env.alive))


CARD_TEXT = """\
**Clean up** is a public-good dilemma after Melting Pot's substrate of the same name. A river runs
along one wall of the arena and an orchard along the opposite one. Dirt piles up in the river cell
by cell. Apples regrow in the orchard at a rate that falls linearly with the river's dirt fraction
and stops at a threshold (40 % by default).

**Rewards.** Eating an apple (driving onto it) pays +1 to the eater. Cleaning pays nothing: the
`clean` action sweeps a beam 1 m ahead of the agent and removes the dirt under it. The `zap` action
tags the nearest agent in front within 1.5 m out of the game for 25 steps.

**Observations.** Pixels from each agent's own camera; the state observation gives the agent's
pose and timeout, every river cell and apple relative to it with its flag, and the other agents.

**The dilemma.** Each agent does best by eating while others clean: a cleaner stands at the river,
far from the apples its work makes grow. If everyone reasons so, the river silts up and the orchard
dies, and all earn less than a group that sends some of its members to clean. The heuristic sends
two agents in seven to clean and the rest to eat, and never zaps.
"""


class CleanUp(ArenaScenario):
    """Clean a river that pays nothing so that apples grow; see the module docstring."""

    name = "clean_up"
    Params = CleanUpParams
    # How fast the river silts up, and how much dirt the orchard tolerates.
    difficulties = {"easy": {"dirt_rate": 0.005, "dirt_threshold": 0.6}, "medium": {},
                    "hard": {"dirt_rate": 0.02, "dirt_threshold": 0.3}}
    State = CleanUpState
    default_num_agents = 7
    agent_range = (2, SPAWN_COLUMNS * SPAWN_ROWS)
    default_max_steps = 300
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"eaten": torch.int64, "cleaned": torch.int64, "dirt_fraction": torch.float32,
                 "apples_left": torch.int64, "tags": torch.int64}
    arena_half_extent = (ARENA, ARENA)
    team_colors = {"agents": AGENT_COLOR}
    shown = "shown"
    mixed_motive = True
    card = Card(text=CARD_TEXT,
                reward="per agent: +1 per apple it eats; cleaning the river pays nothing but apples regrow only "
                       "while its dirt fraction is below dirt_threshold (0.4); zapping tags another agent out for "
                       "tag_timeout (25) steps",
                episode_end="never terminates; truncated at the episode's end (random by default: mixed motive)",
                continuous=egomotion.CONTINUOUS_MEANINGS + (
                    "zap (> 0.5: tag the nearest agent in play within 1.5 m and 45 degrees ahead)",
                    "clean (> 0.5: remove the dirt of the river cells up to 1 m ahead, 0.25 m to each side)"),
                info={"eaten": "apples eaten in this step",
                      "cleaned": "dirty river cells cleaned in this step",
                      "dirt_fraction": "fraction of the river's 16 cells dirty after the step",
                      "apples_left": "apples present after the step",
                      "tags": "agents zapped out in this step"})
    # Step budgets (env steps summed over worlds): 90 and 180 updates of 32 worlds x 32 decisions, what three seeds
    # of every new task fit in one 3-hour session on 2 cores. The estimate for learning was twice commons' (180
    # and 788 updates), as cleaning pays only through the apples it lets regrow: these are short runs.
    training = {"budget": {"pixels": 92_160, "state": 184_320}}
    bots = {"cleaner": Bot("cleans the river and never eats", script=cleaner),
            "free_rider": Bot("eats the nearest apple and never cleans", script=free_rider),
            "zapper": Bot("a free rider that zaps whoever is in front of it", script=zapper),
            "lazy0.5": Bot.lazy(0.5),
            "noisy0.1": Bot.noisy(0.1, population="train"),
            # Last, so that the bots above keep their places (and draws) in the test population.
            "cooperator": Bot("cleans while the river is dirty (at least half the threshold), eats otherwise",
                              script=cooperator)}
    schelling = ("cooperator", "free_rider")  # baselines/schelling.py: the dilemma's two modes
    heldout = (
        HeldOut("resident_with_free_riders", "five focal agents with two that eat and never clean", num_agents=7,
                focal=tuple(numbered("agent", 5)), bots_by_role={"agents": ("free_rider",)}),
        HeldOut("resident_with_zappers", "four focal agents with three free riders that zap", num_agents=7,
                focal=tuple(numbered("agent", 4)), bots_by_role={"agents": ("zapper", "free_rider")}),
        HeldOut("visitor_among_cleaners", "one focal agent among six that only clean", num_agents=7,
                focal=("agent_0",), bots_by_role={"agents": ("cleaner",)}),
        HeldOut("visitor_among_free_riders", "two focal agents among five free riders: nobody else cleans",
                num_agents=7, focal=tuple(numbered("agent", 2)), bots_by_role={"agents": ("free_rider", "zapper")}),
    )

    def setup(self):
        N = self.num_agents
        self.dirt_cells = grid(COLUMNS, DIRT_ROWS).to(self.device)  # [D, 2]
        self.apples = grid(COLUMNS, APPLE_ROWS).to(self.device)  # [M, 2]
        D, M = self.num_cells, self.num_apples = self.dirt_cells.shape[0], self.apples.shape[0]
        self.setup_arena({"agents": numbered("agent", N)}, state_dim=7 + 3 * D + 3 * M + 3 * (N - 1),
                         radius=AGENT_RADIUS, max_speed=2.0, extra_actions=("zap", "clean"))
        self.respawn_points = torch.tensor(RESPAWN_POINTS, device=self.device)
        self._agent_index = torch.arange(N, device=self.device)
        self._not_self = ~torch.eye(N, dtype=torch.bool, device=self.device)

    def _fresh(self, pos, yaw, dirt, present):
        W, N = self.num_worlds, self.num_agents
        counts = torch.zeros(3, W, N, dtype=torch.int64)
        return self.at_rest(pos, yaw, dirt=dirt, present=present, timeout=counts[0],
                            shown=torch.ones(W, N, dtype=torch.bool), eaten=counts[1], cleaned=counts[2],
                            steps=torch.zeros(W, dtype=torch.int64))

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self._fresh(torch.zeros(W, N, 2), torch.zeros(W, N), torch.zeros(W, self.num_cells, dtype=torch.bool),
                           torch.ones(W, self.num_apples, dtype=torch.bool))

    def state_bounds(self):
        # Counters of the episode grow while a world keeps stepping without autoreset.
        return {**super().state_bounds(), "timeout": (0, self.params.tag_timeout), "eaten": (0, MAX_COUNT),
                "cleaned": (0, MAX_COUNT), "steps": (0, MAX_COUNT)}

    def check_state(self, state):
        if not torch.equal(state["shown"], state["timeout"] == 0):
            raise ValueError("state['shown'] must be True exactly for the agents in play (state['timeout'] == 0)")

    def spawn_level(self, draws):
        W, N = self.num_worlds, self.num_agents
        cell = torch.tensor((2 * ARENA / SPAWN_COLUMNS, (SPAWN_BAND[1] - SPAWN_BAND[0]) / SPAWN_ROWS))
        order = draws.rand("cells.order", (W, SPAWN_COLUMNS * SPAWN_ROWS)).argsort(-1)[:, :N]
        corner = torch.tensor((-ARENA, SPAWN_BAND[0]))
        centre = (torch.stack((order % SPAWN_COLUMNS, order // SPAWN_COLUMNS), -1) + 0.5) * cell + corner
        pos = centre + (draws.rand("cells.offset", (W, N, 2)) * 2 - 1) * (cell / 2 - AGENT_RADIUS - 0.05)
        yaw = (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi
        dirt = draws.rand("dirt", (W, self.num_cells)) < self.params.initial_dirt
        present = draws.rand("apples", (W, self.num_apples)) < APPLE_START
        return self._fresh(pos, yaw, dirt, present)

    def props(self):
        river, orchard = (RIVER[1] - RIVER[0], (RIVER[0] + RIVER[1]) / 2), (ORCHARD[1] - ORCHARD[0],
                                                                           (ORCHARD[0] + ORCHARD[1]) / 2)
        width = 2 * ARENA - 0.1
        return [
            Static("river", "box", position=[[0.0, river[1], 0.005]], scale=[[width, river[0], 0.01]],
                   color=[RIVER_COLOR]),
            Static("orchard", "box", position=[[0.0, orchard[1], 0.004]], scale=[[width, orchard[0], 0.008]],
                   color=[ORCHARD_COLOR]),
            Prop("dirt", "box", count=self.num_cells, height=0.02, active="dirt", moves=True,
                 position=lambda state: self.dirt_cells.expand(state.dirt.shape[0], -1, -1),
                 scale=(*DIRT_SIZE, 0.02), color=DIRT_COLOR),
            Prop("apples", mr.sphere(segments=10, rings=5), count=self.num_apples, height=APPLE_RADIUS,
                 position=lambda state: self.apples.expand(state.present.shape[0], -1, -1), active="present",
                 scale=(2 * APPLE_RADIUS,) * 3, color=APPLE_COLOR),
        ]

    def bodies(self, state, active):
        return super().bodies(state, active & (state.timeout == 0))  # tagged agents neither move nor collide

    # ------------------------------------------------------------------ rules
    def in_beam(self, pos: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
        """[W, A, D] bool: the river cells in each agent's cleaning beam (agents at pos [W, A, 2], yaw [W, A])."""
        delta = self.dirt_cells[None, None] - pos[:, :, None]  # [W, A, D, 2]
        ahead = heading(yaw)[:, :, None]  # [W, A, 1, 2]
        forward = (delta * ahead).sum(-1)
        sideways = delta[..., 0] * ahead[..., 1] - delta[..., 1] * ahead[..., 0]
        return (forward > 0) & (forward <= CLEAN_RANGE) & (sideways.abs() <= CLEAN_HALF_WIDTH)

    def zap_targets(self, pos: torch.Tensor, yaw: torch.Tensor, playing: torch.Tensor) -> torch.Tensor:
        """[W, zapper, target] bool: the agents in play within each agent's zap cone and range."""
        delta = pos[:, None] - pos[:, :, None]  # [W, zapper, target, 2]
        bearing = torch.atan2(-delta[..., 0], delta[..., 1])
        gap = torch.linalg.vector_norm(delta, dim=-1)
        cone = (wrap_angle(bearing - yaw[..., None]).abs() <= ZAP_HALF_ANGLE) & (gap <= ZAP_RANGE)
        return cone & playing[:, :, None] & playing[:, None, :] & self._not_self

    def regrowth_rate(self, dirt: torch.Tensor) -> torch.Tensor:
        """[W] probability per step that a missing apple regrows, given the dirty cells [W, D]: the full
        apple_regrowth in a clean river, falling linearly to 0 at dirt_threshold, 0 beyond."""
        fraction = dirt.to(torch.float32).mean(-1)
        return self.params.apple_regrowth * (1 - fraction / self.params.dirt_threshold).clamp(0, 1)

    def rules(self, before, moved, actions, alive, generator):
        W, N, g = self.num_worlds, self.num_agents, generator
        playing = alive & (before.timeout == 0)  # [W, N]
        yaw = torch.where(playing, moved.yaw, before.yaw)
        pos = moved.pos[:, :N]
        # Eating: the closest agent in play touching a present apple takes it.
        dist = torch.cdist(pos, self.apples.expand(W, -1, -1))  # [W, N, M]
        touching = (dist < REACH) & before.present[:, None, :] & playing[:, :, None]
        taken = touching.any(1)
        taker = torch.where(touching, dist, torch.full_like(dist, math.inf)).argmin(1)  # [W, M]
        got = ((taker[:, None, :] == self._agent_index[None, :, None]) & taken[:, None, :]).sum(-1)  # [W, N]
        present = before.present & ~taken
        # Cleaning: every beam removes the dirt it covers; then new dirt settles on clean cells.
        zap_on, clean_on = ((actions[..., 2] > 0.5, actions[..., 3] > 0.5) if self.continuous
                            else (actions == ZAP, actions == CLEAN))
        beams = self.in_beam(pos, yaw) & (clean_on & playing)[:, :, None] & before.dirt[:, None, :]  # [W, N, D]
        swept = beams.any(1)
        dirt = (before.dirt & ~swept) | (torch.rand(before.dirt.shape, generator=g).to(self.device)
                                         < self.params.dirt_rate)
        # Regrowth, slower the dirtier the river.
        regrow = torch.rand(present.shape, generator=g).to(self.device) < self.regrowth_rate(dirt)[:, None]
        present = present | regrow
        # Tagging: each zapper hits the nearest agent in play within range and the cone.
        seen = self.zap_targets(pos, yaw, playing) & (zap_on & playing)[:, :, None]
        gap = torch.linalg.vector_norm(pos[:, None] - pos[:, :, None], dim=-1)
        hit = torch.where(seen, gap, torch.full_like(gap, math.inf)).argmin(-1)  # [W, zapper]
        tagged = (torch.nn.functional.one_hot(hit, N).bool() & seen.any(-1, keepdim=True)).any(1)  # [W, N]
        # Timeouts count down; agents whose timeout ends come back at a random point mid-arena.
        timeout = (before.timeout - 1).clamp_min(0)
        back = before.timeout == 1
        point = self.respawn_points[torch.randint(len(RESPAWN_POINTS), (W, N), generator=g).to(self.device)]
        pos = torch.where(back[..., None], point, pos)
        timeout = torch.where(tagged, self.params.tag_timeout, timeout)
        steps = before.steps + 1
        state = dataclasses.replace(moved, pos=pos, yaw=yaw, vel=moved.vel * (timeout == 0)[..., None], dirt=dirt,
                                    present=present, timeout=timeout, shown=timeout == 0,
                                    eaten=before.eaten + got, cleaned=before.cleaned + beams.sum(-1), steps=steps)
        info = {"eaten": taken.sum(-1), "cleaned": swept.sum(-1), "dirt_fraction": dirt.to(torch.float32).mean(-1),
                "apples_left": present.sum(-1), "tags": tagged.sum(-1)}
        return state, got.to(torch.float32), torch.zeros_like(alive), info

    def tagged_out(self, state) -> torch.Tensor:
        """[W, A] bool: the agents zapped out of the game at `state` (the social outcome metrics' peace)."""
        return state.timeout > 0

    def action_mask(self, state, alive):
        mask = (alive & (state.timeout == 0))[:, :, None].expand(-1, -1, self.num_actions).clone()
        mask[..., NOOP] = True  # noop is always valid
        return mask

    def observation(self, state, alive):
        W, N = self.num_worlds, self.num_agents
        dtype = state.pos.dtype
        dirty = state.dirt[:, None, :, None].to(dtype)  # [W, 1, D, 1]
        cells = (self.relative(state, self.dirt_cells.expand(W, -1, -1)) * dirty).reshape(W, N, -1)
        present = state.present[:, None, :, None].to(dtype)
        apples = (self.relative(state, self.apples.expand(W, -1, -1)) * present).reshape(W, N, -1)
        in_play = state.shown[:, self.others].to(dtype)  # [W, N, N-1]
        others = (self.others_obs(state) * in_play[..., None]).reshape(W, N, -1)
        timeout = state.timeout[..., None].to(dtype) / self.params.tag_timeout
        return torch.cat((self.own_obs(state), timeout, cells, dirty[..., 0].expand(W, N, -1), apples,
                          present[..., 0].expand(W, N, -1), others, in_play), -1)

    # ------------------------------------------------------------------ scripted play
    def scripted(self, state, cleaners: torch.Tensor, zap: bool = False) -> torch.Tensor:
        """Actions of scripted agents: `cleaners` [W, A] bool drive to the nearest dirty cell and clean it
        (waiting on the bank while the river is clean); the others drive to the nearest apple (waiting in
        the orchard while none is left) and, with `zap`, zap whoever is in their cone. Tagged agents noop."""
        W, N = self.num_worlds, self.num_agents
        pos, yaw = state.pos[:, :N], state.yaw
        cell_dist = torch.where(state.dirt[:, None, :], torch.cdist(pos, self.dirt_cells.expand(W, -1, -1)), math.inf)
        bank = torch.stack((pos[..., 0], torch.full_like(pos[..., 0], BANK_Y)), -1)
        river_clean = torch.isinf(cell_dist.amin(-1))[..., None]
        cell = torch.where(river_clean, bank, self.dirt_cells[cell_dist.argmin(-1)])
        apple_dist = torch.where(state.present[:, None, :], torch.cdist(pos, self.apples.expand(W, -1, -1)), math.inf)
        no_apple = torch.isinf(apple_dist.amin(-1))[..., None]
        wait = torch.tensor(ORCHARD_WAIT, device=self.device)
        apple = torch.where(no_apple, wait, self.apples[apple_dist.argmin(-1)])
        target = torch.where(cleaners[..., None], cell, apple)
        action = steer(pos, yaw, target, reach=0.3)
        # A cleaner close to its cell turns to face it rather than driving over it.
        delta = target - pos
        error = wrap_angle(torch.atan2(-delta[..., 0], delta[..., 1]) - yaw)
        close = cleaners & ~river_clean[..., 0] & (torch.linalg.vector_norm(delta, dim=-1) <= 0.6)
        action = torch.where(close, torch.where(error > 0, 2, 3), action)
        action = torch.where(cleaners & (self.in_beam(pos, yaw) & state.dirt[:, None, :]).any(-1), CLEAN, action)
        if zap:
            playing = state.timeout == 0
            action = torch.where(~cleaners & self.zap_targets(pos, yaw, playing).any(-1), ZAP, action)
        action = torch.where(state.timeout > 0, NOOP, action)
        return self.as_actions(action)

    def as_actions(self, action: torch.Tensor) -> torch.Tensor:
        """The env's actions of discrete ones [W, A]: as they are, or continuous (thrust, turn, zap, clean)."""
        if not self.continuous:
            return action
        return torch.cat((self.action_table[action], (action == ZAP)[..., None].float(),
                          (action == CLEAN)[..., None].float()), -1)

    def heuristic(self, state, alive):
        """Two agents in seven (at least one) clean the river, the others eat the nearest apple; nobody
        zaps. Over 16 worlds of 300 steps (seed 0) the seven eat 116 apples per world, random play 1.3;
        with one cleaner 132, with none 22: the river silts up and the orchard stops."""
        cleaners = self._agent_index < max(1, round(CLEANER_SHARE * self.num_agents))
        return self.scripted(state, cleaners.expand(self.num_worlds, -1))


def steer(pos: torch.Tensor, yaw: torch.Tensor, target: torch.Tensor, reach: float) -> torch.Tensor:
    """Discrete int64 [W, A]: turn until facing target [W, A, 2] within 0.3 rad, then forward; noop within
    `reach` (ArenaScenario.steer_to's discrete rule, for tasks that mix steering with their own actions)."""
    delta = target - pos
    error = wrap_angle(torch.atan2(-delta[..., 0], delta[..., 1]) - yaw)
    action = torch.where(error.abs() < 0.3, 1, torch.where(error > 0, 2, 3))
    return torch.where(torch.linalg.vector_norm(delta, dim=-1) <= reach, NOOP, action).to(torch.int64)
