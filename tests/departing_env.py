"""A test-only environment in which agents leave the episode (shared by wrapper tests)."""
from marl_render.envs.spread import Spread


class Departing(Spread):
    """spread with two teams where agents leave: prey_0 at step 2, prey_1 at step 3 (world 0 only)."""

    name = "departing"
    agent_range = (3, 3)

    def _setup(self):
        super()._setup()
        self.agent_names = ["predator_0", "prey_0", "prey_1"]
        self.groups = {"predators": ["predator_0"], "prey": ["prey_0", "prey_1"]}

    def _step_state(self, actions, alive):
        reward, terminated, info = super()._step_state(actions, alive)
        terminated = terminated.clone()
        terminated[0, 1] |= bool(self.step_count[0] == 1)
        terminated[0, 2] |= bool(self.step_count[0] == 2)
        return reward, terminated, info
