"""Foraging: agents collect respawning items, seen through egocentric cameras.

N agents (default 3) drive around a walled arena picking up floating yellow spheres.
Every agent sees the arena through its own camera mounted on its body.

* Arena: |x|, |y| <= 1.5 m, walls and floor are static geometry.
* Agents: blue capsules of radius 0.15 m, mass 1, physics from ``envs/planar.py`` with
  the terms walls + body_collisions + drag (MPE-like damping 0.25 per 0.1 s step), as
  in ``spread``. The camera sits at 0.4 m, pitched 0.2 rad down; a dark "nose" box
  shows other agents which way a body faces.
* Reset: agents in distinct random cells of a 4 x 4 grid of the arena (no overlaps),
  random yaw; items at random places clear of the agents (as when respawning).
* Items: ``num_items`` (default 2 x num_agents) spheres of radius 0.1 m; they are not
  physics bodies (agents drive through them). An agent whose body touches an available
  item (centre distance < 0.25 m, after the physics step) collects it; if several
  agents touch the same item in one step the closest one (lowest index on a tie) gets
  it. A collected item disappears and respawns ``respawn_delay`` steps later (default
  10: collected in step t, it is back in the obs of step t + respawn_delay) at a random
  place at least 0.35 m from every agent (of 8 random candidates the first clear one;
  the last one if none is).
* Actions, egocentric, as in ``spread``: discrete 5: 0 noop, 1 forward, 2 turn left,
  3 turn right, 4 backward; continuous 2: (thrust in [-1, 1] along the heading, turn
  rate in [-1, 1]). Movement as in envs/egomotion.py (shared by the arena envs).
* Reward, per agent: ``item_reward`` (default 1) per item it collected in the step.
* action_mask: every action is always valid (all True).
* Episode: never terminates; truncated after ``max_steps`` = 200.
* State obs (6 + 3 I + 2 (N - 1)): own position (2), velocity (2), cos/sin yaw (2);
  item positions relative to the agent (2 each, zeros while the item is away) and their
  availability (1 each); the other agents' positions relative to the agent (2 each, in
  agent-index order skipping itself). World frame.
* info: ``"collected"`` int64 [W] items collected in the step, ``"team_score"`` float32
  [W] the team's total reward of the episode so far (sum over agents and steps).
"""
from __future__ import annotations

import dataclasses
import math

import torch

import marl_render as mr
from marl_render.util.validation import COUNT_LIMIT, FLOAT32_MAX, positive_int, reward_weight

from . import egomotion, scenery
from .arena import ArenaScenario, ArenaState, Prop, numbered, wander
from .levels import Draws, GeneratorDraws
from .roster import Bot, Card, HeldOut

ARENA = 1.5  # half extent (m)
SPAWN = 1.3  # items spawn in |x|, |y| <= SPAWN
SPAWN_GRID = 4  # agents spawn in distinct cells of a SPAWN_GRID x SPAWN_GRID grid (no overlaps)
AGENT_RADIUS = 0.15
ITEM_RADIUS = 0.1
ITEM_HEIGHT = 0.15  # centre height of the floating spheres
ITEM_COLOR = (0.95, 0.80, 0.15)
REACH = AGENT_RADIUS + ITEM_RADIUS  # an agent touches an item while their centres are closer
RESPAWN_CLEARANCE = REACH + 0.1  # items respawn at least this far from every agent
RESPAWN_CANDIDATES = 8


@dataclasses.dataclass(frozen=True)
class ForageParams:
    num_items: int | None = None  # 1 to 32; None: 2 x num_agents (at most 32)
    respawn_delay: int = 10  # steps before a collected item comes back
    item_reward: float = 1.0  # to the agent that collects an item

    def __post_init__(self):
        if self.num_items is not None and positive_int("num_items", self.num_items) > 32:
            raise ValueError(f"num_items must be an int in [1, 32], got {self.num_items}")
        positive_int("respawn_delay", self.respawn_delay, maximum=COUNT_LIMIT)
        reward_weight("item_reward", self.item_reward)


@dataclasses.dataclass(frozen=True)
class ForageState(ArenaState):
    items: torch.Tensor  # [W, I, 2] item centres (m), also while away
    item_timer: torch.Tensor  # [W, I] int64: steps until the item is back; 0: available
    team_score: torch.Tensor  # [W] float32: the team's reward in this episode so far


