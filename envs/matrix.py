"""In the matrix: a matrix game played with inventories, in an arena seen through egocentric cameras.

After Melting Pot's "*_in_the_matrix" substrates. Resources of K kinds lie about the arena; an
agent collects them into its inventory by walking over them, and so commits to a mixed strategy
(its inventory's proportions). An interaction beam pairs two agents: each is paid by its payoff
matrix applied to both inventories as mixed strategies; both then leave the arena for a few steps
and come back elsewhere with empty inventories.

* Arena: |x|, |y| <= 2.5 m. Agents: capsules of radius 0.15 m (physics: walls, body collisions,
  drag), egocentric movement plus the action "interact" (discrete 5; continuous: a third value
  > 0.5). Camera at 0.4 m, 90 degree field of view.
* Resources: ``resources_per_kind`` of each kind (default 6), spheres of radius 0.07 m placed at
  random each episode (kind k's colour: green, red, yellow, ...: KIND_COLORS). An agent in play
  whose centre comes within 0.22 m of a present resource collects it (the closest agent, lowest
  index on a tie): its inventory of that kind grows by 1. A collected resource comes back at its
  place after ``regrow_steps`` (default 30).
* Interacting: an agent in play holding at least one resource beams the nearest other such agent
  within 1.2 m whose centre lies within 30 degrees of its heading. Beams are matched into pairs:
  of all beams touching an agent, the shortest wins (so each agent meets at most one partner a
  step; the shortest beam of a world always pairs). In a pair the beaming agent is the row player
  and its target the column player: with strategies p = own inventory / its sum and q = the
  partner's, the row player gets p^T A q and the column player p^T B q (A, B: the game's payoff
  matrices; B = A^T for symmetric games, where the roles do not matter). Both are then out of play
  for ``respawn_steps`` (default 5; not drawn, inactive) with empty inventories, and reappear at
  one of 8 spawn points along the walls (drawn from the generator) facing the centre. Each keeps
  its last partner's inventory (the state field ``partner``, in the state observation), as
  Melting Pot's repeated substrates show it.
* Games (``game``): "prisoners_dilemma" (default; kinds cooperate, defect), "stag_hunt" (stag,
  hare), "chicken" (swerve, straight), "pure_coordination", "battle_of_the_sexes" (K = 2;
  asymmetric: the row player prefers kind 0, the column player kind 1) and
  "rock_paper_scissors" (K = 3); or your own ``payoff``: a K x K matrix (a symmetric game) or a
  pair (A, B) of them (K in [2, 8]). Kind 0 is the cooperative one, kind K - 1 the defecting one
  (the bots "cooperator" and "defector" collect those).
* Agents: default 8 (2 to 16); ``repeated=True`` is the 2-agent repeated variant (num_agents 2).
* Observations: the pixels and ``"inventory"`` float32 [W, A, K], the agent's own inventory
  (Melting Pot's INVENTORY), in every front end. State obs (7 + 2K + 3R + 3(N - 1), R = K x
  resources_per_kind): own position, velocity, cos/sin yaw (6), remaining time out /
  respawn_steps (1), own inventory (K), last partner's inventory (K), the resources relative to
  the agent times their present flag (2 each) and the flags (1 each), the other agents' relative
  positions times their in-play flag (2 each) and the flags (1 each).
* action_mask: all valid in play, only noop while out. Reward: the payoffs of the step's
  interactions. Episode: never terminates; a mixed-motive task, so it ends at random (Melting
  Pot's, envs/episodes.py) after at least 150 steps, at max_steps = 300 at the latest, and reports
  the social outcomes (efficiency, equality, sustainability, peace: peace counts agent-steps not
  spent out after an interaction).
* info (each [W]): ``"collected"`` int64 resources collected in the step, ``"interactions"``
  int64 pairs that interacted in it.
"""
from __future__ import annotations

import dataclasses
import math

import torch

