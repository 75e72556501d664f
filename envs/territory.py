"""Territory (after Melting Pot's territory__rooms): agents claim floor cells with a painting beam, are
paid for what they hold, and may zap each other out of the episode; seen through egocentric cameras.

* Arena: the rooms of ``rooms`` (|x|, |y| <= 3 m, a 3 x 3 grid of 2 m rooms with a door in every
  wall slot; a slot is open, without wall, with probability ``open_wall``, default 0.2), its floor
  cut into 12 x 12 cells of 0.5 m (4 x 4 per room; cell ``row * 12 + col``, row 0 at -y).
* Agents: 9 by default (2 to 9), one per room at the start (distinct rooms, drawn), random headings;
  each agent has its own colour (scenery.palette), and paints in it.
* Actions, egocentric, as in ``spread`` plus two: discrete 7: 0 noop, 1 forward, 2 turn left,
  3 turn right, 4 backward, 5 paint, 6 zap; continuous 4: (thrust, turn rate, paint, zap), a beam
  fires when its value is > 0.5.
* Paint: the cell under the point 0.45 m ahead of the agent's centre (before the step), when no wall
  stands between, becomes the agent's, whoever held it (claims can be overpainted). Several agents
  painting one cell in a step: the lowest-indexed one gets it.
* Zap: hits the nearest other agent in play within ``zap_range`` (default 2 m) whose centre lies
  within 30 degrees of the zapper's heading, in its line of sight (not through walls). An agent hit
  twice in the episode (by one zapper twice, or by two in one step) is removed: its episode ends
  (terminated), it is no longer drawn nor collides, and its cells stay painted but pay nobody. An
  agent hit once carries a dark mark over its head. A zap fires only when the zapper's cooldown is
  over: ``zap_cooldown`` (default 5) steps after its last zap (the action mask says so).
* Reward, per agent in play: ``claim_reward`` (default 0.01) per cell it holds after the step.
* Episode: ends for an agent when it is removed; truncated after ``max_steps`` = 300.
* State obs (320 + 4 (N - 1)): own position, velocity, cos/sin yaw (6), own hits / 2 (1), own zap
  cooldown / ``zap_cooldown`` (1); per cell
  (144 x 2) whether it is the agent's and whether another's; the walls (12 flags of closed slots,
  12 door offsets); the other agents' relative positions times their in-play flag (2 each), the
  flags (1 each) and their hits / 2 (1 each). World frame.
* info (each [W]): ``"painted"`` cells that changed owner in the step, ``"claimed"`` cells held by
  anyone after it, ``"zaps"`` hits landed in it, ``"removed"`` agents removed so far this episode.
"""
from __future__ import annotations

import dataclasses
import math

import torch

from marl_render.util.validation import COUNT_LIMIT, finite_float, positive_float, positive_int, reward_weight

from . import egomotion, scenery
from .arena import ArenaScenario, ArenaState, Prop, numbered
from .rooms import ARENA, DOOR_RANGE, GRID, TABLES, WALL_COLOR, WALL_HEIGHT, Rooms, outer_walls, room_floors, room_of
from .roster import Bot, Card, HeldOut

CELLS_PER_SIDE = 12
CELL = 2 * ARENA / CELLS_PER_SIDE
C = CELLS_PER_SIDE ** 2
AGENT_RADIUS = 0.15
PAINT_REACH = 0.45  # the painted cell is the one under the point this far ahead of the agent's centre
ZAP_HALF_ANGLE = math.radians(30.0)
PAINT, ZAP = 5, 6  # the discrete actions
MARK_COLOR = (0.08, 0.08, 0.08)


