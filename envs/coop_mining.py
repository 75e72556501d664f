"""Cooperative mining: a stag hunt in space. Iron pays whoever mines it; gold pays only pairs.

N agents (default 6) mine ore lying about the arena. Iron pays +1 to the agent that mines it,
alone. Gold pays ``gold_reward`` (default 4) to each of exactly two agents that mine it within
``gold_window`` steps of each other, and nothing to one alone: an agent that waits at a gold ore
for a partner earns nothing while it waits, one that mines iron earns a little for sure. After
Melting Pot's coop_mining, on the arena of envs/arena.py, written on the public task API
(docs/authoring.md).

* Arena: |x|, |y| <= 2 m. Ore: 14 sites, 8 iron (rust-red rocks) then 6 gold (yellow rocks, a
  paler yellow while some agent's strike on it is pending); not physics bodies (agents drive over
  them). Sites and agents start in distinct random cells of a 6 x 6 grid of the arena.
* Agents: capsules of radius 0.15 m, physics walls + body_collisions + drag, as in ``forage``.
* Mining: the extra action "mine" (discrete 5; continuous: the third value > 0.5) strikes the
  nearest present ore whose centre is within 0.45 m of the agent's and 45 degrees of its heading.
  - Iron struck in a step goes to the closest striker (lowest index on a tie): +1 to it.
  - A strike on gold stays pending for ``gold_window`` steps (default 3), its own included: strikes
    at steps t and t' pair when |t - t'| < gold_window; striking again renews one's own. When
    exactly two agents' strikes are pending on a gold ore, it is mined: ``gold_reward`` to each.
    Three or more pending at once (a third joined in the same step) crumble it: nobody is paid.
  - A mined (or crumbled) ore comes back at its site ``respawn_delay`` steps later (default 20).
* Actions: discrete 6: 0 noop, 1 forward, 2 turn left, 3 turn right, 4 backward, 5 mine;
  continuous 3: (thrust, turn rate, mine). Every action is always valid.
* Episode: never terminates; truncated after ``max_steps`` = 300. Nobody is ever tagged out.
* State obs (6 + 6 S + 2 (N - 1), S = 14): own position, velocity, cos/sin yaw; the sites relative
  to the agent times their present flag, the present flags, gold flags, whether the agent's own
  strike is pending there and whether anyone's is; the other agents relative to it. World frame.
* info (each [W]): ``"iron"`` int64 iron ores mined in the step, ``"gold"`` int64 gold ores
  mined by a pair, ``"gold_lost"`` int64 gold ores crumbled by three or more, ``"ores_left"``
  int64 ores present after the step.
"""
from __future__ import annotations

import dataclasses
import math

import torch

import marl_render as mr
from marl_render.envs import ArenaScenario, ArenaState, Prop, egomotion, numbered
from marl_render.envs.roster import Bot, Card, HeldOut
from marl_render.envs.scenario import MAX_COUNT
from marl_render.envs.scenery import cell_spawn, wrap_angle
from marl_render.util.validation import COUNT_LIMIT, positive_int, reward_weight

ARENA = 2.0  # half extent (m)
SPAWN_GRID = 6
AGENT_RADIUS = 0.15
NUM_IRON, NUM_GOLD = 8, 6
ORE_SIZE = (0.24, 0.24, 0.16)
IRON_COLOR = (0.6, 0.25, 0.12)
GOLD_COLOR = (0.95, 0.75, 0.05)
STRUCK_GOLD_COLOR = (1.0, 0.95, 0.6)
MINE_REACH = 0.45  # centre to centre (m)
MINE_HALF_ANGLE = math.radians(45.0)
IRON_REWARD = 1.0
NOOP, MINE = 0, 5


@dataclasses.dataclass(frozen=True)
class CoopMiningParams:
    gold_reward: float = 4.0  # to each of the two agents that mine a gold ore together
    gold_window: int = 3  # steps a strike on gold stays pending, its own included
    respawn_delay: int = 20  # steps before a mined ore comes back

    def __post_init__(self):
        reward_weight("gold_reward", self.gold_reward)
        positive_int("gold_window", self.gold_window, maximum=COUNT_LIMIT)
        positive_int("respawn_delay", self.respawn_delay, maximum=COUNT_LIMIT)


