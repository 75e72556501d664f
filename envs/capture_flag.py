"""Two-team capture the flag for many agents (16 to 64 per world) with egocentric cameras.

* Arena: |x| <= 3 m, |y| <= 4 m, walled. Red's half is y < 0, blue's y > 0. Each team's base
  is the point (0, -3) (red) / (0, 3) (blue), drawn as a light pad of radius ``BASE_RADIUS``
  (0.5 m) in the team's colour; the team's flag (a tall thin box in its colour) stands there.
* Agents: ``num_agents`` (even, default 16, 4 to 64): red then blue, names ``red_i`` and
  ``blue_i``, groups ``{"red": [...], "blue": [...]}``. Capsule bodies of radius 0.15 m, mass 1,
  physics terms walls + body_collisions + drag (envs/planar.py), speeds at most 2 m/s.
* Reset: every agent gets its own random cell of an 8 x 5 grid over its team's half (clear of the
  midline by 0.3 m and of the cell's borders), facing the other half within +-45 degrees. Both
  flags at home.
* Actions, egocentric, as in ``spread``: discrete 5: 0 noop, 1 forward, 2 turn left,
  3 turn right, 4 backward; continuous 2: (thrust in [-1, 1] along the heading, turn rate).
* Rules, in this order, after the bodies moved. Two agents touch while their bodies' gap is below
  ``REACH`` (0.05 m); an agent touches a flag at home while its centre is within its radius +
  ``REACH`` of the flag's base point.
  1. Tag: an agent touching an opponent while in the opponent's half (the sign of its y) is
     tagged: it goes back to its home slot (a fixed place behind its base, two rows across
     the arena), still, and drops the flag it carries, which returns home.
  2. Capture: an agent carrying the enemy flag within ``BASE_RADIUS`` of its own base scores a
     capture; the flag returns home. Whether its own flag is home does not matter.
  3. Pick-up: a flag at home touched by opposing agents (not tagged in this step) is picked up
     by the closest; it then follows its carrier (drawn just behind it) until rule 1 or 2.
* Reward: shared per team and zero-sum: ``capture_reward`` (default 1) to every agent of a
  team per capture it scores in the step, minus the same per capture of the other team.
  Optional shaping (``shaping`` >= 0, default 0: off; not zero-sum): each team also gets
  ``shaping x`` the progress it made in the step towards its next capture: the decrease of
  (its nearest agent's distance to the enemy flag at home + the distance between the bases)
  or, while it carries the enemy flag, of the carrier's distance to its own base. Tags count
  (a tagged carrier or attacker loses the progress the tag undoes, so running into defenders
  does not pay); in a step where the team captures, only its movement counts (the restart
  after a capture is not a loss).
* Episode: truncated after ``max_steps`` = 200; with ``captures_to_win`` > 0 (default 0: off)
  it terminates (every agent) once a team has scored that many captures.
* action_mask: every action is always valid (all True).
* State obs (15 + 2 K_mates + 2 K_opps, with K_mates = min(k_nearest, team size - 1) and
  K_opps = min(k_nearest, team size); ``k_nearest`` default 4): own position (2), velocity (2),
  cos/sin yaw (2); own base relative (2); own flag relative (2) and carried (1); enemy flag
  relative (2) and carried (1); whether the agent carries it (1); the K_mates nearest teammates
  then the K_opps nearest opponents relative to the agent (2 each, nearest first). World frame.
* info: ``"captures_red"``, ``"captures_blue"`` int64 [W] captures in this step, ``"tags"`` int64
  [W] agents tagged in it, ``"flag_carried"`` int64 [W] flags carried after it (0 to 2).
"""
from __future__ import annotations

import dataclasses
import math

import torch

from marl_render.util.validation import COUNT_LIMIT, positive_int, reward_weight

from . import egomotion, scenery
from .arena import ArenaScenario, ArenaState, Prop, Static, numbered
from .roster import Bot, Card, HeldOut
from .scenario import MAX_COUNT

