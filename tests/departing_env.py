"""A test-only task in which agents leave the episode (shared by wrapper tests)."""
import dataclasses

import torch

from marl_render.envs.spread import Spread, SpreadState


@dataclasses.dataclass(frozen=True)
class DepartingState(SpreadState):
    t: torch.Tensor  # [W] int64 steps taken in the episode


class Departing(Spread):
    """spread with two teams where agents leave: prey_0 at step 2, prey_1 at step 3 (world 0 only)."""

    name = "departing"
    State = DepartingState
    agent_range = (3, 3)

    def setup(self):
        super().setup()
        self.teams = {"predators": ["predator_0"], "prey": ["prey_0", "prey_1"]}

    def initial_state(self):
        return dataclasses.replace(super().initial_state(), t=torch.zeros(self.num_worlds, dtype=torch.int64))

    def at_rest(self, pos, yaw, **extra):
        return super().at_rest(pos, yaw, **{"t": torch.zeros(pos.shape[0], dtype=torch.int64), **extra})

    def rules(self, before, moved, actions, alive, generator):
        state, reward, terminated, info = super().rules(before, moved, actions, alive, generator)
        terminated = terminated.clone()
        terminated[0, 1] |= bool(before.t[0] == 1)
        terminated[0, 2] |= bool(before.t[0] == 2)
        return dataclasses.replace(state, t=before.t + 1), reward, terminated, info