@dataclasses.dataclass(frozen=True)
class CoopMiningState(ArenaState):
    ores: torch.Tensor  # [W, S, 2] site centres (m): iron first, then gold
    timer: torch.Tensor  # [W, S] int64: steps until the ore is back; 0: present
    pending: torch.Tensor  # [W, S, A] int64: steps each agent's strike on each gold ore stays pending; 0: none
    iron: torch.Tensor  # [W, A] int64: iron each agent mined this episode
    gold: torch.Tensor  # [W, A] int64: gold each agent mined (with a partner) this episode
    steps: torch.Tensor  # [W] int64: steps of the episode so far


# ---------------------------------------------------------------------- the test bots (roster.Bot scripts)
def iron_miner(env) -> torch.Tensor:
    """Every slot mines the nearest iron and never gold."""
    s, state = env.scenario, env.sim
    return s.mine_towards(state, s.nearest(state, ~s.is_gold))


def gold_seeker(env) -> torch.Tensor:
    """Every slot goes to the nearest gold and strikes it until a partner comes (holds still while no
    gold is present); never iron."""
    s, state = env.scenario, env.sim
    return s.mine_towards(state, s.nearest(state, s.is_gold))


CARD_TEXT = """\
**Cooperative mining** is a stag hunt in space, after Melting Pot's coop_mining. Rocks of ore lie
about the arena: rust-red iron and yellow gold. An agent mines the rock in front of it with the
`mine` action.

**Rewards.** Iron pays +1 to the agent that mines it, alone. Gold pays 4 to each of exactly two
agents that strike it within 3 steps of each other, and nothing to an agent alone; a third striker
joining in the same step crumbles it for everyone. A struck gold rock turns pale while the strike is
pending, so a partner can see where help is wanted. Mined rock comes back 20 steps later.

**Observations.** Pixels from each agent's own camera; the state observation gives the agent's pose,
every site relative to it with whether it is present, gold, struck by the agent itself or by anyone,
and the other agents.

**The dilemma.** Gold is the better deal for everyone (the stag), iron the safe one (the hare): an
agent that waits at a gold rock earns nothing until a partner comes, one that mines iron earns for
sure. A group that trusts pairs up for gold and earns more than one that does not. The heuristic
pairs agents 0-1, 2-3, ...: each pair goes to the gold nearest to it that no other pair is nearer to
and strikes it together, mining iron while no such gold is present.
"""