ARENA = (3.0, 4.0)  # half extents (m)
BASE_Y = 3.0  # bases at (0, -BASE_Y) red and (0, BASE_Y) blue
BASE_RADIUS = 0.5  # a carrier within this of its base captures (m)
RADIUS = 0.15
REACH = 0.05  # contact tolerance (m)
HOME_ROWS = (3.45, 3.8)  # |y| of the two rows of home slots (m)
SPAWN_GRID = (8, 5)  # columns, rows of each half's spawn grid
MIDLINE_GAP = 0.3  # spawn cells start this far from the midline (m)
FLAG_SIZE = (0.12, 0.12, 0.8)
FLAG_BEHIND = 0.22  # a carried flag is drawn this far behind its carrier's centre (m)
TEAMS = ("red", "blue")


@dataclasses.dataclass(frozen=True)
class CaptureFlagParams:
    capture_reward: float = 1.0  # to every agent of a team per capture it scores; minus it for the other team's
    captures_to_win: int = 0  # 0: the episode only truncates
    k_nearest: int = 4  # teammates / opponents in the state observation
    shaping: float = 0.0  # weight of the progress towards the next capture (0: off)

    def __post_init__(self):
        reward_weight("capture_reward", self.capture_reward)
        reward_weight("shaping", self.shaping, allow_zero=True)
        positive_int("captures_to_win", self.captures_to_win, minimum=0, maximum=COUNT_LIMIT)
        positive_int("k_nearest", self.k_nearest)


@dataclasses.dataclass(frozen=True)
class CaptureFlagState(ArenaState):
    carrier: torch.Tensor  # [W, 2] int64: agent carrying red's / blue's flag, -1: at home
    captures: torch.Tensor  # [W, 2] int64: red's / blue's captures in this episode


# Bot scripts (envs/roster.py): env -> actions of every agent of every world, [W, A].
def all_attack(env) -> torch.Tensor:
    """Every agent fetches the enemy flag and carries it home (or goes home while a teammate has it)."""
    s, state = env.scenario, env.sim
    enemy = 1 - s.team
    carried = (state.carrier[:, enemy] >= 0)[..., None]
    target = torch.where(carried, s.base[s.team].expand(env.num_worlds, -1, -1), s.flag_position(state)[:, enemy])
    return s.steer_to(state, target)


def all_defend(env) -> torch.Tensor:
    """Every agent guards the point 1 m in front of its own flag."""
    s, state = env.scenario, env.sim
    guard = s.base[s.team] - s.side[:, None] * torch.tensor([0.0, 1.0], device=env.device)
    return s.steer_to(state, guard.expand(env.num_worlds, -1, -1))


