"""RLlib front end (marl_render/wrappers/rllib.py): the env creator and its float pixels run
everywhere; PPO on RLlib and docs/rllib.md's block run where Ray is installed, which
`make test-rllib` arranges in .venv-rllib (Ray pins gymnasium 1.2.2, the main venv has 1.4.0)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from marl_render.wrappers.gymnasium import make_vec_env
from marl_render.wrappers.rllib import FloatPixels, make_rllib_env

RES = 16
pytestmark = pytest.mark.usefixtures("single_torch_thread")


class Context(dict):
    """RLlib's EnvContext: a dict with the EnvRunner's worker_index."""
    worker_index = 2


def test_pixels_are_the_vector_envs_as_float32_in_0_1():
    envs = make_rllib_env(Context(env="spread", num_worlds=2, resolution=RES, seed=5, num_envs=6))
    plain = make_vec_env("spread", 2, resolution=RES, seed=7)  # seed 5 + worker_index 2
    assert isinstance(envs, FloatPixels) and envs.num_envs == 6
    space = envs.single_observation_space
    assert space.dtype == np.float32 and space.shape == (RES, RES, 3) and space.low.min() == 0 and space.high.max() == 1
    obs, _ = envs.reset(seed=3)
    want, _ = plain.reset(seed=3)
    assert obs.dtype == np.float32 and obs.shape == (6, RES, RES, 3) and obs in envs.observation_space
    np.testing.assert_allclose(obs, want / 255.0, atol=1e-6)
    actions = np.arange(6) % envs.single_action_space.n
    obs, reward, *_ = envs.step(actions)
    want, want_reward, *_ = plain.step(actions)
    np.testing.assert_allclose(obs, want / 255.0, atol=1e-6)
    np.testing.assert_array_equal(reward, want_reward)
    envs.close()
    plain.close()


def test_dict_observations_convert_only_the_pixels():
    envs = make_rllib_env(Context(env="cartpole", num_worlds=2, resolution=RES, depth=True, seed=None))
    obs, _ = envs.reset(seed=0)
    assert obs["pixels"].dtype == np.float32 and obs["pixels"].max() <= 1.0
    assert obs["depth"].dtype == envs.env.single_observation_space["depth"].dtype
    assert obs in envs.observation_space
    envs.close()


def test_bad_env_config_is_refused_naming_it():
    with pytest.raises(TypeError, match="env_config must be a mapping"):
        make_rllib_env("spread")
    with pytest.raises(ValueError, match="under 'env'"):
        make_rllib_env({"num_worlds": 2})
    with pytest.raises(ValueError, match=r"num_envs_per_env_runner must be num_worlds x num_agents = 6 .* got 4"):
        make_rllib_env({"env": "spread", "num_worlds": 2, "resolution": RES, "num_envs": 4})


def ppo_config(env: str, worlds: int, agents: int, runners: int):
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

    steps = 10
    return (PPOConfig()
            .environment("marl_render_test", env_config={"env": env, "num_worlds": worlds, "resolution": RES,
                                                         "max_steps": steps})
            .env_runners(num_env_runners=runners, num_envs_per_env_runner=worlds * agents,
                         gym_env_vectorize_mode="vector_entry_point")
            .training(train_batch_size_per_learner=worlds * agents * steps, minibatch_size=30, num_epochs=1)
            .rl_module(model_config=DefaultModelConfig(conv_filters=[[8, 4, 2], [16, 3, 2]], fcnet_hiddens=[32]))
            .debugging(seed=0))


@pytest.mark.parametrize(("env", "worlds", "agents", "runners"), [("spread", 2, 3, 1), ("cartpole", 4, 1, 0)])
def test_ppo_trains_one_iteration_on_batched_worlds(env, worlds, agents, runners):
    pytest.importorskip("ray.rllib", reason="RLlib is not installed (make test-rllib runs these tests)")
    import ray
    from ray.tune.registry import register_env

    register_env("marl_render_test", make_rllib_env)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    algo = ppo_config(env, worlds, agents, runners).build_algo()
    try:
        module = algo.get_module()
        before = torch.nn.utils.parameters_to_vector(module.parameters()).clone()
        result = algo.train()
        after = torch.nn.utils.parameters_to_vector(algo.get_module().parameters())
    finally:
        algo.stop()
    runners_result = result["env_runners"]
    assert runners_result["num_env_steps_sampled"] >= worlds * agents * 10
    assert runners_result["episode_len_mean"] == 10  # every entry played whole 10-step episodes
    assert runners_result["num_episodes"] >= worlds * agents
    assert np.isfinite(runners_result["episode_return_mean"])
    assert not torch.equal(before, after)  # the learner stepped


def test_the_readme_snippet_runs_as_written(tmp_path):
    pytest.importorskip("ray.rllib", reason="RLlib is not installed (make test-rllib runs these tests)")
    from readme_snippets import run_snippet, side_venv_snippets

    (where, code), = side_venv_snippets("rllib")
    result = run_snippet(code, tmp_path, timeout=240)
    assert result.returncode == 0, f"{where}:\n{result.stderr[-3000:]}"
    assert np.isfinite(float(result.stdout.strip().splitlines()[-1]))