import marl_render as mr
from marl_render.util.validation import COUNT_LIMIT, describe, positive_int

from . import egomotion, scenery
from .arena import ArenaScenario, ArenaState, Prop, numbered
from .roster import Bot, Card, HeldOut
from .scenario import MAX_COUNT, VectorObs

ARENA = 2.5
SPAWN_GRID = 5  # agents start in distinct cells of a 5 x 5 grid (up to 16 agents)
AGENT_RADIUS = 0.15
RESOURCE_RADIUS = 0.07
REACH = AGENT_RADIUS + RESOURCE_RADIUS
RESOURCE_MARGIN = 0.3  # resources lie at least this far inside the walls
BEAM_RANGE = 1.2
BEAM_HALF_ANGLE = math.radians(30.0)
HOLD = 2  # the bots collect this many resources before they seek a partner
MAX_KINDS = 8
KIND_COLORS = ((0.2, 0.75, 0.3), (0.85, 0.15, 0.15), (0.95, 0.8, 0.1), (0.6, 0.3, 0.85), (0.1, 0.8, 0.85),
               (0.95, 0.5, 0.1), (0.9, 0.9, 0.9), (0.35, 0.2, 0.1))
RESPAWN_POINTS = ((-2.2, 0.0), (2.2, 0.0), (0.0, -2.2), (0.0, 2.2), (-2.2, -2.2), (-2.2, 2.2), (2.2, -2.2),
                  (2.2, 2.2))

# Row player's payoff A[own kind][partner's kind] and the column player's B (indexed [row kind][column
# kind]); None: symmetric, B = A^T. Melting Pot's values.
GAMES = {
    "prisoners_dilemma": (((3.0, 0.0), (5.0, 1.0)), None),  # cooperate, defect
    "stag_hunt": (((4.0, 0.0), (2.0, 2.0)), None),  # stag, hare
    "chicken": (((3.0, 2.0), (5.0, 0.0)), None),  # swerve, straight
    "pure_coordination": (((1.0, 0.0), (0.0, 1.0)), None),
    "battle_of_the_sexes": (((3.0, 0.0), (0.0, 2.0)), ((2.0, 0.0), (0.0, 3.0))),
    "rock_paper_scissors": (((0.0, -1.0, 1.0), (1.0, 0.0, -1.0), (-1.0, 1.0, 0.0)), None),
}
PAYOFF_LIMIT = 1e6


def _matrix(name: str, value) -> tuple:
    """A K x K matrix of finite numbers as a tuple of tuples of floats, K in [2, MAX_KINDS]."""
    want = f"a K x K matrix (K in [2, {MAX_KINDS}]) of finite numbers within +-{PAYOFF_LIMIT:g}"
    rows = value if isinstance(value, (tuple, list)) else None
    if not (rows and 2 <= len(rows) <= MAX_KINDS and all(isinstance(row, (tuple, list)) and len(row) == len(rows)
                                                        for row in rows)):
        raise ValueError(f"{name} must be {want}, got {describe(value)}")
    numbers = [x for row in rows for x in row]
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
               and abs(x) <= PAYOFF_LIMIT for x in numbers):
        raise ValueError(f"{name} must be {want}, got {value!r}")
    return tuple(tuple(float(x) for x in row) for row in rows)


