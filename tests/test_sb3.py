"""Stable-Baselines3 front end (marl_render/wrappers/sb3.py); skipped without the `sb3` extra."""
from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch

sb3 = pytest.importorskip("stable_baselines3")
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.evaluation import evaluate_policy  # noqa: E402
from stable_baselines3.common.vec_env import VecCheckNan, VecFrameStack, VecMonitor, VecTransposeImage  # noqa: E402

from marl_render.envs import make_env, make_sb3_env  # noqa: E402
from marl_render.wrappers.sb3 import NATURE_CNN_MIN_SIZE, SmallImageCNN  # noqa: E402

W = 4
RES = 40  # SB3's NatureCNN needs images of at least 36 x 36


def make(name="cartpole", **kw):
    kw.setdefault("num_worlds", W)
    kw.setdefault("resolution", RES)
    kw.setdefault("seed", 0)
    return make_sb3_env(name, **kw)


def test_ppo_cnn_policy_trains_from_pixels():
    venv = VecMonitor(make(max_steps=16))
    model = PPO("CnnPolicy", venv, n_steps=32, batch_size=64, n_epochs=1, seed=0, device="cpu")
    assert isinstance(model.get_env(), VecTransposeImage)  # SB3 recognised the uint8 HWC images
    assert model.observation_space.shape == (3, RES, RES)
    model.learn(total_timesteps=256)
    assert model.num_timesteps == 256
    assert len(model.ep_info_buffer) == 256 // 16 and {e["l"] for e in model.ep_info_buffer} == {16}
    obs = model.get_env().reset()
    assert obs.shape == (W, 3, RES, RES) and obs.dtype == np.uint8
    actions, _ = model.predict(obs, deterministic=True)
    assert actions.shape == (W,) and actions.dtype.kind == "i" and ((0 <= actions) & (actions < 5)).all()
    mean, std = evaluate_policy(model, model.get_env(), n_eval_episodes=W)
    assert 0 < mean <= 16 and np.isfinite(std)  # reward per step is in [0, 1]
    venv.close()


def test_multi_agent_ppo_shares_one_policy():
    venv = VecMonitor(make("spread", num_worlds=2, max_steps=8))
    assert venv.num_envs == 6
    model = PPO("CnnPolicy", venv, n_steps=16, batch_size=48, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=96)
    actions, _ = model.predict(model.get_env().reset())
    assert actions.shape == (6,)
    venv.close()


def test_step_gives_terminal_observation_and_time_limit_flag():
    venv = make(max_steps=2)
    core = make_env("cartpole", num_worlds=W, resolution=RES, seed=0, max_steps=2)  # no auto-reset
    venv.seed(3)
    obs = venv.reset()
    want = core.reset(seed=3)
    assert np.array_equal(obs, want["pixels"][:, 0].numpy())
    actions = np.arange(W) % 5
    for _ in range(2):
        obs, rewards, dones, infos = venv.step(actions)
        want, *_ = core.step(torch.from_numpy(actions)[:, None])
    assert dones.all() and rewards.dtype == np.float32 and len(infos) == W
    for i in range(W):
        assert np.array_equal(infos[i]["terminal_observation"], want["pixels"][i, 0].numpy())
        assert infos[i]["TimeLimit.truncated"] is True
    first = core.reset_worlds(torch.ones(W, dtype=torch.bool))
    assert np.array_equal(obs, first["pixels"][:, 0].numpy())  # already the new episode
    obs, _, dones, infos = venv.step(actions)
    assert not dones.any() and infos == [{}] * W
    venv.close(), core.close()


def test_sb3_vec_wrappers():
    venv = VecCheckNan(VecTransposeImage(VecFrameStack(VecMonitor(make(max_steps=3)), n_stack=4)),
                       raise_exception=True)
    obs = venv.reset()
    assert obs.shape == (W, 12, RES, RES)
    for _ in range(3):
        obs, rewards, dones, infos = venv.step(np.zeros(W, dtype=np.int64))
    assert dones.all() and obs.shape == (W, 12, RES, RES)
    assert infos[0]["terminal_observation"].shape == (12, RES, RES) and infos[0]["episode"]["l"] == 3
    venv.close()


def test_attribute_access_and_bad_arguments():
    venv = make()
    assert venv.get_attr("num_worlds") == [W] * W and venv.get_attr("max_steps", [0, 1]) == [1000, 1000]
    assert venv.env_is_wrapped(object) == [False] * W
    assert venv.seed(5) == [5, 6, 7, 8]
    with pytest.raises(RuntimeError, match="step_async"):
        venv.step_wait()
    with pytest.raises(ValueError, match=r"actions must be an array of shape \(4,\)"):
        venv.reset(), venv.step(np.zeros(3, dtype=np.int64))
    venv.close()
    with pytest.raises(TypeError, match="autoreset_mode"):
        make(autoreset_mode="NextStep")


def test_grayscale_declares_and_returns_one_channel():
    """The front ends take the channel count from the driver's spec (it was hard-coded to 3)."""
    venv = make_sb3_env("spread", num_worlds=2, resolution=36, grayscale=True)  # 36 px: NatureCNN's smallest
    try:
        assert venv.observation_space.shape == (36, 36, 1)
        obs = venv.reset()
        assert obs.shape == (6, 36, 36, 1) and obs.dtype == np.uint8
        assert venv.observation_space.contains(obs[0])
        obs, reward, done, infos = venv.step(np.zeros(6, dtype=np.int64))
        assert obs.shape == (6, 36, 36, 1)
        PPO("CnnPolicy", VecTransposeImage(venv), n_steps=8, batch_size=24, n_epochs=1, device="cpu").learn(16)
    finally:
        venv.close()


