"""Communication through pixels (after MPE's ``simple_speaker_listener``): a speaker who knows the
goal shows it with a lamp; a listener who sees the lamp must reach the goal.

* Agents: ``speaker_0`` (team ``speaker``) then ``listener_0`` (team ``listener``); exactly 2.
* Arena: |x|, |y| <= 1.5 m. ``num_targets`` K (default 3, 2 to 6) targets, discs of distinct
  colours, at random places each episode, at least 0.6 m apart.
* The goal: one target, drawn each episode. Only the speaker can tell which: a white ring lies
  under the goal target, drawn in every view but the listener's (the renderer's per-view owner
  mask). The listener sees the targets, the speaker and its lamp, never the ring.
* The speaker stands at (0, -1.2) and cannot move (its thrust is 0), only turn. On its head sits
  a lamp that shows one of the K target colours, or is dark (off, at the start of an episode).
* Actions (one space for both agents): discrete 5 + K: 0 noop, 1 forward, 2 turn left, 3 turn
  right, 4 backward, then ``lamp_k`` (5 + k: set the lamp to target k's colour). The action mask
  gives the speaker noop, the turns and the lamp actions; the listener the five movements.
  Continuous 2 + K: (thrust, turn) as in the arena, then K lamp values: the lamp shows the colour
  of the largest when it is above 0.5 (else it keeps its colour). The listener's lamp values and
  the speaker's thrust do nothing.
* Reward, shared: -0.1 x (distance of the listener to the goal, m) per step; +1 when the
  listener comes within ``REACH`` (0.25 m) of the goal's centre, which terminates the episode.
  Truncated after ``max_steps`` = 100.
* info: ``"reached"`` int64 [W] (1 on the step the listener reaches the goal), ``"distance"``
  float32 [W] (listener to goal, m), ``"lamp_correct"`` int64 [W] (1 while the lamp shows the
  goal's colour).
* State obs (same size for both, 9 + 4 K): own position, velocity, cos/sin yaw (6); the goal as
  a one-hot over K (the speaker's; zeros for the listener); the lamp as a one-hot over K + 1 (off
  first: what the listener can read from its pixels); the targets relative to the agent (2 K);
  the other agent relative to it (2).
"""
from __future__ import annotations

import dataclasses
import math

import torch

from marl_render.util.validation import positive_int

from . import egomotion, scenery
from .arena import ArenaScenario, ArenaState, Prop
from .roster import Bot, Card, HeldOut

ARENA = 1.5
SPEAKER_POS = (0.0, -1.2)
TARGET_RADIUS = 0.15
REACH = 0.25
LAMP_OFF = (0.15, 0.15, 0.15)
RING_COLOR = (1.0, 1.0, 1.0)


@dataclasses.dataclass(frozen=True)
class SpeakerListenerParams:
    num_targets: int = 3  # 2 to 6

    def __post_init__(self):
        if not 2 <= positive_int("num_targets", self.num_targets) <= 6:
            raise ValueError(f"num_targets must be an int in [2, 6], got {self.num_targets}")


@dataclasses.dataclass(frozen=True)
class SpeakerListenerState(ArenaState):
    targets: torch.Tensor  # [W, K, 2] target centres (m)
    goal: torch.Tensor  # [W] int64: the goal's index
    lamp: torch.Tensor  # [W] int64: -1 off, else the target index whose colour the lamp shows


# Bot scripts (envs/roster.py): env -> actions of every agent of every world, [W, A].
def permuted_speaker(env) -> torch.Tensor:
    """The speaker shows the colour after the goal's (a permuted code); the listener as the heuristic."""
    s, state = env.scenario, env.sim
    actions = s.heuristic(state, env.alive).clone()
    actions[:, 0] = 5 + (state.goal + 1) % s.num_targets
    return actions


def first_target_listener(env) -> torch.Tensor:
    """The listener drives to the first target whatever the lamp shows; the speaker as the heuristic."""
    s, state = env.scenario, env.sim
    actions = s.heuristic(state, env.alive).clone()
    actions[:, 1] = s.steer_to(state, state.targets[:, :1].expand(-1, 2, 2))[:, 1]
    return actions