@dataclasses.dataclass(frozen=True)
class MatrixParams:
    game: str = "prisoners_dilemma"  # a preset of GAMES (ignored where payoff is given)
    # Your own game: a K x K matrix (symmetric: the column player's is its transpose) or a pair (A, B).
    payoff: tuple | None = None
    resources_per_kind: int = 6
    regrow_steps: int = 30  # steps until a collected resource is back
    respawn_steps: int = 5  # steps both agents of an interaction stay out
    repeated: bool = False  # the 2-agent repeated variant

    def __post_init__(self):
        if not isinstance(self.game, str) or self.game not in GAMES:
            raise ValueError(f"game must be one of {sorted(GAMES)}, got {describe(self.game)}")
        if self.payoff is not None:
            self.matrices()  # raises naming payoff
        positive_int("resources_per_kind", self.resources_per_kind, maximum=64)
        positive_int("regrow_steps", self.regrow_steps, maximum=COUNT_LIMIT)
        positive_int("respawn_steps", self.respawn_steps, maximum=COUNT_LIMIT)
        if not isinstance(self.repeated, bool):
            raise TypeError(f"repeated must be a bool, got {describe(self.repeated)}")

    def matrices(self) -> tuple:
        """(A, B): the row and column players' payoffs, K x K tuples indexed [row kind][column kind]."""
        if self.payoff is None:
            row, column = GAMES[self.game]
        elif _is_pair(self.payoff):
            row, column = self.payoff
        else:
            row, column = self.payoff, None
        where = "game" if self.payoff is None else "payoff"
        row = _matrix(where if column is None else f"{where}'s row matrix", row)
        column = tuple(zip(*row, strict=True)) if column is None else _matrix(f"{where}'s column matrix", column)
        if len(column) != len(row):
            raise ValueError(f"payoff's two matrices must have the same size K, got {len(row)} and {len(column)}")
        return row, column


def _is_pair(payoff) -> bool:
    """Whether payoff is a pair (A, B) of matrices rather than one matrix of numbers."""
    return (isinstance(payoff, (tuple, list)) and len(payoff) == 2 and isinstance(payoff[0], (tuple, list))
            and len(payoff[0]) > 0 and isinstance(payoff[0][0], (tuple, list)))


@dataclasses.dataclass(frozen=True)
class MatrixState(ArenaState):
    resources: torch.Tensor  # [W, R, 2] resource places (m), kind k holds resources k*n .. (k+1)*n - 1
    regrow: torch.Tensor  # [W, R] int64 steps until a resource is back; 0: present
    inventory: torch.Tensor  # [W, A, K] int64 resources held
    partner: torch.Tensor  # [W, A, K] int64 the last partner's inventory when they interacted
    timeout: torch.Tensor  # [W, A] int64 steps an agent stays out after an interaction; 0: in play
    shown: torch.Tensor  # [W, A] bool agents in play (drawn)


def _collector(kind: str):
    def script(env):
        return env.scenario.collector(env.sim, env.alive, kind)
    script.__name__ = f"{kind}_script"
    return script


