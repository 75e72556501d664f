"""gymnasium front end (marl_render/wrappers/gymnasium.py): make_vec_env as a
gymnasium.vector.VectorEnv over one batched core, its layout, autoreset modes, infos,
seeding, gymnasium's vector wrappers and env checkers."""
from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils import env_checker
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.wrappers import vector as vw

from departing_env import Departing
from marl_render.envs import make_env, make_vec_env
from marl_render.wrappers.gymnasium import MarlRenderVectorEnv

W = 3
RES = 16


def make(name="cartpole", **kw):
    kw.setdefault("num_worlds", W)
    kw.setdefault("resolution", RES)
    kw.setdefault("seed", 0)
    return make_vec_env(name, **kw)


def twin_core(name="cartpole", autoreset="next_step", **kw):
    """The batched core the vector env wraps, built alike: the reference for its outputs."""
    kw.setdefault("num_worlds", W)
    kw.setdefault("resolution", RES)
    kw.setdefault("seed", 0)
    return make_env(name, autoreset=autoreset, **kw)


def sample(envs, seed):
    envs.action_space.seed(seed)
    return envs.action_space.sample()


# ---------------------------------------------------------------------- spaces and layout
@pytest.mark.parametrize("name, agents", [("cartpole", 1), ("spread", 3), ("tag", 4)])
def test_spaces_and_shapes(name, agents):
    envs = make(name)
    n = W * agents
    assert isinstance(envs, VectorEnv) and envs.num_envs == n
    assert envs.single_observation_space == gymnasium.spaces.Box(0, 255, (RES, RES, 3), np.uint8)
    assert envs.observation_space == gymnasium.spaces.Box(0, 255, (n, RES, RES, 3), np.uint8)
    assert envs.single_action_space == gymnasium.spaces.Discrete(envs.core.num_actions)
    assert envs.action_space == gymnasium.spaces.MultiDiscrete([envs.core.num_actions] * n)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs, info = envs.reset(seed=0)
    assert obs.shape == (n, RES, RES, 3) and obs.dtype == np.uint8 and obs in envs.observation_space
    assert info == {}
    obs, reward, terminated, truncated, info = envs.step(sample(envs, 0))
    assert obs in envs.observation_space
    assert reward.shape == (n,) and reward.dtype == np.float32
    assert terminated.shape == truncated.shape == (n,) and terminated.dtype == truncated.dtype == np.bool_
    assert info["step_count"].tolist() == [1] * n and info["_step_count"].all()
    envs.close()


def test_dict_observation_and_continuous_actions():
    envs = make("spread", state_obs=True, depth=True, continuous=True)
    n = W * 3
    space = envs.single_observation_space
    assert isinstance(space, gymnasium.spaces.Dict) and set(space) == {"pixels", "depth", "state"}
    assert space["state"].shape == (envs.core.state_dim,) and space["depth"].shape == (RES, RES)
    assert envs.action_space == gymnasium.spaces.Box(-1, 1, (n, 2), np.float32)
    obs, _ = envs.reset(seed=0)
    assert obs in envs.observation_space and obs["state"].shape == (n, envs.core.state_dim)
    obs, *_ = envs.step(sample(envs, 1))
    assert obs in envs.observation_space
    envs.close()
    masked = make("tag", action_mask=True)
    obs, _ = masked.reset(seed=0)
    assert obs["action_mask"].dtype == np.int8 and obs["action_mask"].shape == (W * 4, masked.core.num_actions)
    assert obs in masked.observation_space
    masked.close()