class Forage(ArenaScenario):
    """Collect respawning items; see the module docstring."""

    name = "forage"
    Params = ForageParams
    # Fewer items that come back later: more searching per reward.
    difficulties = {"easy": {"num_items": 12, "respawn_delay": 5}, "medium": {},
                    "hard": {"num_items": 2, "respawn_delay": 30}}
    State = ForageState
    default_num_agents = 3
    agent_range = (1, 12)
    default_max_steps = 200
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"collected": torch.int64, "team_score": torch.float32}
    arena_half_extent = (ARENA, ARENA)
    bots = {"noisy0.2": Bot.noisy(0.2, population="train"),
            "wanderer": Bot("drives round a circle, ignoring items", script=wander),
            "lazy0.5": Bot.lazy(0.5), "noisy0.5": Bot.noisy(0.5)}
    heldout = (
        HeldOut("two_with_wanderer", "two focal foragers with one that wanders", 3, tuple(numbered("agent", 2)),
                {"agents": ("wanderer",)}),
        HeldOut("one_among_noisy", "one focal forager among two that act at random half the time", 3, ("agent_0",),
                {"agents": ("noisy0.5", "lazy0.5")}),
        HeldOut("two_with_lazy", "two focal foragers with one that idles half the time", 3,
                tuple(numbered("agent", 2)), {"agents": ("lazy0.5",)}),
    )
    card = Card(reward="per agent: +item_reward (1) per item it collects",
                episode_end="never terminates; truncated at max_steps", continuous=egomotion.CONTINUOUS_MEANINGS,
                info={"collected": "items (forage) or apples (commons) collected in this step",
                      "team_score": "the team's total reward of the episode so far (sum over agents and steps)"})
    training = {"budget": {"pixels": 179_200, "state": 1_013_760}}  # env steps of the published runs

    def setup(self):
        N = self.num_agents
        self.num_items = min(2 * N, 32) if self.params.num_items is None else self.params.num_items
        self.setup_arena({"agents": numbered("agent", N)}, state_dim=6 + 3 * self.num_items + 2 * (N - 1),
                         radius=AGENT_RADIUS, max_speed=2.0)
        self._agent_index = torch.arange(N, device=self.device)

    def initial_state(self):
        W, N, I = self.num_worlds, self.num_agents, self.num_items  # noqa: E741 (I: items, the shape letter)
        return self.at_rest(torch.zeros(W, N, 2), torch.zeros(W, N), items=torch.zeros(W, I, 2),
                            item_timer=torch.zeros(W, I, dtype=torch.int64), team_score=torch.zeros(W))

    def props(self):
        return [Prop("items", mr.sphere(segments=10, rings=5), count=self.num_items, position="items",
                     height=ITEM_HEIGHT, active=item_available, scale=(2 * ITEM_RADIUS,) * 3, color=ITEM_COLOR)]

    def _item_spawn(self, agent_pos: torch.Tensor, draws: Draws) -> torch.Tensor:
        """Random item positions [W, I, 2] clear of agent_pos [W, N, 2] (at resets and respawns)."""
        W, I, M = self.num_worlds, self.num_items, RESPAWN_CANDIDATES  # noqa: E741 (I: items, the shape letter)
        candidates = ((draws.rand("items", (W, I * M, 2)) * 2 - 1) * SPAWN).to(self.device)
        clear = (torch.cdist(candidates, agent_pos) > RESPAWN_CLEARANCE).all(-1).reshape(W, I, M)
        clear[..., -1] = True  # fallback: the last candidate
        pick = clear.to(torch.uint8).argmax(-1)  # the first clear candidate
        return candidates.reshape(W, I, M, 2).gather(2, pick[..., None, None].expand(W, I, 1, 2)).squeeze(2)

    def state_bounds(self):
        return {**super().state_bounds(), "items": self.inside_walls(), "item_timer": (0, self.params.respawn_delay),
                "team_score": (0.0, FLOAT32_MAX)}  # a sum of rewards >= 0, growing while a world keeps stepping

    def spawn_level(self, draws):
        W, N = self.num_worlds, self.num_agents
        pos = scenery.cell_spawn(draws, W, torch.full((N,), AGENT_RADIUS + 0.05), SPAWN_GRID, ARENA).to(self.device)
        yaw = (draws.rand("yaw", (W, N)) * 2 - 1) * math.pi
        return self.at_rest(pos, yaw, items=self._item_spawn(pos, draws),
                            item_timer=torch.zeros(W, self.num_items, dtype=torch.int64), team_score=torch.zeros(W))

    def rules(self, before, moved, actions, alive, generator):
        # Items away count down; those reaching 0 come back somewhere clear of the agents.
        timer = (before.item_timer - 1).clamp_min(0)
        back = (before.item_timer > 0) & (timer == 0)
        items = torch.where(back[..., None], self._item_spawn(moved.pos, GeneratorDraws(generator)), before.items)
        # Collection: the closest live agent touching an available item takes it.
        dist = torch.cdist(moved.pos, items)  # [W, N, I]
        touching = (dist < REACH) & (timer == 0)[:, None, :] & alive[:, :, None]
        collected = touching.any(1)  # [W, I]
        taker = torch.where(touching, dist, torch.full_like(dist, math.inf)).argmin(1)  # [W, I]
        got = (taker[:, None, :] == self._agent_index[None, :, None]) & collected[:, None, :]  # [W, N, I]
        reward = self.params.item_reward * got.sum(-1).to(torch.float32)
        timer = torch.where(collected, torch.full_like(timer, self.params.respawn_delay), timer)
        team_score = before.team_score + reward.sum(-1)
        state = dataclasses.replace(moved, items=items, item_timer=timer, team_score=team_score)
        info = {"collected": collected.sum(-1), "team_score": team_score.clone()}
        return state, reward, torch.zeros_like(alive), info

    def observation(self, state, alive):
        W, N = self.num_worlds, self.num_agents
        available = item_available(state)[:, None, :, None].to(state.pos.dtype)  # [W, 1, I, 1]
        return torch.cat((self.own_obs(state), (self.relative(state, state.items) * available).reshape(W, N, -1),
                          available[..., 0].expand(W, N, -1), self.others_obs(state).reshape(W, N, -1)), -1)

    def heuristic(self, state, alive):
        """Each agent drives to the nearest available item (or holds still when none is)."""
        N = self.num_agents
        dist = torch.cdist(state.pos[:, :N], state.items)  # [W, N, I]
        dist = torch.where(item_available(state)[:, None, :], dist, torch.full_like(dist, math.inf))
        nearest = dist.argmin(-1)  # [W, N]
        target = state.items.gather(1, nearest[..., None].expand(-1, -1, 2))
        none = torch.isinf(dist.amin(-1))[..., None]
        return self.steer_to(state, torch.where(none, state.pos[:, :N], target))


def item_available(state: ForageState) -> torch.Tensor:
    """bool [W, I]: items that can be collected (and are drawn)."""
    return state.item_timer == 0
