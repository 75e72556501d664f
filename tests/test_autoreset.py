"""Auto-reset modes of the batched core (envs/core.py): next-step and same-step, as in
gymnasium 1.x's vector envs, checked against gymnasium's own SyncVectorEnv."""
from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from marl_render.envs import list_envs, make_env
from test_envs_core import ToyEnv

W = 3
RES = 16
ENVS = list_envs()


def make(name, **kw):
    kw.setdefault("num_worlds", W)
    kw.setdefault("resolution", RES)
    kw.setdefault("seed", 0)
    kw.setdefault("state_obs", True)
    kw.setdefault("episode_end", False)  # fixed ends: these contracts count steps (random: test_episodes.py)
    return make_env(name, **kw)


def actions_for(env, step):
    return env.random_actions(torch.Generator().manual_seed(100 + step))


def assert_obs_equal(got: dict, want: dict, where=slice(None)):
    assert got.keys() == want.keys()
    for key in want:
        assert torch.equal(got[key][where], want[key][where]), key


@pytest.mark.parametrize("value, mode", [(False, False), (True, "same_step"), ("same_step", "same_step"),
                                         ("next_step", "next_step"), (np.bool_(True), "same_step")])
def test_autoreset_argument(value, mode):
    env = make("cartpole", autoreset=value)
    assert env.autoreset == mode
    env.close()


@pytest.mark.parametrize("value, error", [(1, TypeError), ("NextStep", ValueError), (None, TypeError),
                                          ("disabled", ValueError)])
def test_autoreset_argument_rejected(value, error):
    with pytest.raises(error, match=r"autoreset must be False, True \(= 'same_step'\) or one of"):
        make("cartpole", autoreset=value)


@pytest.mark.parametrize("name", ENVS)
def test_same_step_gives_the_final_obs_of_a_truncated_episode(name):
    env = make(name, max_steps=3, autoreset="same_step", depth=True)
    reference = make(name, max_steps=3, depth=True)  # no auto-reset: shows the true final obs
    env.reset(seed=5), reference.reset(seed=5)
    for step in range(3):
        obs, reward, terminated, truncated, info = env.step(actions_for(env, step))
        want, want_reward, *_ = reference.step(actions_for(env, step))
        if step < 2:  # no world done: the final obs is the returned obs
            assert not info["autoreset_worlds"].any()
            assert_obs_equal(info["final_obs"], obs)
    assert info["done_worlds"].all() and info["autoreset_worlds"].all() and truncated.any()
    assert_obs_equal(info["final_obs"], want)  # the frame that ended the episode...
    assert torch.equal(reward, want_reward)
    first = reference.reset_worlds(torch.ones(W, dtype=torch.bool))
    assert_obs_equal(obs, first)  # ...and the first frame of the new one
    assert not torch.equal(obs["pixels"], want["pixels"])
    env.close(), reference.close()


@pytest.mark.parametrize("name", ENVS)
def test_next_step_returns_the_final_obs_then_resets_on_the_next_step(name):
    env = make(name, max_steps=3, autoreset="next_step")
    other = make(name, max_steps=3, autoreset="next_step")  # the same, with other actions on the reset step
    reference = make(name, max_steps=3)
    for e in (env, other, reference):
        e.reset(seed=5)
    for step in range(3):
        a = actions_for(env, step)
        obs, reward, terminated, truncated, info = env.step(a)
        other.step(a)
        want, want_reward, want_terminated, want_truncated, _ = reference.step(a)
    # The step that ends the episode returns its true final obs, and nothing is reset yet.
    assert_obs_equal(obs, want)
    assert torch.equal(reward, want_reward) and torch.equal(truncated, want_truncated)
    assert info["done_worlds"].all() and not info["autoreset_worlds"].any()
    # The next step resets every done world instead of stepping it; its actions are ignored.
    obs, reward, terminated, truncated, info = env.step(actions_for(env, 3))
    other_obs, *_ = other.step(actions_for(env, 4))
    reference.step(actions_for(env, 3))  # the core draws the new episode after the (ignored) step
    first = reference.reset_worlds(torch.ones(W, dtype=torch.bool))
    assert_obs_equal(obs, first)
    assert_obs_equal(other_obs, first)
    assert (reward == 0).all() and not terminated.any() and not truncated.any()
    assert info["autoreset_worlds"].all() and not info["done_worlds"].any()
    assert info["step_count"].tolist() == [0] * W and env.step_count.tolist() == [0] * W
    # Then the new episode runs normally.
    obs, reward, terminated, truncated, info = env.step(actions_for(env, 5))
    want, want_reward, *_ = reference.step(actions_for(env, 5))
    assert_obs_equal(obs, want)
    assert torch.equal(reward, want_reward) and not info["autoreset_worlds"].any()
    for e in (env, other, reference):
        e.close()


def test_next_step_resets_only_the_worlds_that_were_done():
    env = make("cartpole", max_steps=3, autoreset="next_step")
    env.reset(seed=0)
    env.step(actions_for(env, 0))
    env.reset_worlds(torch.tensor([True, False, False]))  # world 0 now lags one step behind
    for step in range(2):
        env.step(actions_for(env, 1 + step))
    assert env.step_count.tolist() == [2, 3, 3]
    before = env.get_state()["qstate"]
    obs, reward, terminated, truncated, info = env.step(actions_for(env, 3))
    assert info["autoreset_worlds"].tolist() == [False, True, True]
    assert truncated.tolist() == [[True], [False], [False]] and reward[1:].eq(0).all() and reward[0] > 0
    assert env.step_count.tolist() == [3, 0, 0]
    assert not torch.equal(env.sim.qstate[0], before[0])  # world 0 stepped
    obs, reward, terminated, truncated, info = env.step(actions_for(env, 4))
    assert info["autoreset_worlds"].tolist() == [True, False, False]
    assert env.step_count.tolist() == [0, 1, 1] and reward[0].item() == 0 and (reward[1:] > 0).all()
    env.close()


