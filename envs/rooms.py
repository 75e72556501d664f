"""Rooms: find a goal hidden in a procedurally generated layout of rooms and doors.

A memory and exploration task (like Megaverse's): walls hide the goal (a camera sees it only
from its room or through a door; the state observation gives it only inside its room), so
agents must search the rooms, remember which they have seen, and (in the ``return_home``
variant) find their way back.

* Arena: |x|, |y| <= 3 m, divided into a 3 x 3 grid of 2 m square rooms (room index
  ``row * 3 + col``, row 0 at -y, col 0 at -x). Each floor of a room has its own faint tint.
* Layout, new in every world and every episode (drawn from the env's generator): each of the
  12 interior wall slots between two adjacent rooms is either a wall 0.8 m high and 0.1 m
  thick with one door gap 0.7 m wide centred at a uniformly random place along it (keeping at
  least 0.15 m of wall each side), or, with probability ``open_wall`` (default 0.2), absent.
  Every slot is passable, so every room is reachable. Slots 0-5 are the vertical walls
  between room (row, col) and (row, col + 1), index ``row * 2 + col``; slots 6-11 the
  horizontal walls between (row, col) and (row + 1, col), index ``6 + row * 3 + col``.
  A wall slot is two boxes (the pieces either side of its door), drawn as one instance
  group whose positions, sizes and shown flags differ between worlds, and given to the
  physics as the same boxes (``planar.Obstacles``; an absent slot's boxes are moved 1 km
  away, because a box of zero size would still block as a point).
* Agents: ``num_agents`` (1 to 4, default 2) blue capsules of radius 0.15 m, mass 1, physics
  from ``envs/planar.py`` with the terms walls + obstacles + body_collisions + drag (as in
  ``spread``). They start at rest in distinct quarters of a random home room (marked by a
  green disc at its centre), with random yaws. The camera sits at 0.4 m, below the walls'
  tops, so walls hide what lies behind them.
* Goal: a magenta pillar (radius 0.12 m, 0.6 m high) at a random place of a random room
  other than the home room, at least 0.35 m from the room's walls. It is not a body: an
  agent reaches it when their centres are closer than 0.27 m.
* Actions, egocentric, as in ``spread``: discrete 5: 0 noop, 1 forward, 2 turn left,
  3 turn right, 4 backward; continuous 2: (thrust in [-1, 1] along the heading, turn
  rate in [-1, 1]). Movement as in envs/egomotion.py (shared by the arena envs).
* Reward, shared by all agents: ``+found_reward`` (default 1) in the step where any agent
  first reaches the goal; with ``return_home=True`` another ``+found_reward`` in the step
  where an agent that has reached the goal is first back inside the home room;
  ``-step_penalty`` (default 0) every step; ``+explore_reward`` (default 0: off) per room that
  an agent enters for the first time in the episode (a denser signal for learners).
* Episode: terminates (every agent) when the goal is found, or with ``return_home=True``
  when an agent that reached it is back home; truncated after ``max_steps`` = 300.
* action_mask: every action is always valid (all True).
* State obs (46 + 2 (N - 1)), world frame: own position (2), velocity (2), cos/sin yaw (2);
  the rooms visited by any agent this episode (9, 0/1); each wall slot's presence (12, 0/1)
  and door centre along it (12, m from the slot's middle, towards +x or +y); whether the
  agent is in the goal's room (1) and then the goal's position relative to it (2, zeros
  otherwise: rooms are convex and their walls lie on their borders, so inside the goal's
  room nothing but another agent stands between the agent and the goal, and outside it
  the goal is never given away); whether the agent has reached the goal (1); whether any
  agent has (1); the home room's centre relative to the agent (2); the other agents'
  positions relative to it (2 each, in agent-index order skipping itself).
* info: ``"found"`` int64 [W] 1 once the goal has been reached this episode, ``"returned"``
  int64 [W] 1 once a finder is back home (always 0 without ``return_home``),
  ``"rooms_visited"`` int64 [W] distinct rooms any agent has been in this episode (its
  centre inside; the home room counts from the start).
"""
from __future__ import annotations

import dataclasses
import math

import torch

import marl_render as mr
from marl_render.util.validation import boolean, finite_float, reward_weight

from . import egomotion, planar, scenery
from .arena import ArenaScenario, ArenaState, Prop, Static, numbered, wander
from .roster import Bot, Card, HeldOut