@pytest.mark.parametrize("name", ["cartpole", "spread"])
def test_entry_i_is_agent_i_mod_A_of_world_i_div_A(name):
    envs = make(name, state_obs=True)
    core = twin_core(name, state_obs=True)
    A = core.num_agents
    obs, _ = envs.reset(seed=4)
    want = core.reset(seed=4)
    for step in range(3):
        actions = sample(envs, step)
        entry = np.arange(W * A)
        assert np.array_equal(obs["pixels"][entry], want["pixels"][entry // A, entry % A].numpy())
        assert np.array_equal(obs["state"][entry], want["state"][entry // A, entry % A].numpy())
        obs, reward, *_ = envs.step(actions)
        want, want_reward, *_ = core.step(torch.from_numpy(actions).reshape(W, A))
        assert np.array_equal(reward, want_reward.reshape(-1).numpy())
    envs.close(), core.close()


def test_observations_are_views_of_fresh_memory():
    envs = make()
    first, _ = envs.reset(seed=0)
    kept = first.copy()
    second, *_ = envs.step(sample(envs, 0))
    assert not np.shares_memory(first, second) and np.array_equal(first, kept)
    assert first.base is not None  # a view of the renderer's output, not a copy of it
    envs.close()


# ---------------------------------------------------------------------- autoreset modes
def test_next_step_mode():
    envs = make(max_steps=3)
    core = twin_core(max_steps=3, autoreset=False)  # shows what the final obs must be
    envs.reset(seed=1), core.reset(seed=1)
    for step in range(3):
        actions = sample(envs, step)
        obs, reward, terminated, truncated, info = envs.step(actions)
        want, *_ = core.step(torch.from_numpy(actions)[:, None])
    assert truncated.all() and not terminated.any() and (reward > 0).all()
    assert np.array_equal(obs, want["pixels"][:, 0].numpy())  # the final obs, not yet reset
    obs, reward, terminated, truncated, info = envs.step(sample(envs, 3))  # the reset step
    core.step(torch.from_numpy(sample(envs, 3))[:, None])
    first = core.reset_worlds(torch.ones(W, dtype=torch.bool))
    assert np.array_equal(obs, first["pixels"][:, 0].numpy())
    assert (reward == 0).all() and not terminated.any() and not truncated.any()
    assert info == {}  # reset entries have no step info
    obs, reward, *_, info = envs.step(sample(envs, 4))
    assert (reward > 0).all() and info["step_count"].tolist() == [1] * W
    envs.close(), core.close()


def test_same_step_mode_gives_final_obs_and_final_info():
    envs = make(max_steps=3, autoreset_mode=AutoresetMode.SAME_STEP)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    core = twin_core(max_steps=3, autoreset=False)
    envs.reset(seed=1), core.reset(seed=1)
    for step in range(3):
        actions = sample(envs, step)
        obs, reward, terminated, truncated, info = envs.step(actions)
        want, *_ = core.step(torch.from_numpy(actions)[:, None])
        if step < 2:
            assert "final_obs" not in info and info["_step_count"].all()
    assert truncated.all() and info["_final_obs"].all() and info["_final_info"].all()
    assert info["final_obs"].dtype == object and info["final_obs"].shape == (W,)
    for i in range(W):
        assert np.array_equal(info["final_obs"][i], want["pixels"][i, 0].numpy())
    assert info["final_info"]["step_count"].tolist() == [3] * W and info["final_info"]["_step_count"].all()
    assert "step_count" not in info  # every entry ended: none has step info of its new episode
    first = core.reset_worlds(torch.ones(W, dtype=torch.bool))
    assert np.array_equal(obs, first["pixels"][:, 0].numpy())
    envs.close(), core.close()


def test_same_step_info_masks_when_only_some_worlds_end():
    envs = make(max_steps=2, autoreset_mode="SameStep")
    envs.reset(seed=0)
    envs.step(sample(envs, 0))
    envs.reset(options={"reset_mask": np.array([True, False, False])})  # world 0 lags a step behind
    _, _, _, truncated, info = envs.step(sample(envs, 1))
    assert truncated.tolist() == [False, True, True]
    assert info["_final_obs"].tolist() == [False, True, True] and info["final_obs"][0] is None
    assert info["_step_count"].tolist() == [True, False, False] and info["step_count"][0] == 1
    assert info["final_info"]["_step_count"].tolist() == [False, True, True]
    envs.close()


def test_disabled_mode_and_reset_mask():
    envs = make("spread", max_steps=2, autoreset_mode=AutoresetMode.DISABLED)
    assert envs.core.autoreset is False
    envs.reset(seed=0)
    for step in range(2):
        _, _, _, truncated, _ = envs.step(sample(envs, step))
    assert truncated.all()
    mask = np.repeat([True, False, True], 3)
    envs.reset(options={"reset_mask": mask})
    assert envs.core.step_count.tolist() == [0, 2, 0]
    _, _, _, truncated, _ = envs.step(sample(envs, 2))
    assert truncated.tolist() == (~mask).tolist()
    envs.close()


@pytest.mark.parametrize("mask, error, words", [
    (np.ones(9, dtype=bool)[:8], ValueError, r"shape \(9,\).*got shape \(8,\)"),
    (np.ones(9, dtype=np.int64), TypeError, r"reset_mask.*bool"),
    ([True] * 9, TypeError, r"reset_mask.*bool numpy array"),
    (np.array([True, False, True] * 3), ValueError, r"a world resets with all of its agents"),
])
def test_bad_reset_mask_changes_nothing(mask, error, words):
    envs = make("spread")
    envs.reset(seed=0)
    envs.step(sample(envs, 0))
    before = envs.core.get_state()
    with pytest.raises(error, match=words):
        envs.reset(options={"reset_mask": mask})
    after = envs.core.get_state()
    assert all(torch.equal(before[k], after[k]) for k in before)
    envs.close()


def test_unknown_reset_options_are_ignored():
    envs = make()
    obs, _ = envs.reset(seed=0, options={"options": 1})
    again, _ = envs.reset(seed=0)
    assert np.array_equal(obs, again)
    envs.close()


def test_departed_agents_see_black_until_their_world_ends():
    core = make_env(Departing, num_worlds=2, resolution=RES, seed=0, max_steps=4, autoreset="next_step")
    envs = MarlRenderVectorEnv(core)  # entries: world 0 = 0, 1, 2; world 1 = 3, 4, 5
    envs.reset(seed=0)
    zero = np.zeros(6, dtype=np.int64)
    seen = []
    for _ in range(5):
        obs, reward, terminated, truncated, info = envs.step(zero)
        seen.append((obs.reshape(6, -1).any(1).tolist(), terminated.tolist(), truncated.tolist()))
    # prey_0 (entry 1) leaves at step 2, prey_1 (entry 2) at step 3: black from then on,
    # not done until the world's episode ends at step 4 (max_steps), when they are terminated
    # and the predator truncated; step 5 is the reset step.
    on = [True] * 6
    assert seen[0] == (on, [False] * 6, [False] * 6)
    assert seen[1] == ([True, False, True, True, True, True], [False] * 6, [False] * 6)
    assert seen[2] == ([True, False, False, True, True, True], [False] * 6, [False] * 6)
    assert seen[3] == (on, [False, True, True, False, False, False], [True, False, False, True, True, True])
    assert seen[4] == (on, [False] * 6, [False] * 6)
    envs.close()


# ---------------------------------------------------------------------- seeding, errors, render
def test_seeding_is_deterministic():
    envs = make("spread")
    runs = []
    for seed in (7, 7, 8):
        obs, _ = envs.reset(seed=seed)
        trace = [obs]
        for step in range(2):
            trace.append(envs.step(sample(envs, step))[0])
        runs.append(np.stack(trace))
    assert np.array_equal(runs[0], runs[1]) and not np.array_equal(runs[0], runs[2])
    obs, _ = envs.reset(seed=np.int64(7))  # a numpy int seeds like the same int (gymnasium takes Python ints)
    assert np.array_equal(obs, runs[0][0])
    with pytest.raises(TypeError, match="seed must be None or an int.*per-entry"):
        envs.reset(seed=[1, 2, 3])
    envs.close()


def test_bad_actions_raise_and_change_nothing():
    envs = make("spread")
    envs.reset(seed=0)
    before = envs.core.get_state()
    with pytest.raises(ValueError, match=r"actions must be an array of shape \(9,\) \(num_envs = 3 worlds x 3 "
                                         r"agents\), got shape \(3,\)"):
        envs.step(np.zeros(3, dtype=np.int64))
    with pytest.raises(ValueError, match=r"actions must be .* values in \[0, 5\).*got values in \[9, 9\]"):
        envs.step(np.full(9, 9))
    with pytest.raises(TypeError, match="actions"):
        envs.step(np.full(9, 0.5))
    after = envs.core.get_state()
    assert all(torch.equal(before[k], after[k]) for k in before)
    envs.close()


@pytest.mark.parametrize("continuous", [False, True])
def test_actions_with_negative_strides_are_accepted(continuous):
    envs, twin = make("spread", continuous=continuous), make("spread", continuous=continuous)
    envs.reset(seed=0), twin.reset(seed=0)
    actions = sample(envs, 1)[::-1]
    assert actions.strides[0] < 0
    got, expected = envs.step(actions), twin.step(actions.copy())
    assert np.array_equal(got[0], expected[0]) and np.array_equal(got[1], expected[1])
    envs.close(), twin.close()


def test_make_vec_env_arguments():
    with pytest.raises(TypeError, match="does not accept 'autoreset'.*autoreset_mode"):
        make_vec_env("cartpole", autoreset=True)
    with pytest.raises(ValueError, match="autoreset_mode must be a gymnasium.vector.AutoresetMode.*'next'"):
        make_vec_env("cartpole", autoreset_mode="next")
    with pytest.raises(ValueError, match="render_mode must be None or one of"):
        make_vec_env("cartpole", render_mode="human")
    with pytest.raises(ValueError, match="action_mask=True needs a discrete env"):
        make_vec_env("cartpole", continuous=True, action_mask=True)
    envs = make()
    with pytest.raises(RuntimeError, match="call reset"):
        envs.step(np.zeros(W, dtype=np.int64))
    envs.close()
    with pytest.raises(RuntimeError, match="closed"):
        envs.step(np.zeros(W, dtype=np.int64))


def test_render_gives_each_entry_its_world_overview():
    envs = make("spread", num_worlds=2, render_mode="rgb_array")
    envs.reset(seed=0)
    frames = envs.render()
    assert isinstance(frames, tuple) and len(frames) == 6
    assert frames[0].shape == (*envs.core.overview_resolution, 3) and frames[0].dtype == np.uint8
    assert np.array_equal(frames[0], frames[2]) and not np.array_equal(frames[0], frames[3])
    envs.close()
    quiet = make()
    quiet.reset()
    with pytest.warns(UserWarning, match="without a render_mode"):
        assert quiet.render() is None
    quiet.close()


# ---------------------------------------------------------------------- gymnasium's wrappers and checkers
def test_record_episode_statistics_counts_whole_episodes():
    envs = vw.RecordEpisodeStatistics(make("spread", max_steps=4))
    envs.reset(seed=0)
    returns = np.zeros(9)
    for step in range(9):
        _, reward, terminated, truncated, info = envs.step(sample(envs, step))
        returns += reward
        if step in (3, 8):  # episodes of 4 steps, then a reset step that counts in none
            assert info["_episode"].all() and info["episode"]["l"].tolist() == [4] * 9
            assert np.allclose(info["episode"]["r"], returns)
        else:
            assert "episode" not in info
        if step == 4:
            assert (reward == 0).all()
            returns[:] = 0
    assert len(envs.return_queue) == 18
    envs.close()


def test_same_step_record_episode_statistics():
    envs = vw.RecordEpisodeStatistics(make(max_steps=3, autoreset_mode=AutoresetMode.SAME_STEP))
    envs.reset(seed=0)
    total = np.zeros(W)
    for step in range(6):
        _, reward, _, _, info = envs.step(sample(envs, step))
        total += reward
        if step in (2, 5):
            assert info["episode"]["l"].tolist() == [3] * W and np.allclose(info["episode"]["r"], total)
            total[:] = 0
    envs.close()


def test_gymnasium_vector_wrappers_with_defaults():
    envs = make("spread", num_worlds=2)
    envs = vw.RecordEpisodeStatistics(envs)
    envs = vw.GrayscaleObservation(envs)
    envs = vw.DtypeObservation(envs, np.float32)
    envs = vw.TransformObservation(envs, lambda obs: obs / 255.0)
    envs = vw.NormalizeReward(envs)
    envs = vw.ClipReward(envs, -1.0, 1.0)
    envs = vw.DictInfoToList(envs)
    obs, infos = envs.reset(seed=0)
    assert obs.shape == (6, RES, RES) and obs.dtype == np.float32 and isinstance(infos, list)
    for step in range(3):
        obs, reward, terminated, truncated, infos = envs.step(sample(envs, step))
        assert obs.shape == (6, RES, RES) and 0 <= obs.min() and obs.max() <= 1
        assert reward.shape == (6,) and np.abs(reward).max() <= 1
        assert len(infos) == 6 and infos[4]["step_count"] == step + 1
    envs.close()


def test_gymnasium_action_wrappers():
    envs = make("spread", num_worlds=2, continuous=True)
    envs = vw.RescaleAction(envs, min_action=0.0, max_action=2.0)
    envs = vw.ClipAction(envs)
    envs = vw.TransformAction(envs, lambda actions: actions * 10, envs.action_space)
    envs.reset(seed=0)
    obs, reward, *_ = envs.step(np.full((6, 2), 0.5, dtype=np.float32))  # 5 -> clipped to 2 -> rescaled to 1
    assert obs.shape == (6, RES, RES, 3) and reward.shape == (6,)
    with pytest.raises(ValueError, match="actions must be"):
        envs.unwrapped.step(np.full((6, 2), 2.0, dtype=np.float32))  # unwrapped: out of [-1, 1]
    envs.close()


def test_gymnasium_env_checkers():
    envs = make(num_worlds=1)
    env_checker.check_reset_return_type(envs)
    env_checker.check_reset_seed_determinism(envs)
    env_checker.check_reset_options(envs)
    env_checker.check_returned_data_not_reused(envs)  # one entry: its `terminated or truncated` is a bool
    envs.close()


def test_grayscale_vector_env_declares_what_it_returns():
    envs = make_vec_env("cartpole", num_worlds=3, resolution=16, grayscale=True)
    try:
        assert envs.single_observation_space.shape == (16, 16, 1)
        assert envs.observation_space.shape == (3, 16, 16, 1)
        obs, _ = envs.reset(seed=0)
        assert obs.shape == (3, 16, 16, 1) and envs.observation_space.contains(obs)
        obs, *_ = envs.step(envs.action_space.sample())
        assert envs.observation_space.contains(obs)
    finally:
        envs.close()


# ---------------------------------------------------------------------- gymnasium ids and a single-world Env
def test_gymnasium_ids_make_the_vector_envs():
    """`import marl_render.envs` registers marl_render/<name>-v0: make_vec builds make_vec_env (num_envs
    entries = worlds x agents), and the vector env's spec builds it again."""
    from marl_render.envs import list_envs

    assert all(f"marl_render/{name}-v0" in gymnasium.registry for name in list_envs())
    envs = gymnasium.make_vec("marl_render/spread-v0", num_envs=6, resolution=RES, seed=0)
    assert isinstance(envs, MarlRenderVectorEnv) and (envs.num_worlds, envs.num_agents) == (2, 3)
    assert envs.spec.id == "marl_render/spread-v0" and envs.observation_space.shape == (6, RES, RES, 3)
    obs, _ = envs.reset(seed=0)
    twin = make("spread", num_worlds=2)
    assert twin.spec.id == "marl_render/spread-v0" and twin.spec.kwargs["num_envs"] == 6
    again = gymnasium.make_vec(twin.spec)
    for other in (twin, again):
        assert np.array_equal(other.reset(seed=0)[0], obs)
        other.close()
    envs.close()
    with pytest.raises(ValueError, match="num_envs must be a multiple of num_agents=3 for 'spread'.*got 4"):
        gymnasium.make_vec("marl_render/spread-v0", num_envs=4)


def test_single_world_gym_env_passes_gymnasiums_checker():
    import warnings

    from marl_render.envs import make_gym_env

    for kwargs in ({}, {"continuous": True}, {"render_mode": "rgb_array"}):
        env = make_gym_env("cartpole", resolution=RES, **kwargs)
        assert isinstance(env, gymnasium.Env) and env.spec.id == "marl_render/cartpole-v0"
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # not even a warning
            env_checker.check_env(env)
        env.close()
    made = gymnasium.make("marl_render/cartpole-v0", resolution=RES, max_steps=2)
    env_checker.check_env(made.unwrapped)
    core = make_env("cartpole", num_worlds=1, resolution=RES, max_steps=2)
    obs, info = made.reset(seed=4)
    assert obs.shape == (RES, RES, 3) and obs.dtype == np.uint8 and info == {}
    assert np.array_equal(obs, core.reset(seed=4)["pixels"][0, 0].numpy())
    for step in range(2):
        obs, reward, terminated, truncated, info = made.step(1)
        want, want_reward, *_ = core.step(torch.ones(1, 1, dtype=torch.int64))
        assert np.array_equal(obs, want["pixels"][0, 0].numpy()) and reward == float(want_reward[0, 0])
        assert info["step_count"] == step + 1 and (terminated, truncated) == (False, step == 1)
    made.close(), core.close()
    with pytest.raises(ValueError, match="make_gym_env needs a single-agent env, and 'spread' has 3 agents"):
        gymnasium.make("marl_render/spread-v0")