class SpeakerListener(ArenaScenario):
    """Speaker and listener; see the module docstring."""

    name = "speaker_listener"
    Params = SpeakerListenerParams
    # Targets the speaker must tell apart.
    difficulties = {"easy": {"num_targets": 2}, "medium": {}, "hard": {"num_targets": 6}}
    State = SpeakerListenerState
    default_num_agents = 2
    agent_range = (2, 2)
    default_max_steps = 100
    physics_terms = frozenset({"walls", "body_collisions", "drag"})
    info_keys = {"reached": torch.int64, "distance": torch.float32, "lamp_correct": torch.int64}
    arena_half_extent = (ARENA, ARENA)
    bots = {"noisy0.1": Bot.noisy(0.1, population="train"),
            "permuted_speaker": Bot("the speaker shows the next colour (a permuted code)", script=permuted_speaker),
            "first_target_listener": Bot("the listener ignores the lamp", script=first_target_listener),
            "noisy0.5": Bot.noisy(0.5)}
    heldout = (
        HeldOut("permuted_speaker", "a focal listener with a speaker whose lamp code is permuted (convention "
                "following)", 2, ("listener_0",), {"speaker": ("permuted_speaker",)}),
        HeldOut("noisy_speaker", "a focal listener with a speaker that shows a random colour half the time", 2,
                ("listener_0",), {"speaker": ("noisy0.5",)}),
        HeldOut("deaf_listener", "a focal speaker with a listener that ignores the lamp", 2, ("speaker_0",),
                {"listener": ("first_target_listener",)}),
    )
    card = Card(reward="shared: -0.1 x the listener's distance to the goal per step, +1 when it reaches the goal",
                episode_end="the listener reaching the goal terminates both agents; truncated at max_steps",
                continuous=egomotion.CONTINUOUS_MEANINGS + tuple(
                    f"lamp value of target {k}: the lamp shows the colour of the largest when it is above 0.5 (the "
                    f"speaker's only)" for k in range(3)),
                info={"reached": "1 on the step the listener reaches the goal",
                      "distance": "the listener's distance to the goal (m)",
                      "lamp_correct": "1 while the lamp shows the goal's colour"})
    training = {"budget": {"pixels": 167_936, "state": 1_039_360}}  # env steps of the published runs

    def setup(self):
        K = self.num_targets = self.params.num_targets
        self.setup_arena({"speaker": ["speaker_0"], "listener": ["listener_0"]}, state_dim=9 + 4 * K, radius=0.15,
                         max_speed=2.0, extra_actions=tuple(f"lamp_{k}" for k in range(K)))
        self.thrust = self.per_agent({"speaker": 0.0, "listener": egomotion.THRUST})
        self.colors = scenery.palette(K, offset=2)  # skips red and blue (the agents' team colours)
        self._lamp_colors = torch.cat((torch.tensor([LAMP_OFF]), self.colors))  # [K + 1, 3], off first
        mask = torch.ones(2, 5 + K, dtype=torch.bool, device=self.device)
        mask[0, [1, 4]] = False  # the speaker turns and signals, it does not drive
        mask[1, 5:] = False  # the listener drives
        self._mask = mask
        self._speaker_row = torch.tensor([[1.0], [0.0]], device=self.device)  # the goal is the speaker's

    def initial_state(self):
        W, K = self.num_worlds, self.num_targets
        return self.at_rest(torch.zeros(W, 2, 2), torch.zeros(W, 2), targets=torch.zeros(W, K, 2),
                            goal=torch.zeros(W, dtype=torch.int64), lamp=torch.full((W,), -1, dtype=torch.int64))

    def props(self):
        K = self.num_targets
        return [Prop("targets", scenery.disc_mesh(), count=K, position="targets", height=0.02, color=self.colors,
                     scale=(2 * TARGET_RADIUS, 2 * TARGET_RADIUS, 0.04), moves=False),
                Prop("ring", scenery.disc_mesh(), count=1, position=goal_position, height=0.005, color=RING_COLOR,
                     scale=(3.2 * TARGET_RADIUS, 3.2 * TARGET_RADIUS, 0.01), moves=False, hidden_from=1),
                Prop("lamp", "sphere", count=1, position=lambda s: s.pos[:, :1], height=0.64, scale=(0.24,) * 3,
                     color=lambda s: self._lamp_colors[(s.lamp + 1).cpu()][:, None])]

    def state_bounds(self):
        K = self.num_targets
        return {**super().state_bounds(), "targets": self.inside_walls(), "goal": (0, K - 1), "lamp": (-1, K - 1)}

    def spawn_level(self, draws):
        W, K = self.num_worlds, self.num_targets
        cells = scenery.cell_spawn(draws, W, torch.full((K + 1,), 0.3), 3, 1.2)  # targets and listener, apart
        targets, listener = cells[:, :K], cells[:, K:]
        speaker = torch.tensor(SPEAKER_POS).expand(W, 1, 2)
        yaw = torch.stack((torch.zeros(W), (draws.rand("yaw", (W,)) * 2 - 1) * math.pi), -1)
        return self.at_rest(torch.cat((speaker, listener), 1), yaw, targets=targets,
                            goal=draws.randint("goal", K, (W,)), lamp=torch.full((W,), -1, dtype=torch.int64))

    def rules(self, before, moved, actions, alive, generator):
        if self.continuous:
            value, choice = actions[:, 0, 2:].max(-1)
            lamp = torch.where(value > 0.5, choice, before.lamp)
        else:
            lamp = torch.where(actions[:, 0] >= 5, actions[:, 0] - 5, before.lamp)
        goal = goal_position(moved)[:, 0]
        distance = (moved.pos[:, 1] - goal).norm(dim=-1)
        reached = distance < REACH
        reward = (-0.1 * distance + reached.float())[:, None].expand(-1, 2)
        info = {"reached": reached.long(), "distance": distance.float(), "lamp_correct": (lamp == moved.goal).long()}
        return dataclasses.replace(moved, lamp=lamp), reward, reached[:, None].expand(-1, 2), info

    def action_mask(self, state, alive):
        return self._mask.expand(self.num_worlds, -1, -1)

    def observation(self, state, alive):
        W, K = self.num_worlds, self.num_targets
        goal = torch.nn.functional.one_hot(state.goal, K).to(state.pos.dtype)[:, None] * self._speaker_row
        lamp = torch.nn.functional.one_hot(state.lamp + 1, K + 1).to(state.pos.dtype)[:, None].expand(-1, 2, -1)
        return torch.cat((self.own_obs(state), goal, lamp, self.relative(state, state.targets).reshape(W, 2, -1),
                          self.others_obs(state).reshape(W, 2, -1)), -1)

    def heuristic(self, state, alive):
        """The speaker shows the goal's colour; the listener drives to the target of the lamp's colour
        (stays put while the lamp is off)."""
        W = self.num_worlds
        shown = state.lamp.clamp(min=0)
        target = state.targets[torch.arange(W), shown]
        target = torch.where((state.lamp >= 0)[:, None], target, state.pos[:, 1])
        drive = self.steer_to(state, torch.stack((state.pos[:, 0], target), 1))
        if self.continuous:
            signal = torch.nn.functional.one_hot(state.goal, self.num_targets).float()
            speaker = torch.cat((torch.zeros(W, 2), signal), -1)
            listener = torch.cat((drive[:, 1], torch.zeros(W, self.num_targets)), -1)
            return torch.stack((speaker, listener), 1)
        return torch.stack((5 + state.goal, drive[:, 1]), 1)


def goal_position(state: SpeakerListenerState) -> torch.Tensor:
    """[W, 1, 2]: the goal target's centre."""
    return state.targets.gather(1, state.goal[:, None, None].expand(-1, 1, 2))
