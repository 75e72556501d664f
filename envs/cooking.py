"""Collaborative cooking (after Overcooked and Melting Pot's collaborative_cooking): a kitchen where a
team cooks soups to a recipe, seen through egocentric cameras.

* Kitchen: a grid of 9 x 5 cells of 0.6 m (|x| <= 2.7 m, |y| <= 1.5 m), each a floor cell or a
  counter 0.3 m high (solid boxes of the physics). Counters may be stations: a pot, a dish stack,
  a delivery point, an onion or a tomato dispenser. ``kitchen`` picks the layout: one of the five
  classic Overcooked kitchens (``cramped_room``, ``asymmetric_advantages``, ``coordination_ring``,
  ``forced_coordination``, ``counter_circuit``, centred in the grid and padded with counters, each
  with a tomato dispenser in place of one of its onion dispensers or beside it), ``"classic"`` (one
  of the five per level) or ``"procedural"`` (a ring of counters round a floor with islands drawn in
  its middle row and the six stations at drawn places of the ring; every level its own kitchen).
* Agents: 2 by default, 1 to 4; capsules of radius 0.15 m; the first two start on the classic
  kitchens' start cells, every other agent on a drawn free floor cell; random headings.
* Holding: an agent holds nothing, an ingredient (onion, tomato), an empty dish or a dish of soup;
  a counter holds one such item; a pot holds up to 3 ingredients.
* The extra action ``interact`` (discrete 5; continuous: the third value > 0.5) acts on the cell
  0.45 m ahead of the agent's centre before the step (the counter it faces): take an ingredient from a dispenser or
  a dish from the stack (empty hands); put an ingredient into a pot that holds fewer than 3 and is
  not cooking; plate a cooked soup (with an empty dish: the pot empties); deliver a soup at the
  delivery point (the dish goes); put down an item on an empty counter, or pick one up. When
  several agents act on one cell in a step, only the lowest-indexed one does.
* Cooking: a pot with 3 ingredients cooks by itself; it is done ``cook_time`` steps later.
* Recipe: a soup is its number of tomatoes (0 to 3; with ``num_ingredients`` = 1 always 0: onion
  soup); one recipe is drawn per episode. A delivered soup of the recipe pays ``delivery_reward``
  (default 20) to every agent; any other soup pays nothing.
* The recipe is drawn as three balls of the ingredients' colours floating over the (first)
  delivery point. ``recipe_view="all"`` shows it to everyone; ``"one"`` hides it from every view
  but agent 0's (the renderer's per-view mask, as speaker_listener's ring; 2 agents only): partial,
  asymmetric information.
* Episode: never terminates; truncated after ``max_steps`` = 400.
* State obs (738 + 10 (N - 1)): own position, velocity, cos/sin yaw (6); what it holds (one-hot
  over the 8 item codes); per cell (45 x 16): its station (6 flags), the item on it (7 flags), a
  pot's onions and tomatoes / 3 and its cooking progress; the recipe one-hot (4; zeros for agents
  who do not see it); the other agents' relative positions (2) and what they hold (8). World frame.
* info (each [W]): ``"delivered"`` soups of the recipe delivered in the step, ``"wrong"`` other
  soups delivered in it, ``"served"`` soups of the recipe delivered this episode.
"""
from __future__ import annotations

import dataclasses
import math

import torch

import marl_render as mr
from marl_render.util.validation import COUNT_LIMIT, positive_int, reward_weight

from . import egomotion, planar, scenery
from .arena import ArenaScenario, ArenaState, Prop, numbered
from .roster import Bot, Card, HeldOut
from .scenario import MAX_COUNT

GW, GH = 9, 5  # grid columns, rows (row 0 is the far side, +y)
G = GW * GH
CELL = 0.6
HX, HY = GW * CELL / 2, GH * CELL / 2
AGENT_RADIUS = 0.15
REACH = 0.45  # the faced cell is the one 0.45 m ahead of the agent's centre
COUNTER_HEIGHT = 0.3
FAR_AWAY = 1000.0  # where a floor cell's box goes for the physics
STAND_COST = 100.0  # the heuristic's path cost of standing aside instead of reaching a goal

# Cell types.
FLOOR, COUNTER, POT, DISHES, SERVE, ONION_BOX, TOMATO_BOX = range(7)
STATION_TYPES = 6  # the non-floor types, the observation's station flags
# Item codes (held, or on a counter): soup of r tomatoes (and 3 - r onions) is SOUP + r.
EMPTY, ONION, TOMATO, DISH, SOUP = 0, 1, 2, 3, 4
ITEM_CODES = 8
RECIPES = 4
INTERACT = 5  # the discrete action

