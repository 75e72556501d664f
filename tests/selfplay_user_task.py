"""A two-team task defined outside the package, as a user would write one: importing this module
registers it as "beacon_duel" (the trainer's and the evaluation's --import find it by module name).

Red and blue scouts race for one beacon: each step a team earns the number of its scouts on the
beacon minus the other team's (zero-sum). Defined for tests/test_selfplay.py."""
import dataclasses

import torch

from marl_render.envs import ArenaScenario, ArenaState, Prop, list_envs, numbered, register_env


@dataclasses.dataclass(frozen=True)
class DuelState(ArenaState):
    beacon: torch.Tensor  # [W, 1, 2]


class BeaconDuel(ArenaScenario):
    name = "beacon_duel"
    State = DuelState
    default_num_agents = 2
    agent_range = (2, 4)
    default_max_steps = 6
    physics_terms = frozenset({"walls", "drag"})
    info_keys = {"red_on_beacon": torch.int64}
    opponents = ("blue",)

    def setup(self):
        half = self.num_agents // 2
        self.setup_arena({"red": numbered("red", half), "blue": numbered("blue", self.num_agents - half)},
                         state_dim=8, radius=0.15, max_speed=2.0)
        self.red = torch.arange(self.num_agents) < half

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self.at_rest(torch.zeros(W, N, 2), torch.zeros(W, N), beacon=torch.zeros(W, 1, 2))

    def props(self):
        return [Prop("beacon", "box", count=1, position="beacon", height=0.2, scale=(0.3, 0.3, 0.4),
                     color=(1.0, 0.2, 0.8), moves=False)]

    def spawn(self, generator):
        W, N = self.num_worlds, self.num_agents
        pos = torch.rand(W, N, 2, generator=generator) * 2 - 1
        return self.at_rest(pos, torch.zeros(W, N), beacon=torch.rand(W, 1, 2, generator=generator) - 0.5)

    def rules(self, before, moved, actions, alive, generator):
        on = (moved.pos - moved.beacon).norm(dim=-1) < 0.3  # [W, N]
        red = (on & self.red).sum(-1, keepdim=True).float()
        blue = (on & ~self.red).sum(-1, keepdim=True).float()
        reward = torch.where(self.red, red - blue, blue - red)
        return moved, reward, torch.zeros_like(alive), {"red_on_beacon": red[:, 0].long()}

    def observation(self, state, alive):
        return torch.cat((self.own_obs(state), self.relative(state, state.beacon)[:, :, 0]), -1)

    def heuristic(self, state, alive):
        return self.steer_to(state, state.beacon.expand(-1, self.num_agents, -1))


class LoneBeacon(BeaconDuel):
    """One team only: self-play refuses it."""

    name = "lone_beacon"

    def setup(self):
        self.setup_arena({"scouts": numbered("scout", self.num_agents)}, state_dim=8, radius=0.15, max_speed=2.0)
        self.red = torch.ones(self.num_agents, dtype=torch.bool)

    opponents = ()


if "beacon_duel" not in list_envs():
    register_env("beacon_duel", BeaconDuel)