def test_next_step_after_a_manual_reset_does_not_reset_again():
    env = make("cartpole", max_steps=2, autoreset="next_step")
    env.reset(seed=0)
    for step in range(2):
        env.step(actions_for(env, step))
    first = env.reset_worlds(torch.ones(W, dtype=torch.bool))  # the user starts the new episode
    state = env.sim.qstate.clone()
    obs, reward, *_, info = env.step(actions_for(env, 2))
    assert not info["autoreset_worlds"].any() and (reward > 0).all()
    assert not torch.equal(env.sim.qstate, state) and not torch.equal(obs["state"], first["state"])
    env.close()


# ---------------------------------------------------------------------- against gymnasium itself
class OneToyWorld(gymnasium.Env):
    """One world of ToyEnv (no auto-reset) as a plain gymnasium.Env: obs = both agents'
    positions, reward = their sum, terminated = every agent left, truncated = time limit."""

    observation_space = gymnasium.spaces.Box(0, 100, (2,), np.float32)
    action_space = gymnasium.spaces.MultiDiscrete([2, 2])

    def __init__(self, max_steps):
        self.core = ToyEnv(num_worlds=1, seed=0, max_steps=max_steps, state_obs=True)

    def reset(self, *, seed=None, options=None):
        obs = self.core.reset()
        return obs["state"][0, :, 0].numpy(), {}

    def step(self, action):
        obs, reward, terminated, truncated, info = self.core.step(torch.as_tensor(action).reshape(1, 2))
        ended = bool(terminated.all())
        return (obs["state"][0, :, 0].numpy(), float(reward.sum()), ended,
                bool(info["done_worlds"][0]) and not ended, {})

    def close(self):
        self.core.close()


def toy_actions(steps):
    """Worlds that move at different rates, so that they end at different steps (by
    termination: walker at 2, runner at 3) or by the time limit."""
    g = torch.Generator().manual_seed(0)
    rate = torch.tensor([[1.0, 1.0], [0.6, 0.4], [0.2, 0.2], [0.8, 0.0]])
    return [(torch.rand(rate.shape, generator=g) < rate).long() for _ in range(steps)]


@pytest.mark.parametrize("mode", ["next_step", "same_step"])
def test_core_matches_gymnasium_sync_vector_env(mode):
    worlds, max_steps, steps = 4, 6, 30
    gym_mode = AutoresetMode.NEXT_STEP if mode == "next_step" else AutoresetMode.SAME_STEP
    ours = ToyEnv(num_worlds=worlds, seed=0, max_steps=max_steps, state_obs=True, autoreset=mode)
    theirs = SyncVectorEnv([lambda: OneToyWorld(max_steps) for _ in range(worlds)], autoreset_mode=gym_mode)
    obs = ours.reset()
    want, _ = theirs.reset()
    assert np.array_equal(obs["state"][..., 0].numpy(), want)
    resets = 0
    for actions in toy_actions(steps):
        obs, reward, terminated, truncated, info = ours.step(actions)
        want, want_reward, want_terminated, want_truncated, want_info = theirs.step(actions.numpy())
        ended = terminated.all(1)
        assert np.array_equal(obs["state"][..., 0].numpy(), want)
        assert np.array_equal(reward.sum(1).numpy(), want_reward)
        assert np.array_equal(ended.numpy(), want_terminated)
        assert np.array_equal((info["done_worlds"] & ~ended).numpy(), want_truncated)
        if mode == "same_step" and want_info:
            done = want_info["_final_obs"]
            assert np.array_equal(info["autoreset_worlds"].numpy(), done)
            final = np.stack([want_info["final_obs"][i] for i in np.flatnonzero(done)])
            assert np.array_equal(info["final_obs"]["state"][done][..., 0].numpy(), final)
        resets += int(info["autoreset_worlds"].sum())
    assert resets >= 8  # terminations and truncations, at different steps in different worlds
    ours.close(), theirs.close()


# ---------------------------------------------------------------------- cost
# (world done?, renders) of 6 steps with max_steps=2: same-step draws the final frame and the
# new one; next-step draws one frame per step and spends a step on the reset.
RENDERS = {
    False: [(False, 1)] + [(True, 1)] * 5,
    "next_step": [(False, 1), (True, 1), (False, 1)] * 2,
    "same_step": [(False, 1), (True, 2)] * 3,
}


@pytest.mark.parametrize("mode", list(RENDERS))
def test_renders_per_step(mode, monkeypatch):
    env = make("cartpole", max_steps=2, autoreset=mode)
    env.reset(seed=0)
    calls = []
    render = env.renderer.render
    monkeypatch.setattr(env.renderer, "render", lambda *a, **k: calls.append(1) or render(*a, **k))
    counts = []
    for step in range(6):
        before = len(calls)
        _, _, _, _, info = env.step(actions_for(env, step))
        counts.append((bool(info["done_worlds"].any()), len(calls) - before))
    assert counts == RENDERS[mode]
    env.close()