CLASSIC = {  # the Overcooked kitchens: X counter, P pot, D dish stack, S delivery, O onions, T tomatoes
    "cramped_room": ("XXPXX",
                     "O  2T",
                     "X1  X",
                     "XDXSX"),
    "asymmetric_advantages": ("XXXXXXXXX",
                              "O XSXOX S",
                              "T   P 1 T",
                              "X2  P   X",
                              "XXXDXDXXX"),
    "coordination_ring": ("XXXPX",
                          "X  1P",
                          "D2X X",
                          "O   X",
                          "XTSXX"),
    "forced_coordination": ("XXXPX",
                            "O X1P",
                            "T2X X",
                            "D X X",
                            "XXXSX"),
    "counter_circuit": ("XXXPPXXX",
                        "X      X",
                        "D XXXX S",
                        "X2    1X",
                        "XXXOTXXX"),
}
KITCHENS = (*CLASSIC, "classic", "procedural")
CHARS = {" ": FLOOR, "1": FLOOR, "2": FLOOR, "X": COUNTER, "P": POT, "D": DISHES, "S": SERVE, "O": ONION_BOX,
         "T": TOMATO_BOX}

COUNTER_COLOR = (0.62, 0.48, 0.33)
ONION_COLOR = (0.95, 0.85, 0.25)
TOMATO_COLOR = (0.85, 0.12, 0.10)
DISH_COLOR = (0.95, 0.95, 0.95)
SERVE_COLOR = (0.20, 0.75, 0.30)
POT_COLOR = (0.18, 0.18, 0.20)
TILE_COLORS = ((0.0, 0.0, 0.0), COUNTER_COLOR, (0.30, 0.30, 0.32), (0.80, 0.80, 0.86), SERVE_COLOR, ONION_COLOR,
               TOMATO_COLOR)  # by cell type
ONION_SOUP, TOMATO_SOUP = (0.92, 0.62, 0.15), (0.75, 0.20, 0.10)
ITEM_COLORS = ((0.0, 0.0, 0.0), ONION_COLOR, TOMATO_COLOR, DISH_COLOR,
               *(tuple(a + (b - a) * r / 3 for a, b in zip(ONION_SOUP, TOMATO_SOUP, strict=True)) for r in range(4)))
ITEM_SCALES = ((0.0, 0.0, 0.0), (0.16, 0.16, 0.16), (0.16, 0.16, 0.16), (0.30, 0.30, 0.05),
               *((0.26, 0.26, 0.14),) * 4)
DONE_COLOR = (1.0, 0.55, 0.10)  # a cooked pot's soup


def cell_centres() -> torch.Tensor:
    """[G, 2] the centres of the cells (row 0 at +y, column 0 at -x)."""
    row, col = torch.arange(G) // GW, torch.arange(G) % GW
    return torch.stack(((col + 0.5) * CELL - HX, (GH - 1 - row + 0.5) * CELL - HY), -1)


def classic_tables() -> tuple:
    """(cells [5, G] int64, starts [5, 2] int64): the classic kitchens centred in the grid (padded
    with counters) and the cells of their start marks 1 and 2."""
    cells, starts = [], []
    for rows in CLASSIC.values():
        top, left = (GH - len(rows)) // 2, (GW - len(rows[0])) // 2
        grid = [["X"] * GW for _ in range(GH)]
        for r, line in enumerate(rows):
            for c, char in enumerate(line):
                grid[top + r][left + c] = char
        flat = [char for line in grid for char in line]
        cells.append([CHARS[char] for char in flat])
        starts.append([flat.index("1"), flat.index("2")])
    return torch.tensor(cells), torch.tensor(starts)


def ring_candidates() -> torch.Tensor:
    """[20] the cells of the procedural ring that may hold a station: every ring cell but the corners."""
    return torch.tensor([c for c in range(1, GW - 1)] + [(GH - 1) * GW + c for c in range(1, GW - 1)]
                        + [r * GW for r in range(1, GH - 1)] + [r * GW + GW - 1 for r in range(1, GH - 1)])


def recipe_balls(recipe: torch.Tensor) -> torch.Tensor:
    """[W, 3] item codes of a recipe's three ingredients: 3 - r onions, then r tomatoes."""
    return torch.where(torch.arange(3, device=recipe.device) >= 3 - recipe[:, None], TOMATO, ONION)