def cell_centres() -> torch.Tensor:
    """[C, 2] the cells' centres (row 0 at -y, column 0 at -x)."""
    index = torch.arange(C)
    return torch.stack(((index % CELLS_PER_SIDE + 0.5) * CELL - ARENA, (index // CELLS_PER_SIDE + 0.5) * CELL - ARENA),
                       -1)


def cell_of(point: torch.Tensor) -> torch.Tensor:
    """int64 [...]: the cell under each point [..., 2], -1 outside the floor."""
    col, row = ((point + ARENA) / CELL).floor().long().unbind(-1)
    inside = (col >= 0) & (col < CELLS_PER_SIDE) & (row >= 0) & (row < CELLS_PER_SIDE)
    return torch.where(inside, row * CELLS_PER_SIDE + col, -1)


# ---------------------------------------------------------------- test bots: env -> actions [W, A]
def painter(env) -> torch.Tensor:
    """paints (its room first, then anywhere), never zaps"""
    return env.scenario.play(env.sim, env.alive, zaps="never")


def zapper(env) -> torch.Tensor:
    """chases the nearest agent in play and zaps it whenever it can; paints only the cells it passes"""
    s, state, alive = env.scenario, env.sim, env.alive
    N = env.num_agents
    pos = state.pos[:, :N]
    gap = torch.where(state.shown[:, None, :] & ~torch.eye(N, dtype=torch.bool, device=env.device),
                      torch.cdist(pos, pos), math.inf)
    chase = s.steer_to(state, pos.gather(1, gap.argmin(-1)[..., None].expand(-1, -1, 2)))
    _, can_zap = s.zap_target(state)
    can_zap = can_zap & (state.cooldown == 0)
    ahead = s.painted_cell(state)
    mine = (ahead >= 0) & (state.owner.gather(1, ahead.clamp_min(0)) == s.index)
    action = torch.where(can_zap, ZAP, torch.where((ahead >= 0) & ~mine, PAINT, chase))
    return torch.where(alive & state.shown, action, 0)


def defender(env) -> torch.Tensor:
    """paints its own room only and zaps every agent it can reach in that room"""
    return env.scenario.play(env.sim, env.alive, zaps="room", room_only=True)


@dataclasses.dataclass(frozen=True)
class TerritoryParams:
    claim_reward: float = 0.01  # per held cell and step
    open_wall: float = 0.2  # probability that a wall slot has no wall (as in rooms)
    zap_range: float = 2.0  # m
    zap_cooldown: int = 5  # steps after a zap before the agent can zap again

    def __post_init__(self):
        reward_weight("claim_reward", self.claim_reward)
        if not 0.0 <= finite_float("open_wall", self.open_wall) <= 1.0:
            raise ValueError(f"open_wall must be a probability in [0, 1], got {self.open_wall}")
        if positive_float("zap_range", self.zap_range) > 2 * ARENA * math.sqrt(2):
            raise ValueError(f"zap_range must be in (0, {2 * ARENA * math.sqrt(2):.2f}] m (the arena's diagonal), "
                             f"got {self.zap_range}")
        positive_int("zap_cooldown", self.zap_cooldown, maximum=COUNT_LIMIT)


@dataclasses.dataclass(frozen=True)
class TerritoryState(ArenaState):
    door: torch.Tensor  # [W, 12] door centre of each wall slot, along it from its middle (m), as rooms'
    wall_open: torch.Tensor  # [W, 12] bool: the slot has no wall
    owner: torch.Tensor  # [W, C] int64: the agent holding each cell, -1 none
    hits: torch.Tensor  # [W, A] int64: times each agent was zapped this episode (2: removed)
    cooldown: torch.Tensor  # [W, A] int64: steps before each agent's zap fires again (0: ready)
    shown: torch.Tensor  # [W, A] bool: agents in play (drawn)


class Territory(ArenaScenario):
    """Claim floor cells with a painting beam, defend them with a zap; see the module docstring."""

    name = "territory"
    Params = TerritoryParams
    # Zaps of short or long reach: holding ground is easier or harder.
    difficulties = {"easy": {"zap_range": 1.0}, "medium": {}, "hard": {"zap_range": 3.0}}
    State = TerritoryState
    default_num_agents = 9
    agent_range = (2, 9)
    default_max_steps = 300
    default_resolution = 64
    physics_terms = frozenset({"walls", "obstacles", "body_collisions", "drag"})
    info_keys = {"painted": torch.int64, "claimed": torch.int64, "zaps": torch.int64, "removed": torch.int64}
    arena_half_extent = (ARENA, ARENA)
    overview_resolution = (160, 160)
    shown = "shown"
    mixed_motive = True
    # Step budgets (env steps summed over worlds): 45 and 90 updates of 32 worlds x 32 decisions, what three seeds
    # of every new task fit in one 3-hour session on 2 cores (territory's env is the suite's slowest). The estimate
    # for learning was commons' (90 and 394 updates): these are short runs.
    training = {"budget": {"pixels": 46_080, "state": 92_160}}
    # The rooms' walls and their physics, as rooms draws and builds them from the same state fields.
    walls = Rooms.walls
    doors = Rooms.doors
    obstacles = Rooms.obstacles

    def setup(self):
        N, d = self.num_agents, self.device
        self.setup_arena({"agents": numbered("agent", N)}, state_dim=320 + 4 * (N - 1), radius=AGENT_RADIUS,
                         max_speed=2.0, extra_actions=("paint", "zap"))
        self.tables = {k: torch.tensor(v, device=d) for k, v in TABLES.items()}
        self.centres = cell_centres().to(d)
        self.cell_room = room_of(self.centres)  # [C]
        self.colors = scenery.palette(N)  # each agent its own colour, its paint a lighter one
        self._agent_color = self.colors.expand(self.num_worlds, N, 3)  # the arena draws agents in these
        self.paint_colors = 0.75 * self.colors + 0.25
        self.index = torch.arange(N, device=d)

    # ------------------------------------------------------------------ state
    def _fresh(self, pos, yaw, door, wall_open):
        W, N = self.num_worlds, self.num_agents
        return self.at_rest(pos, yaw, door=door, wall_open=wall_open, owner=torch.full((W, C), -1, dtype=torch.int64),
                            hits=torch.zeros(W, N, dtype=torch.int64), cooldown=torch.zeros(W, N, dtype=torch.int64),
                            shown=torch.ones(W, N, dtype=torch.bool))

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self._fresh(self.centres[:N].expand(W, N, 2).clone(), torch.zeros(W, N), torch.zeros(W, 12),
                           torch.zeros(W, 12, dtype=torch.bool))

    def state_bounds(self):
        return {**super().state_bounds(), "door": (-DOOR_RANGE, DOOR_RANGE), "owner": (-1, self.num_agents - 1),
                "hits": (0, 2), "cooldown": (0, self.params.zap_cooldown)}

    def check_state(self, state):
        if not torch.equal(state["shown"], state["hits"] < 2):
            raise ValueError("state['shown'] must be True exactly for the agents in play (state['hits'] < 2)")

    def spawn_level(self, draws):
        W, N = self.num_worlds, self.num_agents
        door = (draws.rand("doors", (W, 12)) * 2 - 1) * DOOR_RANGE
        wall_open = draws.rand("open_walls", (W, 12)) < self.params.open_wall
        pos = scenery.cell_spawn(draws, W, torch.full((N,), AGENT_RADIUS + 0.15), GRID, ARENA)  # one per room
        yaw = (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi
        return self._fresh(pos, yaw, door, wall_open)

    # ------------------------------------------------------------------ rules
    def beams(self, state, actions) -> tuple:
        """(paint [W, A], zap [W, A]) bool: the beams each agent fires."""
        if self.continuous:
            return actions[..., 2] > 0.5, actions[..., 3] > 0.5
        return actions == PAINT, actions == ZAP

    def painted_cell(self, state) -> torch.Tensor:
        """[W, A] int64: the cell each agent's paint beam reaches (-1: none, off the floor or behind a wall)."""
        N = self.num_agents
        point = state.pos[:, :N] + PAINT_REACH * scenery.heading(state.yaw)
        clear = self.sees(state, point, fov=math.pi).diagonal(dim1=1, dim2=2)  # no wall between
        return torch.where(clear, cell_of(point), -1)

    def zap_target(self, state) -> tuple:
        """(target [W, A] int64, hit [W, A] bool): the agent each agent's zap would hit, if any."""
        N = self.num_agents
        seen = self.sees(state, "agents", fov=2 * ZAP_HALF_ANGLE, reach=self.params.zap_range)  # [W, A, A]
        gap = torch.cdist(state.pos[:, :N], state.pos[:, :N])
        target = torch.where(seen, gap, math.inf).argmin(-1)
        return target, seen.any(-1)

    def rules(self, before, moved, actions, alive, generator):
        W, N = self.num_worlds, self.num_agents
        playing = alive & before.shown
        paint, zap = self.beams(before, actions)
        # Paint: each reached cell goes to the lowest-indexed painter (index C: no cell).
        cell = torch.where(paint & playing, self.painted_cell(before), -1)
        painter = torch.full((W, C + 1), N, dtype=torch.int64, device=self.device).scatter_reduce(
            1, torch.where(cell >= 0, cell, C), self.index.expand(W, N), "amin")[:, :C]
        owner = torch.where(painter < N, painter, before.owner)
        # Zap: each zapper in play hits its target; two hits in an episode remove an agent.
        target, hit = self.zap_target(before)
        fired = zap & playing & (before.cooldown == 0)
        hit = hit & fired
        cooldown = torch.where(fired, self.params.zap_cooldown, (before.cooldown - 1).clamp_min(0))
        landed = torch.zeros(W, N + 1, dtype=torch.int64, device=self.device).scatter_add(
            1, torch.where(hit, target, N), torch.ones_like(target))[:, :N]
        hits = (before.hits + landed).clamp_max(2)
        removed_now = (hits >= 2) & before.shown
        shown = before.shown & ~removed_now
        held = self.holdings(owner)
        reward = self.params.claim_reward * held.to(torch.float32) * shown
        state = dataclasses.replace(moved, owner=owner, hits=hits, cooldown=cooldown, shown=shown,
                                    vel=moved.vel * shown[..., None], active=moved.active & shown)
        info = {"painted": (owner != before.owner).sum(-1), "claimed": (owner >= 0).sum(-1),
                "zaps": landed.sum(-1), "removed": (~shown).sum(-1)}
        return state, reward, removed_now, info

    def holdings(self, owner: torch.Tensor) -> torch.Tensor:
        """[W, A] int64: the cells each agent holds."""
        W, N = owner.shape[0], self.num_agents
        return torch.zeros(W, N + 1, dtype=torch.int64, device=owner.device).scatter_add(
            1, torch.where(owner >= 0, owner, N), torch.ones_like(owner))[:, :N]

    def tagged_out(self, state) -> torch.Tensor:
        """[W, A] bool: agents removed from the episode (zapped twice) at this state."""
        return ~state.shown

    def action_mask(self, state, alive):
        mask = (alive & state.shown)[:, :, None].expand(-1, -1, self.num_actions).clone()
        mask[..., ZAP] &= state.cooldown == 0
        mask[..., 0] = True  # noop is always valid
        return mask

    # ------------------------------------------------------------------ what is drawn
    def props(self):
        return [room_floors(), outer_walls(),
                Prop("walls", "box", count=24, position=lambda s: self.walls(s)[0], height=WALL_HEIGHT / 2,
                     scale=lambda s: self.walls(s)[1], active=lambda s: self.walls(s)[2], color=WALL_COLOR,
                     moves=False, role="wall"),
                Prop("paint", "plane", count=C, position=lambda s: self.centres.expand(s.owner.shape[0], C, 2),
                     height=0.004, active=lambda s: s.owner >= 0, scale=(0.96 * CELL, 0.96 * CELL, 1.0),
                     color=lambda s: self.paint_colors[s.owner.clamp_min(0).cpu()]),
                Prop("marks", "sphere", count=self.num_agents, position=lambda s: s.pos[:, :self.num_agents],
                     height=0.62, active=lambda s: (s.hits == 1) & s.shown, scale=(0.14,) * 3, color=MARK_COLOR)]

    # ------------------------------------------------------------------ observation
    def observation(self, state, alive):
        W, N, f = self.num_worlds, self.num_agents, state.pos.dtype
        mine = state.owner[:, None, :] == self.index[None, :, None]  # [W, N, C]
        theirs = (state.owner[:, None, :] >= 0) & ~mine
        walls = torch.cat(((~state.wall_open).to(f), state.door), -1)[:, None].expand(W, N, -1)
        in_play = state.shown[:, self.others].to(f)  # [W, N, N-1]
        others = (self.others_obs(state) * in_play[..., None]).reshape(W, N, -1)
        hits = state.hits.to(f) / 2
        cooldown = state.cooldown.to(f)[..., None] / self.params.zap_cooldown
        return torch.cat((self.own_obs(state), hits[..., None], cooldown, mine.to(f), theirs.to(f), walls, others,
                          in_play, hits[:, self.others]), -1)

    # ------------------------------------------------------------------ scripted players
    def heuristic(self, state, alive):
        """A painter that defends: it zaps an agent in its zap's reach standing on one of its cells; else it
        paints the cell ahead when that is not its own; else it drives to the nearest cell of its room that
        is not its own (any such cell once its room is all its own). Removed agents noop."""
        return self.play(state, alive, zaps="intruders")

    def play(self, state, alive, zaps: str = "intruders", room_only: bool = False) -> torch.Tensor:
        """Actions of the scripted players: zaps "never", at "intruders" (agents on its cells) or at "room"
        (any agent in its room); room_only: it never leaves its room."""
        W, N = self.num_worlds, self.num_agents
        pos = state.pos[:, :N]
        mine = state.owner[:, None, :] == self.index[None, :, None]  # [W, N, C]
        ahead = self.painted_cell(state)
        ahead_mine = (ahead >= 0) & mine.gather(2, ahead.clamp_min(0)[..., None])[..., 0]
        paint = (ahead >= 0) & ~ahead_mine
        dist = torch.cdist(pos, self.centres.expand(W, C, 2))  # [W, N, C]
        room = room_of(pos)
        same_room = self.cell_room[None, None, :] == room[..., None]
        candidate = ~mine & (dist > 0.35)
        in_room = candidate & same_room
        pick = in_room if room_only else torch.where(in_room.any(-1, keepdim=True), in_room, candidate)
        score = torch.where(pick, dist, math.inf)
        target = torch.where(torch.isinf(score.amin(-1))[..., None], pos, self.centres[score.argmin(-1)])
        move = self.steer_to(state, target)
        target_agent, can_zap = self.zap_target(state)
        can_zap = can_zap & (state.cooldown == 0)
        if zaps == "never":
            zap = torch.zeros_like(can_zap)
        elif zaps == "room":
            zap = can_zap & (room.gather(1, target_agent) == room)
        else:
            under = cell_of(pos).gather(1, target_agent)  # the cell the target stands on
            zap = can_zap & (under >= 0) & mine.gather(2, under.clamp_min(0)[..., None])[..., 0]
        playing = alive & state.shown
        if self.continuous:
            beams = torch.stack((paint & ~zap, zap), -1).float()
            move = torch.where((paint | zap)[..., None], 0.0, move)
            return torch.cat((move, beams), -1) * playing[..., None]
        action = torch.where(zap, ZAP, torch.where(paint, PAINT, move))
        return torch.where(playing, action, 0)

    card = Card(
        text="Territory after Melting Pot's territory__rooms: agents claim floor cells with a painting beam and "
             "are paid a little each step for every cell they hold; claims can be overpainted, and an agent "
             "zapped twice is out for the rest of the episode. A mixed-motive task: painting pays each agent, "
             "zapping removes a rival's income and its own risk.",
        reward="per agent in play: claim_reward (0.01) per floor cell it holds after the step",
        episode_end="an agent terminates when zapped twice (removed); truncated at the episode's end (random by "
                    "default: mixed motive)",
        continuous=egomotion.CONTINUOUS_MEANINGS + (
            "paint (> 0.5: claim the cell 0.45 m ahead)",
            "zap (> 0.5: hit the nearest agent in play within zap_range and 30 degrees ahead, in sight)"),
        info={"painted": "cells that changed owner in this step",
              "claimed": "cells held by anyone after the step",
              "zaps": "hits landed in this step",
              "removed": "agents removed (zapped twice) so far this episode"})
    bots = {"painter": Bot(painter.__doc__, script=painter), "zapper": Bot(zapper.__doc__, script=zapper),
            "defender": Bot(defender.__doc__, script=defender), "noisy0.2": Bot.noisy(0.2, population="train")}
    heldout = (
        HeldOut("visitor_among_zappers", "one focal agent among aggressive zappers and pure painters", num_agents=9,
                focal=("agent_0",), bots_by_role={"agents": ("zapper", "painter")}),
        HeldOut("visitor_among_defenders", "one focal agent among defenders that zap anyone in their room",
                num_agents=9, focal=("agent_0",), bots_by_role={"agents": ("defender",)}),
        HeldOut("residents_with_zappers", "five focal agents with four aggressive zappers", num_agents=9,
                focal=tuple(f"agent_{i}" for i in range(5)), bots_by_role={"agents": ("zapper",)}),
        HeldOut("residents_with_painters", "five focal agents with four pure painters", num_agents=9,
                focal=tuple(f"agent_{i}" for i in range(5)), bots_by_role={"agents": ("painter",)}),
    )
