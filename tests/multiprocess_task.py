"""A test-only task for tests/test_multiprocess.py: cartpole whose step fails on all-ones actions.

A module of its own (not the test file) so that the spawned worker processes import it by name."""
from marl_render.envs.cartpole import CartPoleBalance


class FailingCartPole(CartPoleBalance):
    """cartpole, except that a step whose actions are all 1 (in the batch this env steps) raises."""

    def step(self, state, actions, alive, generator):
        if bool((actions == 1).all()):
            raise ValueError("FailingCartPole.step refuses a batch of all-ones actions")
        return super().step(state, actions, alive, generator)