ARENA = 3.0  # half extent (m)
GRID = 3  # rooms per side
ROOM = 2 * ARENA / GRID  # room side (m)
WALL_HEIGHT = 0.8
WALL_THICKNESS = 0.1
WALL_COLOR = (0.72, 0.68, 0.60)
DOOR_WIDTH = 0.7
DOOR_RANGE = ROOM / 2 - DOOR_WIDTH / 2 - 0.15  # door centres within +-DOOR_RANGE of the slot's middle
AGENT_RADIUS = 0.15
GOAL_RADIUS = 0.12
GOAL_HEIGHT = 0.6
GOAL_COLOR = (1.0, 0.1, 0.9)
GOAL_MARGIN = 0.35  # the goal keeps this far from its room's borders
REACH = AGENT_RADIUS + GOAL_RADIUS
HOME_RADIUS = 0.3
HOME_COLOR = (0.35, 0.85, 0.40)
FAR_AWAY = 1000.0  # where an absent wall's boxes go for the physics


def _layout_tables() -> dict:
    """Constant tables of the 3 x 3 grid (built once): room centres, wall slots, shortest hops."""
    centre = [[(col + 0.5) * ROOM - ARENA, (row + 0.5) * ROOM - ARENA] for row in range(GRID) for col in range(GRID)]
    slot_centre, along, between = [], [], {}
    for row in range(GRID):  # vertical walls between horizontal neighbours
        for col in range(GRID - 1):
            between[row * 3 + col, row * 3 + col + 1] = len(slot_centre)
            slot_centre.append([(col + 1) * ROOM - ARENA, (row + 0.5) * ROOM - ARENA])
            along.append([0.0, 1.0])
    for row in range(GRID - 1):  # horizontal walls between vertical neighbours
        for col in range(GRID):
            between[row * 3 + col, (row + 1) * 3 + col] = len(slot_centre)
            slot_centre.append([(col + 0.5) * ROOM - ARENA, (row + 1) * ROOM - ARENA])
            along.append([1.0, 0.0])
    rooms = range(GRID * GRID)

    def hop(a, b):
        """The next room on a shortest path from room a to room b (along the row first): every
        slot can be crossed, so the shortest paths are those of the grid."""
        (ra, ca), (rb, cb) = divmod(a, GRID), divmod(b, GRID)
        if ca != cb:
            return a + (1 if cb > ca else -1)
        return a + GRID * ((rb > ra) - (rb < ra))

    next_room = [[hop(a, b) for b in rooms] for a in rooms]
    slot = [[between.get((min(a, n), max(a, n)), 0) for n in row] for a, row in zip(rooms, next_room, strict=True)]
    steps = [[abs(a // GRID - b // GRID) + abs(a % GRID - b % GRID) for b in rooms] for a in rooms]
    return {"room_centre": centre, "slot_centre": slot_centre, "along": along, "next_room": next_room,
            "slot_to": slot, "steps": steps}


TABLES = _layout_tables()


@dataclasses.dataclass(frozen=True)
class RoomsParams:
    return_home: bool = False  # a finder must also come back to the home room
    open_wall: float = 0.2  # probability that a wall slot has no wall
    found_reward: float = 1.0  # when the goal is first reached (with return_home: again once home)
    step_penalty: float = 0.0  # subtracted every step
    explore_reward: float = 0.0  # per room first entered this episode (0: off)

    def __post_init__(self):
        boolean("return_home", self.return_home)
        if not 0.0 <= finite_float("open_wall", self.open_wall) <= 1.0:
            raise ValueError(f"open_wall must be a probability in [0, 1], got {self.open_wall}")
        reward_weight("found_reward", self.found_reward)
        reward_weight("step_penalty", self.step_penalty, allow_zero=True)
        reward_weight("explore_reward", self.explore_reward, allow_zero=True)


@dataclasses.dataclass(frozen=True)
class RoomsState(ArenaState):
    door: torch.Tensor  # [W, 12] door centre of each wall slot, along it from its middle (m)
    wall_open: torch.Tensor  # [W, 12] bool: the slot has no wall
    goal: torch.Tensor  # [W, 1, 2] goal centre (m)
    home: torch.Tensor  # [W] int64: the home room
    visited: torch.Tensor  # [W, 9] bool: rooms any agent has been in this episode
    finder: torch.Tensor  # [W, A] bool: agents that have reached the goal this episode
    returned: torch.Tensor  # [W] bool: a finder has been back home (return_home only)


class Rooms(ArenaScenario):
    """Find the goal in procedurally generated rooms; see the module docstring."""

    name = "rooms"
    Params = RoomsParams
    # Open wall slots make the goal easier to reach; "hard" has only the doors.
    difficulties = {"easy": {"open_wall": 0.6}, "medium": {}, "hard": {"open_wall": 0.0}}
    State = RoomsState
    default_num_agents = 2
    agent_range = (1, 4)
    default_max_steps = 300
    default_resolution = 64
    physics_terms = frozenset({"walls", "obstacles", "body_collisions", "drag"})
    info_keys = {"found": torch.int64, "returned": torch.int64, "rooms_visited": torch.int64}
    arena_half_extent = (ARENA, ARENA)
    overview_resolution = (160, 160)
    bots = {"noisy0.2": Bot.noisy(0.2, population="train"),
            "wanderer": Bot("drives round a circle, ignoring doors and the goal", script=wander),
            "lazy0.5": Bot.lazy(0.5), "noisy0.5": Bot.noisy(0.5)}
    heldout = (
        HeldOut("with_wanderer", "a focal explorer with a partner that wanders", 2, ("agent_0",),
                {"agents": ("wanderer",)}),
        HeldOut("with_lazy", "a focal explorer with a partner that idles half the time", 2, ("agent_0",),
                {"agents": ("lazy0.5",)}),
        HeldOut("with_noisy", "a focal explorer with a partner that acts at random half the time", 2, ("agent_0",),
                {"agents": ("noisy0.5",)}),
    )
    card = Card(reward="shared: +found_reward (1) when any agent first reaches the goal; with return_home another "
                       "+found_reward when an agent that reached it is first back in the home room; -step_penalty (0) "
                       "per step; optional +explore_reward per room first entered",
                episode_end="the goal found (with return_home: a finder back home) terminates every agent; truncated "
                            "at max_steps",
                continuous=egomotion.CONTINUOUS_MEANINGS,
                info={"found": "1 once an agent has reached the goal in this episode",
                      "returned": "1 once an agent that reached the goal is back in the home room (return_home; else "
                                  "always 0)",
                      "rooms_visited": "distinct rooms any agent has been in this episode (the home room included)"})
    training = {"budget": {"pixels": 880_640, "state": 794_624}}  # env steps of the published runs

    def setup(self):
        N = self.num_agents
        self.setup_arena({"agents": numbered("agent", N)}, state_dim=46 + 2 * (N - 1), radius=AGENT_RADIUS,
                         max_speed=2.0)
        self.tables = {k: torch.tensor(v, device=self.device) for k, v in TABLES.items()}
        # Each agent breaks ties between equally near unexplored rooms in its own order, so
        # agents starting together fan out: row-major, reversed, column-major, reversed.
        room = torch.arange(GRID * GRID, device=self.device)
        transposed = (room % GRID) * GRID + room // GRID
        self.preference = torch.stack((room, 8 - room, transposed, 8 - transposed))[:N]  # [N, 9]

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self.at_rest(torch.zeros(W, N, 2), torch.zeros(W, N), door=torch.zeros(W, 12),
                            wall_open=torch.zeros(W, 12, dtype=torch.bool), goal=torch.zeros(W, 1, 2),
                            home=torch.zeros(W, dtype=torch.int64), visited=torch.zeros(W, 9, dtype=torch.bool),
                            finder=torch.zeros(W, N, dtype=torch.bool), returned=torch.zeros(W, dtype=torch.bool))

    def props(self):
        return [room_floors(), outer_walls(),
                Prop("walls", "box", count=24, position=lambda s: self.walls(s)[0], height=WALL_HEIGHT / 2,
                     scale=lambda s: self.walls(s)[1], active=lambda s: self.walls(s)[2], color=WALL_COLOR,
                     moves=False, role="wall"),
                Prop("home", scenery.disc_mesh(), count=1, position=lambda s: self.room_centre(s.home)[:, None],
                     height=0.01, scale=(2 * HOME_RADIUS, 2 * HOME_RADIUS, 0.02), color=HOME_COLOR, moves=False),
                Prop("goal", mr.cylinder(segments=10), count=1, position="goal", height=GOAL_HEIGHT / 2,
                     scale=(2 * GOAL_RADIUS, 2 * GOAL_RADIUS, GOAL_HEIGHT), color=GOAL_COLOR, moves=False)]

    def state_bounds(self):
        return {**super().state_bounds(), "door": (-DOOR_RANGE, DOOR_RANGE), "goal": self.inside_walls(),
                "home": (0, GRID * GRID - 1)}

    def spawn_level(self, draws):
        W, N = self.num_worlds, self.num_agents
        home = draws.randint("home", GRID * GRID, (W,))
        goal_room = (home + 1 + draws.randint("goal_room", GRID * GRID - 1, (W,))) % (GRID * GRID)
        goal = (draws.rand("goal", (W, 1, 2)) * 2 - 1) * (ROOM / 2 - GOAL_MARGIN)
        door = (draws.rand("doors", (W, 12)) * 2 - 1) * DOOR_RANGE
        wall_open = draws.rand("open_walls", (W, 12)) < self.params.open_wall
        inside = ROOM / 2 - WALL_THICKNESS / 2  # quarters of the home room, clear of its walls
        pos = scenery.cell_spawn(draws, W, torch.full((N,), AGENT_RADIUS + 0.1), 2, inside)
        yaw = (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi
        home, goal_room = home.to(self.device), goal_room.to(self.device)
        goal = goal.to(self.device) + self.room_centre(goal_room)[:, None]
        return self.at_rest(pos.to(self.device) + self.room_centre(home)[:, None], yaw, door=door,
                            wall_open=wall_open, goal=goal,
                            home=home, visited=torch.nn.functional.one_hot(home, GRID * GRID).bool(),
                            finder=torch.zeros(W, N, dtype=torch.bool), returned=torch.zeros(W, dtype=torch.bool))

    def rules(self, before, moved, actions, alive, generator):
        room = room_of(moved.pos)  # [W, A]
        entered = (room[..., None] == torch.arange(GRID * GRID, device=self.device)) & alive[..., None]
        visited = before.visited | entered.any(1)
        finder = before.finder | (((moved.pos - moved.goal).norm(dim=-1) < REACH) & alive)
        found_now = finder.any(1) & ~before.finder.any(1)
        back = (finder & alive & (room == moved.home[:, None])).any(1) & self.params.return_home
        returned_now = back & ~before.returned
        returned = before.returned | back
        events = found_now.to(torch.float32) + returned_now.to(torch.float32)
        shared = self.params.found_reward * events - self.params.step_penalty
        if self.params.explore_reward:
            shared = shared + self.params.explore_reward * (visited & ~before.visited).sum(1).to(torch.float32)
        reward = shared[:, None].expand(-1, self.num_agents)
        done = returned if self.params.return_home else finder.any(1)
        state = dataclasses.replace(moved, visited=visited, finder=finder, returned=returned)
        info = {"found": finder.any(1).long(), "returned": returned.long(), "rooms_visited": visited.sum(1)}
        return state, reward, done[:, None].expand(-1, self.num_agents).clone(), info

    def obstacles(self, state):
        centre, size, shown = self.walls(state)
        centre = torch.where(shown[..., None], centre, torch.full_like(centre, FAR_AWAY))
        return planar.Obstacles(centre, size[..., :2] / 2, torch.zeros_like(centre[..., 0]))

    def observation(self, state, alive):
        W, N = self.num_worlds, self.num_agents
        pos, f = state.pos[:, :N], state.pos.dtype
        sees = (room_of(pos) == room_of(state.goal)).to(f)[..., None]  # [W, N, 1]: in the goal's room
        layout = torch.cat((state.visited.to(f), (~state.wall_open).to(f), state.door), -1)[:, None].expand(W, N, -1)
        found = state.finder.any(1, keepdim=True)[:, None].expand(W, N, 1).to(f)
        return torch.cat((self.own_obs(state), layout, sees, (state.goal - pos) * sees, state.finder[..., None].to(f),
                          found, self.room_centre(state.home)[:, None] - pos, self.others_obs(state).reshape(W, N, -1)),
                         -1)

    def heuristic(self, state, alive):
        """Only what the state observation gives: an agent in the goal's room drives to the goal;
        otherwise it heads for the nearest room nobody has visited (or, having reached the goal
        with return_home, for the home room) through the doors on a shortest path: lined up with
        the next door it drives through it, else to a point just before it."""
        N, t = self.num_agents, self.tables
        pos = state.pos[:, :N]
        room = room_of(pos)
        steps = t["steps"][room].to(torch.float32) * 16 + self.preference  # [W, N, 9]
        steps = torch.where(state.visited[:, None], torch.full_like(steps, math.inf), steps)
        target = torch.where(torch.isinf(steps.amin(-1)), state.home[:, None], steps.argmin(-1))
        going_home = state.finder & self.params.return_home
        target = torch.where(going_home, state.home[:, None], target)
        ahead = t["next_room"][room, target]  # [W, N]
        direction = t["room_centre"][ahead] - t["room_centre"][room]
        direction = direction / torch.linalg.vector_norm(direction, dim=-1, keepdim=True).clamp_min(1e-6)
        door = self.doors(state).gather(1, t["slot_to"][room, ahead][..., None].expand(-1, -1, 2))
        offset = pos - door
        lateral = (offset - (offset * direction).sum(-1, keepdim=True) * direction).norm(dim=-1, keepdim=True)
        waypoint = door + direction * torch.where(lateral < 0.1, 0.5, -0.4)
        waypoint = torch.where((ahead == room)[..., None], t["room_centre"][room], waypoint)
        sees_goal = (room == room_of(state.goal)) & ~going_home
        return self.steer_to(state, torch.where(sees_goal[..., None], state.goal.expand(-1, N, 2), waypoint))

    # ------------------------------------------------------------------ the layout
    def room_centre(self, room: torch.Tensor) -> torch.Tensor:
        """[..., 2] centres of rooms (int64 [...])."""
        return self.tables["room_centre"][room]

    def doors(self, state) -> torch.Tensor:
        """[W, 12, 2] door centres of the wall slots (where one would be if the slot is open)."""
        return self.tables["slot_centre"] + state.door[..., None] * self.tables["along"]

    def walls(self, state):
        """(centres [W, 24, 2], full sizes [W, 24, 3], shown [W, 24] bool) of the wall boxes: each
        slot's piece before its door (2k) and after it (2k + 1), each running into the corners."""
        end = ROOM / 2 + WALL_THICKNESS / 2
        before, after = state.door - DOOR_WIDTH / 2, state.door + DOOR_WIDTH / 2
        middle = torch.stack(((before - end) / 2, (after + end) / 2), -1)  # [W, 12, 2] along the slot
        length = torch.stack((before + end, end - after), -1)
        along = self.tables["along"][:, None]  # [12, 1, 2]
        centre = self.tables["slot_centre"][:, None] + middle[..., None] * along  # [W, 12, 2, 2]
        size = length[..., None] * along + WALL_THICKNESS * (1 - along)
        size = torch.cat((size, torch.full_like(size[..., :1], WALL_HEIGHT)), -1)
        W = state.door.shape[0]
        shown = (~state.wall_open)[..., None].expand(W, 12, 2)
        return centre.reshape(W, 24, 2), size.reshape(W, 24, 3), shown.reshape(W, 24)


def room_of(pos: torch.Tensor) -> torch.Tensor:
    """int64 [...]: the room (row * 3 + col) that contains each point pos [..., 2]."""
    cell = ((pos + ARENA) / ROOM).floor().clamp(0, GRID - 1).long()
    return cell[..., 1] * GRID + cell[..., 0]


def room_floors() -> Static:
    """A faint tint of each room's floor (the same in every world): something to remember a room by."""
    tint = 0.75 * torch.tensor(scenery.FLOOR_COLOR) + 0.25 * scenery.palette(GRID * GRID)
    centre = torch.tensor(TABLES["room_centre"])
    return Static("room_floors", "plane", position=torch.cat((centre, torch.full((9, 1), 0.002)), 1).tolist(),
                  scale=[[ROOM, ROOM, 1.0]] * 9, color=tint.tolist())


def outer_walls() -> Static:
    """The arena's walls raised to WALL_HEIGHT (over the default ones, which are lower)."""
    h, t = WALL_HEIGHT, WALL_THICKNESS
    position = [[ARENA + t / 2, 0.0, h / 2], [-ARENA - t / 2, 0.0, h / 2], [0.0, ARENA + t / 2, h / 2],
                [0.0, -ARENA - t / 2, h / 2]]
    scale = [[t, 2 * ARENA + 2 * t, h]] * 2 + [[2 * ARENA, t, h]] * 2
    return Static("outer_walls", "box", position=position, scale=scale, color=[list(scenery.WALL_COLOR)] * 4,
                  role="wall")