@dataclasses.dataclass(frozen=True)
class CookingParams:
    kitchen: str = "cramped_room"  # a classic kitchen, "classic" (one per level) or "procedural"
    num_ingredients: int = 2  # 1: onions only (one recipe); 2: onions and tomatoes (four recipes)
    cook_time: int = 20  # steps a full pot cooks
    delivery_reward: float = 20.0  # to every agent per soup of the recipe delivered
    recipe_view: str = "all"  # "all": every agent sees the recipe; "one": agent 0 only (2 agents)

    def __post_init__(self):
        if self.kitchen not in KITCHENS:
            raise ValueError(f"kitchen must be one of {list(KITCHENS)}, got {self.kitchen!r}")
        if positive_int("num_ingredients", self.num_ingredients) > 2:
            raise ValueError(f"num_ingredients must be 1 or 2, got {self.num_ingredients}")
        positive_int("cook_time", self.cook_time, maximum=COUNT_LIMIT)
        reward_weight("delivery_reward", self.delivery_reward)
        if self.recipe_view not in ("all", "one"):
            raise ValueError(f"recipe_view must be 'all' or 'one', got {self.recipe_view!r}")


@dataclasses.dataclass(frozen=True)
class CookingState(ArenaState):
    cells: torch.Tensor  # [W, G] int64: each cell's type (FLOOR .. TOMATO_BOX)
    item: torch.Tensor  # [W, G] int64: the item on each counter (EMPTY .. SOUP + 3)
    pot: torch.Tensor  # [W, G, 2] int64: onions and tomatoes in each pot
    cook: torch.Tensor  # [W, G] int64: steps a full pot has cooked
    held: torch.Tensor  # [W, A] int64: the item each agent holds
    recipe: torch.Tensor  # [W] int64: the recipe's number of tomatoes
    served: torch.Tensor  # [W] int64: soups of the recipe delivered this episode


# ---------------------------------------------------------------- test bots: env -> actions [W, A]
def fetcher(env) -> torch.Tensor:
    """fetches the ingredients the pots lack and puts them in; never takes a dish"""
    return env.scenario.cook(env.sim, env.alive, plate=False)


def plater(env) -> torch.Tensor:
    """fetches dishes, plates cooked soups and delivers them; never fetches an ingredient"""
    return env.scenario.cook(env.sim, env.alive, fetch=False)


