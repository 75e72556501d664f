"""A focal-only env's state holds its bots' own generators, and a failed step leaves them as they were."""
from __future__ import annotations

import pytest
import torch

from marl_render.envs import make_env

SCENARIO = "speaker_listener/noisy_speaker"  # its speaker bot plays a random action half the time


def _bot_generators(env) -> list:
    return [b.generator for b in env.bots if isinstance(getattr(b, "generator", None), torch.Generator)]


def _rollout(env, actions) -> list:
    return [env.step(a)[0]["state"] for a in actions]


@pytest.fixture(scope="module")
def env():
    """One env for the module (building one costs seconds): every test starts with a seeded reset."""
    with make_env("speaker_listener", heldout=SCENARIO, num_worlds=8, resolution=8, seed=3, state_obs=True) as env:
        yield env


def test_set_state_restores_the_bots_own_generators(env):
    assert len(_bot_generators(env)) == 1
    env.reset(seed=3)
    state = env.get_state()
    actions = [env.random_actions(torch.Generator().manual_seed(k)) for k in range(6)]
    first = _rollout(env, actions)
    env.set_state(state)
    again = _rollout(env, actions)
    assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True))


def test_state_without_or_with_bad_bot_generators_is_refused_and_changes_nothing(env):
    env.reset(seed=0)
    state = env.get_state()
    (generator,) = _bot_generators(env)
    before = generator.get_state()
    with pytest.raises(ValueError, match="bot_rngs"):
        env.set_state({k: v for k, v in state.items() if k != "bot_rngs"})
    with pytest.raises(ValueError, match=r"bot_rngs.*list of 1"):
        env.set_state({**state, "bot_rngs": []})
    with pytest.raises(ValueError, match=r"state\['bot_rngs'\]\[0\] must be a torch.Generator state"):
        env.set_state({**state, "bot_rngs": [torch.zeros(3, dtype=torch.uint8)]})
    with pytest.raises(ValueError, match=r"state\['background_rng'\] must be a torch.Generator state"):
        env.set_state({**state, "background_rng": "not a state"})
    assert torch.equal(generator.get_state(), before)
    assert torch.equal(env.get_state()["step_count"], state["step_count"])


def test_a_step_that_fails_in_the_core_leaves_the_bots_generators_as_they_were(env, monkeypatch):
    env.reset(seed=5)
    (generator,) = _bot_generators(env)
    before = generator.get_state()
    actions = env.random_actions(torch.Generator().manual_seed(0))

    def failing_step(full):
        raise RuntimeError("a hook failed")

    monkeypatch.setattr(env.core, "step", failing_step)
    with pytest.raises(RuntimeError, match="a hook failed"):
        env.step(actions)
    assert torch.equal(generator.get_state(), before)  # the bot drew its noise, then it was undone