class Matrix(ArenaScenario):
    """Collect resources into an inventory (a mixed strategy), then beam a partner to play a matrix game."""

    name = "matrix"
    Params = MatrixParams
    State = MatrixState
    difficulties = {"easy": {"resources_per_kind": 10, "regrow_steps": 15}, "medium": {},
                    "hard": {"resources_per_kind": 4, "regrow_steps": 60}}
    default_num_agents = 8
    agent_range = (2, 16)
    default_max_steps = 300
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"collected": torch.int64, "interactions": torch.int64}
    arena_half_extent = (ARENA, ARENA)
    shown = "shown"
    mixed_motive = True
    # Step budgets (env steps summed over worlds): 88 and 176 updates of 32 worlds x 32 decisions, what three
    # seeds of every new task fit in one 3-hour session on 2 cores. The estimate for learning was forage's (175
    # and 990 updates; a random end makes a mean episode 192 steps, about forage's): these are short runs.
    training = {"budget": {"pixels": 90_112, "state": 180_224}}
    schelling = ("cooperator", "defector")
    bots = {
        "cooperator": Bot("collects only kind 0 (cooperate, stag, swerve), then beams the nearest agent holding "
                          "resources", script=_collector("cooperate")),
        "defector": Bot("collects only kind K-1 (defect, hare, straight), then beams the nearest agent holding "
                        "resources", script=_collector("defect")),
        "reciprocator": Bot("tit for tat: collects the kind its last partner held most of (kind 0 before it met "
                            "anyone), then beams", script=_collector("reciprocate")),
        "noisy0.2": Bot.noisy(0.2, population="train"),
    }
    heldout = (
        HeldOut("visitor_cooperators", "visitor: one focal agent among 7 cooperators", num_agents=8,
                focal=("agent_0",), bots_by_role={"agents": ("cooperator",)}),
        HeldOut("visitor_defectors", "visitor: one focal agent among 7 defectors", num_agents=8,
                focal=("agent_0",), bots_by_role={"agents": ("defector",)}),
        HeldOut("visitor_reciprocators", "visitor: one focal agent among 7 tit-for-tat reciprocators",
                num_agents=8, focal=("agent_0",), bots_by_role={"agents": ("reciprocator",)}),
        HeldOut("resident_with_defectors", "resident: 6 focal agents with 2 defectors", num_agents=8,
                focal=tuple(numbered("agent", 6)), bots_by_role={"agents": ("defector",)}),
        HeldOut("repeated_reciprocator", "visitor, repeated: one focal agent and one reciprocator, 2 agents",
                num_agents=2, focal=("agent_0",), bots_by_role={"agents": ("reciprocator",)},
                params={"repeated": True}),
    )
    card = Card(text="Collect resources of K kinds into an inventory, which is a mixed strategy, then beam another "
                     "agent: both are paid by a matrix game of the two inventories (prisoner's dilemma by default; "
                     "stag hunt, chicken, pure coordination, battle of the sexes, rock-paper-scissors or your own "
                     "payoff) and come back with empty inventories. Each agent observes its inventory beside the "
                     "pixels (obs key \"inventory\"). After Melting Pot's \"in the matrix\" substrates.",
                reward="per agent, at an interaction: p^T A q for the beaming (row) agent, p^T B q for its partner "
                       "(p, q: the two inventories' proportions; A, B: the game's payoff matrices); 0 otherwise",
                episode_end="never terminates; truncated at the episode's end (random by default: mixed motive)",
                continuous=egomotion.CONTINUOUS_MEANINGS + (
                    "interact (> 0.5: beam the nearest agent holding resources within 1.2 m and 30 degrees ahead)",),
                info={"collected": "resources collected in this step",
                      "interactions": "pairs that interacted in this step"})

    @classmethod
    def num_agents_for(cls, params, num_agents):
        if params.repeated:
            if num_agents not in (None, 2):
                raise ValueError(f"num_agents must be 2 (or None) with repeated=True (the 2-agent repeated "
                                 f"variant), got {num_agents!r}")
            return 2
        return num_agents

    def setup(self):
        N = self.num_agents
        row, column = self.params.matrices()
        K = self.num_kinds = len(row)
        n = self.params.resources_per_kind
        R = self.num_resources = K * n
        self.setup_arena({"agents": numbered("agent", N)}, state_dim=7 + 2 * K + 3 * R + 3 * (N - 1),
                         radius=AGENT_RADIUS, max_speed=2.0, extra_actions=("interact",))
        self.row_payoff = torch.tensor(row, device=self.device, dtype=torch.float32)
        self.column_payoff = torch.tensor(column, device=self.device, dtype=torch.float32)
        self.kind = torch.arange(K, device=self.device).repeat_interleave(n)  # [R]
        self.vector_obs = {"inventory": VectorObs(K, 0.0, math.inf)}
        self.respawn_points = torch.tensor(RESPAWN_POINTS, device=self.device)
        self._index = torch.arange(N, device=self.device)
        self._not_self = ~torch.eye(N, dtype=torch.bool, device=self.device)

    def _fresh(self, pos, yaw, resources):
        W, N, K = self.num_worlds, self.num_agents, self.num_kinds
        return self.at_rest(pos, yaw, resources=resources,
                            regrow=torch.zeros(W, self.num_resources, dtype=torch.int64),
                            inventory=torch.zeros(W, N, K, dtype=torch.int64),
                            partner=torch.zeros(W, N, K, dtype=torch.int64),
                            timeout=torch.zeros(W, N, dtype=torch.int64), shown=torch.ones(W, N, dtype=torch.bool))

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self._fresh(torch.zeros(W, N, 2), torch.zeros(W, N), torch.zeros(W, self.num_resources, 2))

    def spawn_level(self, draws):
        W, N = self.num_worlds, self.num_agents
        pos = scenery.cell_spawn(draws, W, torch.full((N,), AGENT_RADIUS + 0.05), SPAWN_GRID, ARENA)
        yaw = (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi
        resources = (draws.rand("resources", (W, self.num_resources, 2)) * 2 - 1) * (ARENA - RESOURCE_MARGIN)
        return self._fresh(pos, yaw, resources)

    def state_bounds(self):
        return {**super().state_bounds(), "resources": self.inside_walls(), "regrow": (0, self.params.regrow_steps),
                "inventory": (0, MAX_COUNT), "partner": (0, MAX_COUNT), "timeout": (0, self.params.respawn_steps)}

    def check_state(self, state):
        if not torch.equal(state["shown"], state["timeout"] == 0):
            raise ValueError("state['shown'] must be True exactly for the agents in play (state['timeout'] == 0)")
        if bool(((state["timeout"] > 0)[..., None] & (state["inventory"] > 0)).any()):
            raise ValueError("state['inventory'] must be empty (0) for agents out of play (state['timeout'] > 0)")

    def props(self):
        colors = torch.tensor(KIND_COLORS[:self.num_kinds])[self.kind.cpu()]
        return [Prop("resources", mr.sphere(segments=10, rings=5),
                     count=self.num_resources, height=RESOURCE_RADIUS, position="resources",
                     active=lambda state: state.regrow == 0, scale=(2 * RESOURCE_RADIUS,) * 3, color=colors)]

    def bodies(self, state, active):
        return super().bodies(state, active & (state.timeout == 0))  # agents out neither move nor collide

    def tagged_out(self, state):
        return state.timeout > 0

    # ------------------------------------------------------------------ rules
    def _beams(self, state, interact, playing):
        """(seen [W, A, A] bool: whom each agent's beam may pair it with, gap [W, A, A] m): agents in play
        holding resources, the target within range and the beam's cone."""
        N = self.num_agents
        ready = playing & (state.inventory.sum(-1) > 0)
        delta = state.pos[:, None, :N] - state.pos[:, :N, None]  # [W, from, to, 2]
        bearing = torch.atan2(-delta[..., 0], delta[..., 1])
        gap = torch.linalg.vector_norm(delta, dim=-1)
        seen = (scenery.wrap_angle(bearing - state.yaw[..., None]).abs() <= BEAM_HALF_ANGLE) & (gap <= BEAM_RANGE)
        return seen & (interact & ready)[:, :, None] & ready[:, None, :] & self._not_self, gap

    def pairs(self, state, interact, playing):
        """[W, A, A] bool: row player i pairs with column player j this step (see the module docstring)."""
        N = self.num_agents
        seen, gap = self._beams(state, interact, playing)
        inf = torch.full_like(gap, math.inf, dtype=torch.float64)
        # Each beam hits the nearest agent it may pair with; a beam's key is its length (ties: by index).
        nearest = torch.where(seen, gap, torch.full_like(gap, math.inf)).argmin(-1)  # [W, A]
        beam = torch.nn.functional.one_hot(nearest, N).bool() & seen.any(-1, keepdim=True)  # [W, from, to]
        order = (self._index[:, None] * N + self._index[None, :]).to(torch.float64) * 1e-9
        key = torch.where(beam, gap.to(torch.float64) + order, inf)
        pair_key = torch.minimum(key, key.transpose(1, 2))  # a pair's key: its shortest beam
        best = pair_key.amin(-1)  # [W, A]: each agent's shortest pair
        chosen = torch.isfinite(pair_key) & (pair_key == best[:, :, None]) & (pair_key == best[:, None, :])
        return chosen & (key == pair_key)  # the agent whose beam it was is the row player

    def payoffs(self, inventory, pairs):
        """[W, A] float32: each agent's payoff of this step's pairs (0 for agents without a partner)."""
        strategy = inventory.to(torch.float32) / inventory.sum(-1, keepdim=True).clamp_min(1)
        as_row, as_column = pairs.any(2), pairs.any(1)
        partner = torch.where(as_row, pairs.to(torch.int8).argmax(2), pairs.to(torch.int8).argmax(1))  # [W, A]
        theirs = strategy.gather(1, partner[..., None].expand_as(strategy))
        row = torch.einsum("wak,kl,wal->wa", strategy, self.row_payoff, theirs)
        column = torch.einsum("wak,kl,wal->wa", theirs, self.column_payoff, strategy)
        return torch.where(as_row, row, torch.where(as_column, column, torch.zeros_like(row))), partner

    def rules(self, before, moved, actions, alive, generator):
        W, N, g = self.num_worlds, self.num_agents, generator
        playing = alive & (before.timeout == 0)
        yaw = torch.where(playing, moved.yaw, before.yaw)
        # Collection: the closest agent in play touching a present resource takes it.
        present = before.regrow == 0
        dist = torch.cdist(moved.pos[:, :N], moved.resources)  # [W, N, R]
        touching = (dist < REACH) & present[:, None, :] & playing[:, :, None]
        taken = touching.any(1)
        taker = torch.where(touching, dist, torch.full_like(dist, math.inf)).argmin(1)  # [W, R]
        got = (taker[:, None, :] == self._index[None, :, None]) & taken[:, None, :]  # [W, N, R]
        inventory = before.inventory + got.to(torch.int64) @ torch.nn.functional.one_hot(self.kind, self.num_kinds)
        regrow = torch.where(taken, self.params.regrow_steps, (before.regrow - 1).clamp_min(0))
        # Interactions, with the inventories after this step's collection.
        interact = actions[..., 2] > 0.5 if self.continuous else actions == 5
        now = dataclasses.replace(moved, yaw=yaw, inventory=inventory)
        pairs = self.pairs(now, interact, playing)
        reward, partner = self.payoffs(inventory, pairs)
        met = pairs.any(2) | pairs.any(1)
        theirs = inventory.gather(1, partner[..., None].expand_as(inventory))
        partner_inventory = torch.where(met[..., None], theirs, before.partner)
        # Time out: counts down; agents whose time out ends come back at a random spawn point.
        timeout = (before.timeout - 1).clamp_min(0)
        back = before.timeout == 1
        point = self.respawn_points[torch.randint(len(RESPAWN_POINTS), (W, N), generator=g).to(self.device)]
        pos = torch.where(back[..., None], point, moved.pos[:, :N])
        yaw = torch.where(back, torch.atan2(point[..., 0], -point[..., 1]), yaw)  # facing the centre
        timeout = torch.where(met, self.params.respawn_steps, timeout)
        inventory = torch.where(met[..., None], torch.zeros_like(inventory), inventory)
        state = dataclasses.replace(moved, pos=pos, yaw=yaw, vel=moved.vel * (timeout == 0)[..., None], regrow=regrow,
                                    inventory=inventory, partner=partner_inventory, timeout=timeout,
                                    shown=timeout == 0)
        info = {"collected": taken.sum(-1), "interactions": pairs.sum((1, 2))}
        return state, reward, torch.zeros_like(alive), info

    def action_mask(self, state, alive):
        mask = (alive & (state.timeout == 0))[:, :, None].expand(-1, -1, self.num_actions).clone()
        mask[..., 0] = True  # noop is always valid
        return mask

    # ------------------------------------------------------------------ observations
    def vector_observations(self, state, alive):
        return {"inventory": state.inventory.to(torch.float32)}

    def observation(self, state, alive):
        W, N = self.num_worlds, self.num_agents
        dtype = state.pos.dtype
        present = (state.regrow == 0)[:, None, :, None].to(dtype)  # [W, 1, R, 1]
        resources = (self.relative(state, state.resources) * present).reshape(W, N, -1)
        in_play = state.shown[:, self.others].to(dtype)  # [W, N, N-1]
        others = (self.others_obs(state) * in_play[..., None]).reshape(W, N, -1)
        timeout = state.timeout[..., None].to(dtype) / self.params.respawn_steps
        return torch.cat((self.own_obs(state), timeout, state.inventory.to(dtype), state.partner.to(dtype), resources,
                          present[..., 0].expand(W, N, -1), others, in_play), -1)

    # ------------------------------------------------------------------ scripted play
    def heuristic(self, state, alive):
        """The cooperator: collects HOLD resources of kind 0, then drives to the nearest agent in play
        that holds resources and beams it once it is in the beam's cone and range."""
        return self.collector(state, alive, "cooperate")

    def collector(self, state, alive, mode: str):
        """Actions of agents that collect HOLD resources of one kind, then seek a partner and beam it.
        mode: "cooperate" (kind 0), "defect" (kind K-1) or "reciprocate" (the kind the agent's last
        partner held most of; kind 0 before it met anyone)."""
        W, N, K = self.num_worlds, self.num_agents, self.num_kinds
        if mode == "cooperate":
            wanted = torch.zeros(W, N, dtype=torch.int64, device=self.device)
        elif mode == "defect":
            wanted = torch.full((W, N), K - 1, dtype=torch.int64, device=self.device)
        elif mode == "reciprocate":
            wanted = torch.where(state.partner.sum(-1) > 0, state.partner.argmax(-1), 0)
        else:
            raise ValueError(f"mode must be 'cooperate', 'defect' or 'reciprocate', got {mode!r}")
        playing = alive & (state.timeout == 0)
        # Collecting: the nearest present resource of the wanted kind.
        dist = torch.cdist(state.pos[:, :N], state.resources)  # [W, N, R]
        usable = (state.regrow == 0)[:, None, :] & (self.kind[None, None, :] == wanted[..., None])
        dist = torch.where(usable, dist, torch.full_like(dist, math.inf))
        resource = state.resources.gather(1, dist.argmin(-1)[..., None].expand(-1, -1, 2))  # [W, N, 2]
        # Seeking: the nearest other agent in play holding resources.
        ready = playing & (state.inventory.sum(-1) > 0)
        gap = torch.cdist(state.pos[:, :N], state.pos[:, :N])
        gap = torch.where(ready[:, None, :] & self._not_self, gap, torch.full_like(gap, math.inf))
        mate = state.pos[:, :N].gather(1, gap.argmin(-1)[..., None].expand(-1, -1, 2))
        seeking = state.inventory.sum(-1) >= HOLD
        no_resource = torch.isinf(dist.amin(-1))
        seeking = seeking | (no_resource & (state.inventory.sum(-1) > 0))
        target = torch.where(seeking[..., None], mate, resource)
        lost = torch.where(seeking, torch.isinf(gap.amin(-1)), no_resource)  # nothing to go for: stay
        target = torch.where(lost[..., None], state.pos[:, :N], target)
        drive = self.steer_to(state, target)
        seen, _ = self._beams(state, torch.ones_like(playing), playing)
        beam = seeking & seen.any(-1)
        if self.continuous:
            drive = torch.cat((drive, torch.where(beam, 1.0, -1.0)[..., None].to(drive.dtype)), -1)
            return torch.where(playing[..., None], drive, torch.zeros_like(drive))
        return torch.where(playing, torch.where(beam, 5, drive), 0)