class Cooking(ArenaScenario):
    """Cook soups to a recipe in a shared kitchen; see the module docstring."""

    name = "cooking"
    Params = CookingParams
    # One recipe and short cooking, or a new classic kitchen every level.
    difficulties = {"easy": {"num_ingredients": 1, "cook_time": 10}, "medium": {}, "hard": {"kitchen": "classic"}}
    State = CookingState
    default_num_agents = 2
    agent_range = (1, 4)
    default_max_steps = 400
    default_resolution = 64
    physics_terms = frozenset({"walls", "obstacles", "body_collisions", "drag"})
    info_keys = {"delivered": torch.int64, "wrong": torch.int64, "served": torch.int64}
    arena_half_extent = (HX, HY)
    overview_resolution = (180, 100)
    mixed_motive = False
    # Step budgets (env steps summed over worlds): 180 updates of 32 worlds x 32 decisions each, what three seeds
    # of every new task fit in one 3-hour session on 2 cores. The estimate for learning was rooms' for as many
    # 400-step episodes (1147 and 1035 updates): these are short runs, and a row below random is published as it is.
    training = {"budget": {"pixels": 184_320, "state": 184_320}}

    def setup(self):
        N, p = self.num_agents, self.params
        if p.recipe_view == "one" and N != 2:
            raise ValueError(f"recipe_view='one' needs num_agents=2 (the renderer hides an object from one view "
                             f"only), got num_agents={N}")
        self.setup_arena({"agents": numbered("agent", N)}, state_dim=6 + ITEM_CODES + 16 * G + RECIPES + 10 * (N - 1),
                         radius=AGENT_RADIUS, max_speed=2.0, extra_actions=("interact",))
        d = self.device
        self.centres = cell_centres().to(d)
        self.classic_cells, self.classic_starts = (t.to(d) for t in classic_tables())
        self.candidates = ring_candidates().to(d)
        self.earlier = torch.ones(N, N, dtype=torch.bool, device=d).tril(-1)  # [i, j]: j acts before i
        self.tile_colors = torch.tensor(TILE_COLORS)
        self.item_colors, self.item_scales = torch.tensor(ITEM_COLORS), torch.tensor(ITEM_SCALES)
        self.sees_recipe = torch.ones(N, device=d) if p.recipe_view == "all" else (torch.arange(N, device=d) == 0)

    # ------------------------------------------------------------------ state
    def _fresh(self, cells, pos, yaw, recipe):
        W, N = self.num_worlds, self.num_agents
        zeros = torch.zeros(W, G, dtype=torch.int64)
        return self.at_rest(pos, yaw, cells=cells, item=zeros, pot=torch.zeros(W, G, 2, dtype=torch.int64),
                            cook=zeros, held=torch.zeros(W, N, dtype=torch.int64), recipe=recipe,
                            served=torch.zeros(W, dtype=torch.int64))

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        cells = self.classic_cells[0].expand(W, G).clone()
        return self._fresh(cells, self.centres[self.classic_starts[0, 0]].expand(W, N, 2).clone(), torch.zeros(W, N),
                           torch.zeros(W, dtype=torch.int64))

    def state_bounds(self):
        recipes = 3 if self.params.num_ingredients == 2 else 0
        return {**super().state_bounds(), "cells": (0, TOMATO_BOX), "item": (0, SOUP + 3), "pot": (0, 3),
                "cook": (0, self.params.cook_time), "held": (0, SOUP + 3), "recipe": (0, recipes),
                "served": (0, MAX_COUNT)}

    def check_state(self, state):
        cells, pot = state["cells"], state["pot"]
        if bool(((state["item"] != EMPTY) & (cells != COUNTER)).any()):
            raise ValueError("state['item'] may hold items only on plain counters (state['cells'] == COUNTER)")
        if bool(((pot.sum(-1) > 0) & (cells != POT)).any()) or bool((pot.sum(-1) > 3).any()):
            raise ValueError("state['pot'] may hold at most 3 ingredients, and only in pots (state['cells'] == POT)")
        if bool(((state["cook"] > 0) & (pot.sum(-1) < 3)).any()):
            raise ValueError("state['cook'] may count only in full pots (3 ingredients in state['pot'])")
        tomatoes = ((state["held"] == TOMATO).any() | (state["item"] == TOMATO).any() | (pot[..., 1] > 0).any()
                    | (cells == TOMATO_BOX).any())
        if self.params.num_ingredients == 1 and bool(tomatoes):
            raise ValueError("with num_ingredients=1 the state may hold no tomatoes nor tomato dispensers")

    def spawn_level(self, draws):
        W, N, p, d = self.num_worlds, self.num_agents, self.params, self.device
        if p.kitchen == "procedural":
            cells, starts = self._procedural(draws), None
        else:
            index = (draws.randint("kitchen", len(CLASSIC), (W,)).to(d) if p.kitchen == "classic"
                     else torch.full((W,), list(CLASSIC).index(p.kitchen), device=d))
            cells, starts = self.classic_cells[index], self.classic_starts[index]
        if p.num_ingredients == 1:
            cells = torch.where(cells == TOMATO_BOX, COUNTER, cells)
        # Agents on distinct floor cells: the classic start marks first, drawn cells for the others.
        score = draws.rand("spawn", (W, G)).to(d)
        free = cells == FLOOR
        if starts is not None:
            free = free & ~torch.zeros_like(free).scatter(1, starts, True)
        drawn = torch.where(free, score, -1.0).topk(N, dim=1).indices  # [W, N]
        if starts is not None:
            drawn = torch.cat((starts[:, :N], drawn[:, :max(N - 2, 0)]), 1)
        yaw = (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi
        recipe = (draws.randint("recipe", RECIPES, (W,)) if p.num_ingredients == 2
                  else torch.zeros(W, dtype=torch.int64))
        return self._fresh(cells, self.centres[drawn], yaw, recipe)

    def _procedural(self, draws) -> torch.Tensor:
        """[W, G] cells of procedural kitchens: a ring of counters round a 7 x 3 floor whose middle row
        has an island counter at each of its inner 5 cells with probability 1/2 (the outer rows of the
        floor stay free, so every floor cell is reachable), and the six stations on distinct cells of
        the ring (not its corners), all of them next to the floor."""
        W, d = self.num_worlds, self.device
        row, col = torch.arange(G, device=d) // GW, torch.arange(G, device=d) % GW
        ring = (row == 0) | (row == GH - 1) | (col == 0) | (col == GW - 1)
        cells = torch.where(ring, COUNTER, FLOOR).expand(W, G).clone()
        islands = (draws.rand("islands", (W, GW - 4)) < 0.5).to(d)
        cells[:, 2 * GW + 2:2 * GW + GW - 2] = torch.where(islands, COUNTER, FLOOR)
        order = draws.rand("stations", (W, len(self.candidates))).to(d).argsort(-1)[:, :6]
        stations = torch.tensor([POT, POT, DISHES, SERVE, ONION_BOX, TOMATO_BOX], device=d).expand(W, 6)
        return cells.scatter(1, self.candidates[order], stations)

    # ------------------------------------------------------------------ rules
    def faced(self, state) -> torch.Tensor:
        """[W, A] int64: the cell REACH ahead of each agent's centre (-1: outside the kitchen)."""
        point = state.pos[:, :self.num_agents] + REACH * scenery.heading(state.yaw)
        col = ((point[..., 0] + HX) / CELL).floor().long()
        row = GH - 1 - ((point[..., 1] + HY) / CELL).floor().long()
        inside = (col >= 0) & (col < GW) & (row >= 0) & (row < GH)
        return torch.where(inside, row * GW + col, -1)

    def rules(self, before, moved, actions, alive, generator):
        W, N, p = self.num_worlds, self.num_agents, self.params
        full = before.pot.sum(-1) == 3
        cook = torch.where(full & (before.cook < p.cook_time), before.cook + 1, before.cook)
        interact = (actions[..., 2] > 0.5) if self.continuous else actions == INTERACT
        cell = self.faced(before)  # the counter it faced when it chose to act
        interact = interact & alive & (cell >= 0)
        # One actor per cell: an agent whose cell an earlier agent acts on does nothing.
        clash = (cell[:, :, None] == cell[:, None, :]) & interact[:, None, :] & self.earlier
        acts = interact & ~clash.any(-1)
        c = cell.clamp_min(0)
        kind, item, cooked = before.cells.gather(1, c), before.item.gather(1, c), cook.gather(1, c)
        pot = before.pot.gather(1, c[..., None].expand(-1, -1, 2))  # [W, N, 2]
        h = before.held
        ingredient = (h == ONION) | (h == TOMATO)
        done = (pot.sum(-1) == 3) & (cooked >= p.cook_time)
        take = acts & (h == EMPTY) & ((kind == ONION_BOX) | (kind == TOMATO_BOX))
        take_dish = acts & (h == EMPTY) & (kind == DISHES)
        add = acts & ingredient & (kind == POT) & (pot.sum(-1) < 3)
        plate = acts & (h == DISH) & (kind == POT) & done
        serve = acts & (h >= SOUP) & (kind == SERVE)
        place = acts & (h != EMPTY) & (kind == COUNTER) & (item == EMPTY)
        pick = acts & (h == EMPTY) & (kind == COUNTER) & (item != EMPTY)
        held = torch.where(take, ONION + kind - ONION_BOX, h)
        held = torch.where(take_dish, DISH, held)
        held = torch.where(plate, SOUP + pot[..., 1], held)
        held = torch.where(pick, item, held)
        held = torch.where(add | serve | place, EMPTY, held)
        # The cells acted on change; each has at most one actor (index G: a column no cell uses).
        new_pot = torch.where(plate[..., None], 0, pot + torch.nn.functional.one_hot(
            (h - ONION).clamp(0, 1), 2) * add[..., None])
        touched = torch.where(add | plate, c, G)
        pot_all = torch.cat((before.pot, before.pot[:, :1]), 1).scatter(1, touched[..., None].expand(-1, -1, 2),
                                                                          new_pot)[:, :G]
        cook = torch.cat((cook, cook[:, :1]), 1).scatter(1, touched, torch.where(plate, 0, cooked))[:, :G]
        on_counter = torch.where(place, h, EMPTY)
        item_all = torch.cat((before.item, before.item[:, :1]), 1).scatter(1, torch.where(place | pick, c, G),
                                                                            on_counter)[:, :G]
        correct = serve & (h - SOUP == before.recipe[:, None])
        delivered = correct.sum(-1)
        reward = (p.delivery_reward * delivered.to(torch.float32))[:, None].expand(W, N)
        served = before.served + delivered
        state = dataclasses.replace(moved, item=item_all, pot=pot_all, cook=cook, held=held, served=served)
        info = {"delivered": delivered, "wrong": (serve & ~correct).sum(-1), "served": served}
        return state, reward, torch.zeros_like(alive), info

    def obstacles(self, state):
        solid = (state.cells != FLOOR)[..., None]
        centre = torch.where(solid, self.centres, FAR_AWAY)
        return planar.Obstacles(centre, torch.full_like(centre, CELL / 2), torch.zeros_like(centre[..., 0]))

    # ------------------------------------------------------------------ what is drawn
    def props(self):
        centres = lambda s: self.centres.expand(s.cells.shape[0], G, 2)  # noqa: E731
        station = lambda s: (s.cells != FLOOR) & (s.cells != COUNTER)  # noqa: E731
        return [
            Prop("counters", "box", count=G, position=centres, height=COUNTER_HEIGHT / 2,
                 active=lambda s: s.cells != FLOOR,
                 scale=(CELL, CELL, COUNTER_HEIGHT), color=COUNTER_COLOR, moves=False, role="wall"),
            Prop("stations", "box", count=G, position=centres, height=COUNTER_HEIGHT + 0.01, active=station,
                 scale=(0.8 * CELL, 0.8 * CELL, 0.03), color=lambda s: self.tile_colors[s.cells.cpu()], moves=False),
            Prop("pots", mr.cylinder(segments=12), count=G, position=centres, height=COUNTER_HEIGHT + 0.08,
                 active=lambda s: s.cells == POT, scale=(0.4, 0.4, 0.16), color=POT_COLOR, moves=False),
            Prop("items", "sphere", count=G, position=centres, height=COUNTER_HEIGHT + 0.12, active=self._cell_shows,
                 scale=self._cell_scale, color=self._cell_color),
            Prop("held", "sphere", count=self.num_agents, position=self._held_position, height=0.32,
                 active=lambda s: s.held != EMPTY, scale=lambda s: self.item_scales[s.held.cpu()],
                 color=lambda s: self.item_colors[s.held.cpu()]),
            Prop("recipe", "sphere", count=3, position=self._recipe_position, height=0.75, scale=(0.14,) * 3,
                 color=lambda s: self.item_colors[recipe_balls(s.recipe).cpu()], moves=False,
                 hidden_from=1 if self.params.recipe_view == "one" else None),
        ]

    def _cell_shows(self, s) -> torch.Tensor:
        return (s.item != EMPTY) | (s.pot.sum(-1) > 0)

    def _cell_scale(self, s) -> torch.Tensor:
        """Items as their code's size; a pot's soup grows with its ingredients."""
        filled = s.pot.sum(-1).cpu()
        soup = (filled.to(torch.float32) / 3 * 0.3)[..., None].expand(-1, -1, 3)
        return torch.where((filled > 0)[..., None], soup, self.item_scales[s.item.cpu()])

    def _cell_color(self, s) -> torch.Tensor:
        """Items as their code's colour; a pot's soup the mix of its ingredients, orange once cooked."""
        pot, filled = s.pot.cpu().to(torch.float32), s.pot.sum(-1).cpu()
        mix = (pot[..., :1] * self.item_colors[ONION] + pot[..., 1:] * self.item_colors[TOMATO]) / filled.clamp_min(
            1)[..., None]
        done = ((filled == 3) & (s.cook.cpu() >= self.params.cook_time))[..., None]
        mix = torch.where(done, torch.tensor(DONE_COLOR), mix)
        return torch.where((filled > 0)[..., None], mix, self.item_colors[s.item.cpu()])

    def _held_position(self, s) -> torch.Tensor:
        return s.pos[:, :self.num_agents] + (AGENT_RADIUS + 0.1) * scenery.heading(s.yaw)

    def _recipe_position(self, s) -> torch.Tensor:
        serve = (s.cells == SERVE).to(torch.int64).argmax(1)  # the first delivery point
        offsets = torch.tensor([[-0.16, 0.0], [0.0, 0.0], [0.16, 0.0]], device=s.cells.device)
        return self.centres[serve][:, None] + offsets

    # ------------------------------------------------------------------ observation
    def observation(self, state, alive):
        W, N, f = self.num_worlds, self.num_agents, state.pos.dtype
        stations = torch.nn.functional.one_hot(state.cells, STATION_TYPES + 1)[..., 1:].to(f)
        items = torch.nn.functional.one_hot(state.item, ITEM_CODES)[..., 1:].to(f)
        progress = (state.cook.to(f) / self.params.cook_time)[..., None]
        grid = torch.cat((stations, items, state.pot.to(f) / 3, progress), -1).reshape(W, 1, -1).expand(W, N, -1)
        held = torch.nn.functional.one_hot(state.held, ITEM_CODES).to(f)
        recipe = torch.nn.functional.one_hot(state.recipe, RECIPES).to(f)[:, None] * self.sees_recipe[:, None].to(f)
        others = torch.cat((self.others_obs(state), held[:, self.others]), -1).reshape(W, N, -1)
        return torch.cat((self.own_obs(state), held, grid, recipe, others), -1)

    # ------------------------------------------------------------------ the scripted cooks
    def heuristic(self, state, alive):
        """A team of scripted cooks reading the state: each holding a soup delivers it; each holding a dish
        goes to a cooked pot (or a cooking one, and waits); each holding an ingredient puts it into the
        nearest filling pot that the recipe needs it in; the empty-handed share out, in agent order, the
        dishes the cooking pots need, then the ingredients the filling pots lack. Paths are shortest paths
        over the floor cells (breadth-first, other agents' cells blocked); an agent interacts when it
        faces a cell it is heading for."""
        return self.cook(state, alive)

    def cook(self, state, alive, fetch: bool = True, plate: bool = True) -> torch.Tensor:
        """The heuristic's actions; fetch=False: never fetches ingredients (idles instead), plate=False:
        never fetches dishes, plates or delivers."""
        W, N, p = self.num_worlds, self.num_agents, self.params
        h, cells = state.held, state.cells
        pot_sum = state.pot.sum(-1)
        is_pot = cells == POT
        cooking = is_pot & (pot_sum == 3)
        done = cooking & (state.cook >= p.cook_time)
        filling = is_pot & (pot_sum < 3)
        want = torch.stack((3 - state.recipe, state.recipe), -1)[:, None]  # [W, 1, 2] onions, tomatoes
        lack = (want - state.pot).clamp_min(0) * filling[..., None]  # [W, G, 2]
        spoiled = filling & (state.pot > want).any(-1)  # a wrong mix: filled up with onions, to clear it
        lack = torch.where(spoiled[..., None], torch.stack((3 - pot_sum, 0 * pot_sum), -1), lack)
        need = lack.sum(1) - torch.stack(((h == ONION).sum(-1), (h == TOMATO).sum(-1)), -1)  # [W, 2]
        # Dishes: first those the cooking pots need, then (after the ingredients) those of the filling ones.
        holders = (h == DISH).sum(-1)
        urgent = (cooking.sum(-1) - holders).clamp_min(0) * plate  # [W]; none for a cook that never plates
        later = ((cooking | filling & (pot_sum > 0)).sum(-1) - holders - urgent).clamp_min(0) * plate
        need = need.clamp_min(0)
        # The empty-handed share the tasks out in agent order.
        empty = (h == EMPTY) & alive
        rank = empty.cumsum(-1) - 1
        bounds = torch.stack((urgent, urgent + need[:, 0], urgent + need[:, 0] + need[:, 1],
                              urgent + need[:, 0] + need[:, 1] + later), -1)[:, None]  # [W, 1, 4]
        task = (rank[..., None] >= bounds).sum(-1)  # 0 dish, 1 onion, 2 tomato, 3 dish, 4 nothing
        task = torch.where(task == 3, 0, torch.where(task == 4, 3, task))
        if not fetch:
            task = torch.where((task == 1) | (task == 2), 3, task)
        # The cells each agent heads for (to face them).
        kind = (h - ONION).clamp(0, 1)  # 0 onion, 1 tomato while it holds one
        needs_it = lack.transpose(1, 2).gather(1, kind[..., None].expand(-1, -1, G)) > 0  # [W, N, G]
        any_pot = filling[:, None].expand(W, N, G)
        for_ingredient = torch.where(needs_it.any(-1, keepdim=True), needs_it & filling[:, None], any_pot)
        for_dish = torch.where(done.any(-1, keepdim=True), done, cooking)[:, None].expand(W, N, G)
        goal = torch.zeros(W, N, G, dtype=torch.bool, device=self.device)
        goal = torch.where(((h == ONION) | (h == TOMATO))[..., None], for_ingredient, goal)
        goal = torch.where((h == DISH)[..., None], for_dish if plate else goal, goal)
        goal = torch.where((h >= SOUP)[..., None], (cells == SERVE)[:, None] if plate else goal, goal)
        empty_goal = torch.stack(((cells == DISHES), (cells == ONION_BOX), (cells == TOMATO_BOX),
                                  torch.zeros_like(cells, dtype=torch.bool)), 1)  # [W, 4, G]
        empty_goal = empty_goal.gather(1, task[..., None].expand(-1, -1, G))
        goal = torch.where(empty[..., None], empty_goal, goal)
        # An agent with nothing to do (or no way to its goal) steps aside, onto a floor cell next to no
        # station, out of the others' way.
        station = ((cells != FLOOR) & (cells != COUNTER)).reshape(W, GH, GW).float()
        aside = (cells == FLOOR) & (neighbours(station, 0.0).reshape(W, G) == 0)
        return self.walk_to(state, alive, goal, stand=aside[:, None].expand(W, N, G))

    def walk_to(self, state, alive, goal: torch.Tensor, stand: torch.Tensor | None = None) -> torch.Tensor:
        """Actions that take each agent along a shortest path over the floor to a cell next to one of its
        goal cells (goal [W, N, G] bool), turn it to face that cell and interact; or, without a goal, to
        one of its `stand` cells ([W, N, G] bool), where it stops (noop with neither)."""
        W, N = self.num_worlds, self.num_agents
        pos = state.pos[:, :N]
        col = ((pos[..., 0] + HX) / CELL).floor().long().clamp(0, GW - 1)
        row = (GH - 1 - ((pos[..., 1] + HY) / CELL).floor().long()).clamp(0, GH - 1)
        here = row * GW + col  # [W, N]
        occupied = torch.nn.functional.one_hot(here, G).bool() & alive[..., None]  # [W, N, G]
        # Each agent gives way to the agents before it: their cells are walls on its paths.
        blocked = (occupied[:, None] & self.earlier[None, :, :, None]).any(2)  # [W, N, G]
        open_ = ((state.cells == FLOOR)[:, None] & ~blocked).reshape(W, N, GH, GW)
        goal_grid = goal.reshape(W, N, GH, GW)
        inf = torch.tensor(math.inf, device=self.device)
        # Distances to a cell next to a goal (0 there), or else to a stand cell (STAND_COST there): an
        # agent whose goals are out of reach steps aside.
        dist = torch.where(open_ & (neighbours(goal_grid.float(), 0.0) > 0), 0.0, inf)
        if stand is not None:
            dist = torch.minimum(dist, torch.where(open_ & stand.reshape(W, N, GH, GW), STAND_COST, inf))
        for _ in range(G):
            relaxed = torch.where(open_, torch.minimum(dist, neighbours(dist, math.inf, torch.minimum) + 1), inf)
            if torch.equal(relaxed, dist):
                break
            dist = relaxed
        steps = torch.stack(shifted(dist, math.inf), -1).reshape(W, N, G, 4)  # up, down, left, right of each cell
        options = steps.gather(2, here[..., None, None].expand(-1, -1, 1, 4))[:, :, 0]  # [W, N, 4]
        goals = torch.stack(shifted(goal_grid.float(), 0.0), -1).reshape(W, N, G, 4)
        goal_side = goals.gather(2, here[..., None, None].expand(-1, -1, 1, 4))[:, :, 0] > 0
        step = torch.tensor([-GW, GW, -1, 1], device=self.device)
        now = dist.reshape(W, N, G).gather(2, here[..., None])[..., 0]
        at_goal = (now == 0) & goal_side.any(-1)
        direction = torch.where(at_goal, goal_side.to(torch.float32).argmax(-1), options.argmin(-1))
        target_cell = (here + step[direction]).clamp(0, G - 1)
        moving = at_goal | (options.amin(-1) < now)
        target = torch.where(moving[..., None], self.centres[target_cell], pos)
        action = self.steer_to(state, target)
        faced = self.faced(state)
        facing_goal = (faced >= 0) & goal.gather(2, faced.clamp_min(0)[..., None])[..., 0]
        if self.continuous:
            return torch.cat((torch.where(facing_goal[..., None], 0.0, action), facing_goal[..., None].float()), -1)
        return torch.where(facing_goal, INTERACT, action)

    # ------------------------------------------------------------------ declarations
    card = Card(
        text="Collaborative cooking after Overcooked: ingredients go from dispensers into a pot, cook, are "
             "plated on a dish and delivered; only a soup of the current recipe pays the team. Five classic "
             "kitchens and procedural ones; the recipe may be shown to one agent only (`recipe_view=\"one\"`), "
             "so that the other must learn it from its partner.",
        reward="shared: delivery_reward (20) to every agent per soup of the episode's recipe delivered; any other "
               "soup pays nothing",
        episode_end="never terminates; truncated at max_steps",
        continuous=egomotion.CONTINUOUS_MEANINGS + (
            "interact (> 0.5: take, put, cook, plate or deliver at the counter 0.45 m ahead)",),
        info={"delivered": "soups of the recipe delivered in this step",
              "wrong": "other soups delivered in this step",
              "served": "soups of the recipe delivered this episode"})
    bots = {"fetcher": Bot(fetcher.__doc__, script=fetcher), "plater": Bot(plater.__doc__, script=plater),
            "slow": Bot.lazy(0.5), "noisy0.1": Bot.noisy(0.1, population="train")}
    heldout = (
        HeldOut("with_fetcher", "a focal cook whose partner only fetches ingredients: it must plate and deliver",
                num_agents=2, focal=("agent_0",), bots_by_role={"agents": ("fetcher",)}),
        HeldOut("with_plater", "a focal cook whose partner only plates and delivers: it must fetch every ingredient",
                num_agents=2, focal=("agent_0",), bots_by_role={"agents": ("plater",)}),
        HeldOut("blind_with_fetcher", "the focal cook does not see the recipe; its partner who does only fetches",
                num_agents=2, focal=("agent_1",), bots_by_role={"agents": ("fetcher",)},
                params={"recipe_view": "one"}),
        HeldOut("pair_with_slow_partner", "two focal cooks with a third that idles half the time", num_agents=3,
                focal=("agent_0", "agent_1"), bots_by_role={"agents": ("slow",)}),
    )


def shifted(grid: torch.Tensor, fill: float) -> tuple:
    """(up, down, left, right) neighbour values of each cell of grid [..., GH, GW] (`fill` outside):
    up[r, c] = grid[r - 1, c], and so on."""
    padded = torch.nn.functional.pad(grid, (1, 1, 1, 1), value=fill)
    return padded[..., :-2, 1:-1], padded[..., 2:, 1:-1], padded[..., 1:-1, :-2], padded[..., 1:-1, 2:]


def neighbours(grid: torch.Tensor, fill: float, combine=torch.maximum) -> torch.Tensor:
    """The four neighbours of each cell combined (maximum by default)."""
    up, down, left, right = shifted(grid, fill)
    return combine(combine(up, down), combine(left, right))