def test_seed_takes_one_int_and_says_so_otherwise():
    venv = make()
    assert venv.seed(np.int64(5)) == [5, 6, 7, 8]
    with pytest.raises(TypeError, match=r"seed must be None or one int .*got \[1, 2\]"):
        venv.seed([1, 2])
    seeds = venv.seed(None)  # a random seed, then seed + i per entry
    assert seeds[1] == seeds[0] + 1
    twin = make()
    venv.seed(np.int64(9)), twin.seed(9)
    assert np.array_equal(venv.reset(), twin.reset())
    venv.close(), twin.close()


def test_set_options_reach_the_next_reset():
    venv = make()
    venv.reset()
    for _ in range(3):
        venv.step(np.zeros(W, dtype=np.int64))
    mask = np.array([True, False, False, True])
    venv.set_options({"reset_mask": mask})
    venv.reset()
    assert venv.get_attr("step_count")[0].tolist() == [0, 3, 3, 0]
    venv.set_options([{"reset_mask": mask.copy()} for _ in range(W)])  # the same for every entry: fine
    venv.reset()  # the options are used once, as in SB3
    assert venv.get_attr("step_count")[0].tolist() == [0, 3, 3, 0]
    venv.reset()
    assert venv.get_attr("step_count")[0].tolist() == [0, 0, 0, 0]
    with pytest.raises(ValueError, match="options must be the same for every entry"):
        venv.set_options([{"reset_mask": mask}, {}, {}, {}])
    with pytest.raises(ValueError, match="list of 4 dicts"):
        venv.set_options([{}])
    with pytest.raises(TypeError, match="options must be None, a dict"):
        venv.set_options("reset")
    venv.close()


def test_indices_out_of_range_raise():
    venv = make()
    assert venv.get_attr("num_worlds", -1) == [W]
    for call in (lambda: venv.get_attr("num_worlds", indices=[99]), lambda: venv.set_attr("x", 1, indices=[0, 4]),
                 lambda: venv.env_method("__repr__", indices=99), lambda: venv.env_is_wrapped(object, [-5])):
        with pytest.raises(IndexError, match=r"indices must be in \[0, 4\) \(num_envs = 4\)"):
            call()
    with pytest.raises(TypeError, match="indices must be"):
        venv.get_attr("num_worlds", indices=[0.5])
    assert not hasattr(venv.venv, "x")
    venv.close()


def test_default_cnn_policy_needs_36_pixels_a_side():
    """What the SB3 docs here say (marl_render/wrappers/sb3.py, docs/sb3.md): NatureCNN takes 36 x 36, not 35."""
    for resolution, fits in ((NATURE_CNN_MIN_SIZE, True), ((48, NATURE_CNN_MIN_SIZE - 1), False)):
        venv = make_sb3_env("cartpole", num_worlds=1, resolution=resolution)
        try:
            if fits:
                PPO("CnnPolicy", venv, n_steps=8, batch_size=8, device="cpu")
            else:
                with pytest.raises(RuntimeError, match="Kernel size can't be greater than actual input size"):
                    PPO("CnnPolicy", venv, n_steps=8, batch_size=8, device="cpu")
        finally:
            venv.close()


def test_small_image_cnn_trains_ppo_at_16_pixels():
    venv = VecMonitor(make_sb3_env("spread", num_worlds=2, resolution=16, max_steps=8, seed=0))
    model = PPO("CnnPolicy", venv, n_steps=16, batch_size=48, n_epochs=1, seed=0, device="cpu",
                policy_kwargs={"features_extractor_class": SmallImageCNN,
                               "features_extractor_kwargs": {"features_dim": 64}})
    extractor = model.policy.features_extractor
    assert isinstance(extractor, SmallImageCNN) and extractor.features_dim == 64
    obs = torch.as_tensor(model.get_env().reset()).float() / 255
    assert obs.shape == (6, 3, 16, 16) and extractor(obs).shape == (6, 64)
    before = [p.detach().clone() for p in extractor.parameters()]
    model.learn(total_timesteps=96)  # one rollout of 16 steps x 6 entries, then one epoch of updates
    assert model.num_timesteps == 96 and len(model.ep_info_buffer) == 96 // 8
    assert any(not torch.equal(a, b) for a, b in zip(before, extractor.parameters(), strict=True))  # it learned
    actions, _ = model.predict(model.get_env().reset())
    assert actions.shape == (6,)
    venv.close()


def test_small_image_cnn_takes_8_pixels_and_refuses_fewer():
    image = gymnasium.spaces.Box(0, 255, (3, 8, 8), np.uint8)
    assert SmallImageCNN(image, features_dim=16)(torch.zeros(2, 3, 8, 8)).shape == (2, 16)
    with pytest.raises(ValueError, match="at least 8 x 8 pixels, got 7 x 12"):
        SmallImageCNN(gymnasium.spaces.Box(0, 255, (3, 7, 12), np.uint8))
    with pytest.raises(ValueError, match="observation_space must be an image Box"):
        SmallImageCNN(gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32))