class CoopMining(ArenaScenario):
    """Mine iron alone or gold in pairs; see the module docstring."""

    name = "coop_mining"
    Params = CoopMiningParams
    # How closely two strikes on gold must follow each other, and how fast ore comes back.
    difficulties = {"easy": {"gold_window": 6, "respawn_delay": 10}, "medium": {},
                    "hard": {"gold_window": 2, "respawn_delay": 40}}
    State = CoopMiningState
    default_num_agents = 6
    agent_range = (2, 12)
    default_max_steps = 300
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"iron": torch.int64, "gold": torch.int64, "gold_lost": torch.int64, "ores_left": torch.int64}
    arena_half_extent = (ARENA, ARENA)
    mixed_motive = True
    card = Card(text=CARD_TEXT,
                reward="per agent: +1 per iron ore it mines alone; gold_reward (4) to each of exactly two agents "
                       "whose strikes on one gold ore fall within gold_window (3) steps, nothing to one alone, "
                       "nothing when three strike at once",
                episode_end="never terminates; truncated at the episode's end (random by default: mixed motive)",
                continuous=egomotion.CONTINUOUS_MEANINGS + (
                    "mine (> 0.5: strike the nearest present ore within 0.45 m and 45 degrees ahead)",),
                info={"iron": "iron ores mined in this step",
                      "gold": "gold ores mined by a pair in this step",
                      "gold_lost": "gold ores crumbled by three or more strikers in this step",
                      "ores_left": "ores present after the step"})
    # Step budgets (env steps summed over worlds): 130 and 260 updates of 32 worlds x 32 decisions, what three
    # seeds of every new task fit in one 3-hour session on 2 cores. The estimate for learning was forage's for as
    # many 300-step episodes, x 1.5 (263 and 1485 updates): these are short runs.
    training = {"budget": {"pixels": 133_120, "state": 266_240}}
    bots = {"iron_miner": Bot("mines the nearest iron, never gold", script=iron_miner),
            "gold_seeker": Bot("goes to the nearest gold and strikes it until a partner comes", script=gold_seeker),
            "lazy0.5": Bot.lazy(0.5),
            "noisy0.1": Bot.noisy(0.1, population="train")}
    heldout = (
        HeldOut("visitor_among_gold_seekers", "one focal agent among five that wait at gold for a partner",
                num_agents=6, focal=("agent_0",), bots_by_role={"agents": ("gold_seeker",)}),
        HeldOut("visitor_pair_among_iron_miners", "two focal agents among four that only mine iron: a partner for "
                "gold must be the other focal agent", num_agents=6, focal=tuple(numbered("agent", 2)),
                bots_by_role={"agents": ("iron_miner",)}),
        HeldOut("resident_with_gold_seekers", "four focal agents with two that wait at gold for a partner",
                num_agents=6, focal=tuple(numbered("agent", 4)), bots_by_role={"agents": ("gold_seeker",)}),
        HeldOut("resident_with_lazy", "four focal agents with two iron miners or idlers", num_agents=6,
                focal=tuple(numbered("agent", 4)), bots_by_role={"agents": ("iron_miner", "lazy0.5")}),
    )

    def setup(self):
        N = self.num_agents
        S = self.num_sites = NUM_IRON + NUM_GOLD
        self.setup_arena({"agents": numbered("agent", N)}, state_dim=6 + 6 * S + 2 * (N - 1), radius=AGENT_RADIUS,
                         max_speed=2.0, extra_actions=("mine",))
        self.is_gold = (torch.arange(S) >= NUM_IRON).to(self.device)  # [S]
        self._agent_index = torch.arange(N, device=self.device)
        self._colors = torch.tensor((IRON_COLOR, GOLD_COLOR, STRUCK_GOLD_COLOR), device=self.device)

    def _fresh(self, pos, yaw, ores):
        W, N, S = self.num_worlds, self.num_agents, self.num_sites
        return self.at_rest(pos, yaw, ores=ores, timer=torch.zeros(W, S, dtype=torch.int64),
                            pending=torch.zeros(W, S, N, dtype=torch.int64), iron=torch.zeros(W, N, dtype=torch.int64),
                            gold=torch.zeros(W, N, dtype=torch.int64),
                            steps=torch.zeros(W, dtype=torch.int64))

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self._fresh(torch.zeros(W, N, 2), torch.zeros(W, N), torch.zeros(W, self.num_sites, 2))

    def state_bounds(self):
        # Counters of the episode grow while a world keeps stepping without autoreset.
        return {**super().state_bounds(), "ores": self.inside_walls(), "timer": (0, self.params.respawn_delay),
                "pending": (0, self.params.gold_window), "iron": (0, MAX_COUNT), "gold": (0, MAX_COUNT),
                "steps": (0, MAX_COUNT)}

    def check_state(self, state):
        pending = state["pending"] > 0
        if bool(pending[:, :NUM_IRON].any()):
            raise ValueError(f"state['pending'] must be 0 on iron (sites 0 to {NUM_IRON - 1}): only gold waits for "
                             f"a partner")
        if bool((pending.sum(-1) >= 2).any()):
            raise ValueError("state['pending'] must hold at most one agent's pending strike per gold ore (two are "
                             "mined at once)")
        if bool((pending & (state["timer"] > 0)[..., None]).any()):
            raise ValueError("state['pending'] must be 0 on ore that is not present (state['timer'] > 0)")

    def spawn_level(self, draws):
        W, N, S = self.num_worlds, self.num_agents, self.num_sites
        places = cell_spawn(draws, W, torch.full((N + S,), AGENT_RADIUS + 0.05), SPAWN_GRID, ARENA)
        yaw = (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi
        return self._fresh(places[:, :N], yaw, places[:, N:])

    def props(self):
        return [Prop("ores", mr.sphere(segments=8, rings=4), count=self.num_sites, position="ores",
                     height=ORE_SIZE[2] / 2, active=lambda state: state.timer == 0, scale=ORE_SIZE,
                     color=self.ore_colors)]

    def ore_colors(self, state) -> torch.Tensor:
        """[W, S, 3]: iron, gold, or pale gold while a strike on it is pending."""
        kind = self.is_gold.long() + (state.pending > 0).any(-1).long()
        return self._colors[kind]

    # ------------------------------------------------------------------ rules
    def mine_target(self, state, pos: torch.Tensor, yaw: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """[W, A] int64: the ore each agent at pos [W, A, 2] facing yaw [W, A] would strike: the nearest of
        the `present` [W, S] sites of `state` within reach and the cone; -1: none."""
        delta = state.ores[:, None] - pos[:, :, None]  # [W, A, S, 2]
        gap = torch.linalg.vector_norm(delta, dim=-1)
        bearing = torch.atan2(-delta[..., 0], delta[..., 1])
        cone = (wrap_angle(bearing - yaw[..., None]).abs() <= MINE_HALF_ANGLE) & (gap <= MINE_REACH)
        gap = torch.where(cone & present[:, None], gap, math.inf)
        return torch.where(torch.isinf(gap.amin(-1)), -1, gap.argmin(-1))

    def rules(self, before, moved, actions, alive, generator):
        N, S = self.num_agents, self.num_sites
        pos, yaw = moved.pos[:, :N], moved.yaw
        present = before.timer == 0
        mining = (actions[..., 2] > 0.5 if self.continuous else actions == MINE) & alive
        target = self.mine_target(before, pos, yaw, present)
        strikes = (torch.nn.functional.one_hot(target.clamp_min(0), S).bool()
                   & (mining & (target >= 0))[..., None]).transpose(1, 2)  # [W, S, A]
        # Iron: the closest striker takes it.
        iron_struck = strikes & ~self.is_gold[:, None]
        iron_taken = iron_struck.any(-1)  # [W, S]
        gap = torch.linalg.vector_norm(before.ores[:, :, None] - pos[:, None], dim=-1)  # [W, S, A]
        taker = torch.where(iron_struck, gap, math.inf).argmin(-1)  # [W, S]
        got_iron = ((taker[:, :, None] == self._agent_index) & iron_taken[..., None]).sum(1)  # [W, A]
        # Gold: strikes stay pending for gold_window steps; exactly two pending mine it, three crumble it.
        pending = (before.pending - 1).clamp_min(0)
        pending = torch.where(strikes & self.is_gold[:, None], self.params.gold_window, pending)
        partners = (pending > 0).sum(-1)  # [W, S]
        paired, crumbled = partners == 2, partners >= 3
        got_gold = ((pending > 0) & paired[..., None]).sum(1)  # [W, A]
        done = paired | crumbled
        pending = torch.where(done[..., None], 0, pending)
        timer = torch.where(iron_taken | done, self.params.respawn_delay, (before.timer - 1).clamp_min(0))
        reward = IRON_REWARD * got_iron.to(torch.float32) + self.params.gold_reward * got_gold.to(torch.float32)
        state = dataclasses.replace(moved, timer=timer, pending=pending, iron=before.iron + got_iron,
                                    gold=before.gold + got_gold, steps=before.steps + 1)
        info = {"iron": iron_taken.sum(-1), "gold": paired.sum(-1), "gold_lost": crumbled.sum(-1),
                "ores_left": (timer == 0).sum(-1)}
        return state, reward, torch.zeros_like(alive), info

    def tagged_out(self, state) -> torch.Tensor:
        """[W, A] bool: agents out of the game at `state`: none, ever (there is no zap)."""
        return torch.zeros_like(state.iron, dtype=torch.bool)

    def observation(self, state, alive):
        W, N, S = self.num_worlds, self.num_agents, self.num_sites
        dtype = state.pos.dtype
        present = (state.timer == 0)[:, None, :].to(dtype).expand(W, N, S)
        sites = (self.relative(state, state.ores) * present[..., None]).reshape(W, N, -1)
        gold = self.is_gold.to(dtype).expand(W, N, S)
        own = (state.pending > 0).transpose(1, 2).to(dtype)  # [W, A, S]
        anyone = (state.pending > 0).any(-1)[:, None].to(dtype).expand(W, N, S)
        return torch.cat((self.own_obs(state), sites, present, gold, own, anyone,
                          self.others_obs(state).reshape(W, N, -1)), -1)

    # ------------------------------------------------------------------ scripted play
    def nearest(self, state, kind: torch.Tensor) -> torch.Tensor:
        """[W, A] int64: each agent's nearest present ore among the sites `kind` [S] bool; -1: none."""
        gap = torch.cdist(state.pos[:, :self.num_agents], state.ores)
        gap = torch.where(((state.timer == 0) & kind)[:, None], gap, math.inf)
        return torch.where(torch.isinf(gap.amin(-1)), -1, gap.argmin(-1))

    def mine_towards(self, state, target: torch.Tensor) -> torch.Tensor:
        """Actions that take each agent to its ore `target` [W, A] (-1: hold still) and strike it once it
        would be the one struck; close to it, the agent turns to face it rather than drive over it."""
        N = self.num_agents
        pos, yaw = state.pos[:, :N], state.yaw
        site = state.ores.gather(1, target.clamp_min(0)[..., None].expand(-1, -1, 2))  # [W, A, 2]
        site = torch.where((target >= 0)[..., None], site, pos)
        delta = site - pos
        error = wrap_angle(torch.atan2(-delta[..., 0], delta[..., 1]) - yaw)
        action = torch.where(error.abs() < 0.3, 1, torch.where(error > 0, 2, 3))
        action = torch.where(torch.linalg.vector_norm(delta, dim=-1) <= MINE_REACH - 0.05,
                             torch.where(error > 0, 2, 3), action)
        struck = self.mine_target(state, pos, yaw, state.timer == 0)
        action = torch.where((struck == target) & (target >= 0), MINE, action)
        action = torch.where(target >= 0, action, NOOP)
        if not self.continuous:
            return action
        return torch.cat((self.action_table[action], (action == MINE)[..., None].float()), -1)

    def heuristic(self, state, alive):
        """Agents pair up (0-1, 2-3, ...): each pair goes to the present gold nearest to its midpoint of
        those no other pair is nearer to, and both strike it; a pair without such gold, and an odd agent
        out, mine the nearest iron. Never three on one gold. Over 16 worlds of 300 steps (seed 0) the six
        earn 354 per world (42 gold ores), random play 9, iron miners alone 66, gold seekers alone 217."""
        W, N = self.num_worlds, self.num_agents
        P = N // 2
        pos = state.pos[:, :2 * P].reshape(W, P, 2, 2).mean(2)  # [W, P, 2] pair midpoints
        gap = torch.cdist(pos, state.ores)  # [W, P, S]
        gap = torch.where(((state.timer == 0) & self.is_gold)[:, None], gap, math.inf)
        nearest_pair = gap.argmin(1)  # [W, S]
        ours = nearest_pair[:, None] == torch.arange(P, device=self.device)[:, None]  # [W, P, S]
        gap = torch.where(ours, gap, math.inf)
        gold = torch.where(torch.isinf(gap.amin(-1)), -1, gap.argmin(-1))  # [W, P]
        gold = torch.cat((gold.repeat_interleave(2, 1), gold.new_full((W, N - 2 * P), -1)), 1)  # [W, A]
        target = torch.where(gold >= 0, gold, self.nearest(state, ~self.is_gold))
        return self.mine_towards(state, target)