class CaptureFlag(ArenaScenario):
    """Red and blue capture each other's flag; see the module docstring."""

    name = "capture_flag"
    Params = CaptureFlagParams
    # Team sizes (num_agents is both teams): more agents to coordinate and to get past.
    difficulties = {"easy": {"num_agents": 4}, "medium": {}, "hard": {"num_agents": 32}}
    State = CaptureFlagState
    default_num_agents = 16
    agent_range = (4, 64)
    default_max_steps = 200
    default_resolution = 64
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"captures_red": torch.int64, "captures_blue": torch.int64, "tags": torch.int64,
                 "flag_carried": torch.int64}
    arena_half_extent = ARENA
    opponents = ("blue",)  # the reference evaluation: red plays the policy, blue random
    mixed_motive = True  # social outcomes in info, Melting Pot's random episode ends (envs/episodes.py)
    sides = ("red", "blue")  # cross-play: red policies (rows) against blue policies (columns)
    bots = {"noisy0.2": Bot.noisy(0.2, population="train"),
            "all_attack": Bot("fetches the enemy flag, never defends", script=all_attack),
            "all_defend": Bot("guards its own flag, never attacks", script=all_defend),
            "lazy0.5": Bot.lazy(0.5)}
    heldout = (
        HeldOut("red_vs_attackers", "focal red team against a team that only attacks or only defends", 16,
                tuple(numbered("red", 8)), {"blue": ("all_attack", "all_defend")}),
        HeldOut("blue_vs_defenders", "focal blue team against a team that only defends or idles half the time", 16,
                tuple(numbered("blue", 8)), {"red": ("all_defend", "lazy0.5")}),
        HeldOut("resident_red", "focal red team and half of blue, with four blue attackers", 16,
                (*numbered("red", 8), *numbered("blue", 4)), {"blue": ("all_attack",)}),
        # The same opponents at the reference trainer's 2 v 2 (docs/baselines): its runs' agent one-hot fixes
        # their team size, so without these capture_flag's trained actors would play no scenario.
        HeldOut("duel_red_vs_attackers", "a focal red pair against a pair that only attacks or only defends", 4,
                tuple(numbered("red", 2)), {"blue": ("all_attack", "all_defend")}),
        HeldOut("duel_blue_vs_defenders", "a focal blue pair against a pair that only defends or idles half the time",
                4, tuple(numbered("blue", 2)), {"red": ("all_defend", "lazy0.5")}),
        HeldOut("duel_red_with_lazy_teammate", "one focal red player with a teammate that idles half the time, "
                "against attackers", 4, ("red_0",), {"red": ("lazy0.5",), "blue": ("all_attack",)}),
    )
    card = Card(reward="shared per team, zero-sum: +capture_reward (1) to every agent of a team per capture it "
                       "scores, -capture_reward per capture of the other team; optional shaping by the progress "
                       "towards the next capture",
                episode_end="with captures_to_win > 0, every agent terminates once a team has that many captures; "
                            "truncated at the episode's end (random by default: mixed motive)",
                continuous=egomotion.CONTINUOUS_MEANINGS,
                info={"captures_red": "captures red scored in this step",
                      "captures_blue": "captures blue scored in this step",
                      "tags": "agents tagged in this step (commons: out for a while; capture_flag: sent home)",
                      "flag_carried": "flags carried after the step (0 to 2)"})
    training = {"budget": {"pixels": 951_296, "state": 966_656}}  # env steps of the published runs

    def setup(self):
        N = self.num_agents
        if N % 2:
            raise ValueError(f"num_agents must be even for capture_flag (two equal teams), got {N}")
        T = self.team_size = N // 2
        self.k_mates, self.k_opps = min(self.params.k_nearest, T - 1), min(self.params.k_nearest, T)
        self.setup_arena({team: numbered(team, T) for team in TEAMS}, radius=RADIUS, max_speed=2.0,
                         state_dim=15 + 2 * (self.k_mates + self.k_opps))
        d = self.device
        self.team = (torch.arange(N, device=d) >= T).long()  # [N] 0 red, 1 blue
        self.side = self.team * 2.0 - 1.0  # [N] the sign of y in the own half
        self.base = torch.tensor([[0.0, -BASE_Y], [0.0, BASE_Y]], device=d)  # [2, 2] per team
        self.same = self.team[:, None] == self.team[None, :]  # [N, N]
        # Home slots (where tagged agents go): two rows behind the team's base, over |x| <= 2.5 m.
        slot = torch.arange(N, device=d) % T
        cols = (T + 1) // 2
        x = (slot // 2).float() * (5.0 / max(cols - 1, 1)) - (2.5 if cols > 1 else 0.0)
        self.home = torch.stack((x, self.side * torch.tensor(HOME_ROWS, device=d)[slot % 2]), -1)  # [N, 2]
        self.attacker = slot < (T + 1) // 2  # [N] the heuristic's roles

    def tagged_out(self, state):
        """Nobody: a tagged agent is sent home at once and plays on from there (its peace is full)."""
        return torch.zeros_like(state.active[:, :self.num_agents])

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self.at_rest(torch.zeros(W, N, 2), torch.zeros(W, N), carrier=torch.full((W, 2), -1),
                            captures=torch.zeros(W, 2, dtype=torch.int64))

    def props(self):
        colors = [scenery.TEAM_COLORS[t] for t in TEAMS]
        pads = [[0.0, float(y), 0.005] for y in self.base[:, 1].tolist()]
        return [Static("bases", scenery.disc_mesh(16), position=pads, scale=[[2 * BASE_RADIUS] * 2 + [0.01]] * 2,
                       color=[[0.5 + 0.5 * c for c in color] for color in colors]),
                Prop("flags", "box", count=2, position=self.flag_position, height=FLAG_SIZE[2] / 2,
                     scale=FLAG_SIZE, color=colors)]

    def flag_position(self, state) -> torch.Tensor:
        """[W, 2, 2]: each flag at its base, or just behind its carrier."""
        carried = state.carrier >= 0
        who = state.carrier.clamp_min(0)
        behind = state.pos.gather(1, who[..., None].expand(-1, -1, 2)) - FLAG_BEHIND * scenery.heading(
            state.yaw.gather(1, who))
        return torch.where(carried[..., None], behind, self.base.expand_as(behind))

    def state_bounds(self):
        N, T = self.num_agents, self.team_size
        return {**super().state_bounds(), "carrier": ((-1, -1), (N - 1, T - 1)), "captures": (0, MAX_COUNT)}

    def check_state(self, state):
        red_flag = state["carrier"][:, 0]  # carried by blue agents (T .. N-1) only
        if bool(((red_flag >= 0) & (red_flag < self.team_size)).any()):
            raise ValueError(f"state['carrier'][:, 0] (red's flag) must be -1 or a blue agent in "
                             f"[{self.team_size}, {self.num_agents - 1}]: a team never carries its own flag")

    def spawn_level(self, draws):
        W, N, T = self.num_worlds, self.num_agents, self.team_size
        cols, rows = SPAWN_GRID
        cell = torch.tensor([2 * ARENA[0] / cols, (ARENA[1] - MIDLINE_GAP) / rows])
        order = draws.rand("cells", (W, 2, cols * rows)).argsort(-1)[..., :T].reshape(W, N)
        centre = (torch.stack((order % cols, order // cols), -1) + 0.5) * cell
        reach = cell / 2 - (RADIUS + 0.05)
        pos = centre + (draws.rand("offset", (W, N, 2)) * 2 - 1) * reach
        side = self.side.cpu()
        pos = torch.stack((pos[..., 0] - ARENA[0], side * (pos[..., 1] + MIDLINE_GAP)), -1)
        yaw = (self.team.cpu() * math.pi) + (draws.rand("yaw", (W, N)) * 2 - 1) * (math.pi / 4)
        return self.at_rest(pos, scenery.wrap_angle(yaw), carrier=torch.full((W, 2), -1),
                            captures=torch.zeros(W, 2, dtype=torch.int64))

    def rules(self, before, moved, actions, alive, generator):
        pos = moved.pos
        # 1. Tags: touching an opponent while in its half sends an agent home, dropping its flag.
        touch = torch.cdist(pos, pos) < 2 * RADIUS + REACH
        away = pos[..., 1] * self.side < 0  # [W, N] in the opponent's half
        tagged = (touch & ~self.same & alive[:, None, :]).any(-1) & away & alive
        pos = torch.where(tagged[..., None], self.home, pos)
        vel = torch.where(tagged[..., None], torch.zeros_like(moved.vel), moved.vel)
        carrier = before.carrier
        held = carrier >= 0
        dropped = held & tagged.gather(1, carrier.clamp_min(0))
        carrier = torch.where(dropped, -1, carrier)
        # 2. Captures: flag f is carried by team 1 - f, whose base is base[1 - f].
        held = carrier >= 0
        carrier_pos = pos.gather(1, carrier.clamp_min(0)[..., None].expand(-1, -1, 2))
        scored = held & ((carrier_pos - self.base.flip(0)).norm(dim=-1) < BASE_RADIUS)  # [W, 2] per flag
        carrier = torch.where(scored, -1, carrier)
        scores = scored.flip(1).long()  # [W, 2] per scoring team
        # 3. Pick-ups: the closest untagged opponent touching a flag at home takes it.
        to_flag = torch.cdist(pos, self.base.expand(pos.shape[0], 2, 2))  # [W, N, 2]
        can = (to_flag < RADIUS + REACH) & (self.team[:, None] != torch.arange(2, device=self.device))
        can = can & (alive & ~tagged)[..., None] & (carrier < 0)[:, None, :]
        closest = torch.where(can, to_flag, torch.full_like(to_flag, math.inf)).argmin(1)  # [W, 2]
        carrier = torch.where(can.any(1), closest, carrier)
        captures = before.captures + scores
        net = (scores - scores.flip(1)).float() * self.params.capture_reward  # [W, 2] per team
        reward = net[:, self.team]
        if self.params.shaping:
            # Tags and pick-ups count (a tag undoes progress: running into defenders must not pay);
            # a team that scored is credited its movement only, not the restart after the capture.
            after = torch.where(scores > 0, self.capture_progress(moved.pos, before.carrier, alive),
                                self.capture_progress(pos, carrier, alive))
            gain = after - self.capture_progress(before.pos, before.carrier, alive)
            gain = torch.nan_to_num(gain, nan=0.0, posinf=0.0, neginf=0.0)  # a team with nobody left: none
            reward = reward + self.params.shaping * gain[:, self.team]
        win = self.params.captures_to_win
        done = (captures >= win).any(-1) if win else torch.zeros_like(captures[:, 0], dtype=torch.bool)
        state = dataclasses.replace(moved, pos=pos, vel=vel, carrier=carrier, captures=captures)
        info = {"captures_red": scores[:, 0], "captures_blue": scores[:, 1], "tags": tagged.sum(-1),
                "flag_carried": (carrier >= 0).sum(-1)}
        return state, reward, done[:, None].expand_as(alive).clone(), info

    def capture_progress(self, pos, carrier, alive):
        """[W, 2] per team: minus the way left to its next capture (see the module docstring)."""
        pos = pos[:, :self.num_agents]
        to_enemy_flag = (pos[:, :, None] - self.base.flip(0)).norm(dim=-1)  # [W, N, 2 teams]
        member = (self.team[:, None] == torch.arange(2, device=self.device)) & alive[..., None]
        nearest = torch.where(member, to_enemy_flag, math.inf).amin(1)  # [W, 2]
        enemy_carrier = carrier.flip(1)  # [W, 2]: per team, who carries the flag it attacks
        carrier_pos = pos.gather(1, enemy_carrier.clamp_min(0)[..., None].expand(-1, -1, 2))
        to_home = (carrier_pos - self.base).norm(dim=-1)
        return -torch.where(enemy_carrier >= 0, to_home, nearest + 2 * BASE_Y)

    def nearest(self, state, alive):
        """Indices [W, N, K_mates] and [W, N, K_opps] of each agent's nearest teammates / opponents."""
        pos = state.pos[:, :self.num_agents]
        dist = torch.cdist(pos, pos)
        eye = torch.eye(self.num_agents, dtype=torch.bool, device=self.device)
        mates = torch.where(self.same & ~eye, dist, math.inf).topk(self.k_mates, -1, largest=False).indices
        opps = torch.where(~self.same, dist, math.inf).topk(self.k_opps, -1, largest=False).indices
        return mates, opps

    def observation(self, state, alive):
        W, N = self.num_worlds, self.num_agents
        pos = state.pos[:, :N]
        flags = self.relative(state, self.flag_position(state))  # [W, N, 2 flags, 2]
        own, enemy = self.team, 1 - self.team
        held = (state.carrier >= 0).float()  # [W, 2]
        mine = (state.carrier[:, enemy] == torch.arange(N, device=self.device)).float()
        mates, opps = self.nearest(state, alive)
        near = torch.cat((mates, opps), -1)  # [W, N, K]
        rel = pos.gather(1, near.reshape(W, -1, 1).expand(-1, -1, 2)).reshape(W, N, -1, 2) - pos[:, :, None]
        return torch.cat((self.own_obs(state), self.base[own] - pos, flags[:, torch.arange(N), own],
                          held[:, own, None], flags[:, torch.arange(N), enemy], held[:, enemy, None],
                          mine[..., None], rel.reshape(W, N, -1)), -1)

    def heuristic(self, state, alive):
        """Attackers (half of each team) fetch the enemy flag and carry it home (or go home while a
        teammate carries it); defenders chase the nearest opponent in their half, else guard the
        point 1 m in front of their flag."""
        N = self.num_agents
        pos = state.pos[:, :N]
        flags = self.flag_position(state)  # [W, 2, 2]
        enemy = 1 - self.team
        own_base = self.base[self.team].expand_as(pos)
        enemy_flag = flags[:, enemy]  # [W, N, 2]
        carried = (state.carrier[:, enemy] >= 0)[..., None]  # [W, N, 1] by a teammate (or self)
        attack = torch.where(carried, own_base, enemy_flag)
        intruder = ~self.same & (pos[..., 1][:, None, :] * self.side[:, None] > 0)  # [W, N, N] j in i's half
        dist = torch.where(intruder & alive[:, None, :], torch.cdist(pos, pos), math.inf)
        chase = pos.gather(1, dist.argmin(-1)[..., None].expand(-1, -1, 2))
        guard = own_base - self.side[:, None] * torch.tensor([0.0, 1.0], device=self.device)
        defend = torch.where(torch.isinf(dist.amin(-1))[..., None], guard, chase)
        return self.steer_to(state, torch.where(self.attacker[:, None], attack, defend))
