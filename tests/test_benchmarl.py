"""BenchMARL tasks (marl_render/wrappers/benchmarl.py): one task per env, the specs BenchMARL
reads, and MAPPO with a CNN for a few iterations. Skipped where BenchMARL is not installed;
`make test-benchmarl` builds a venv with BenchMARL and the torchrl it pins and runs them."""
from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

pytest.importorskip("benchmarl", reason="BenchMARL is not installed (make test-benchmarl runs these tests)")

from benchmarl.algorithms import MappoConfig  # noqa: E402
from benchmarl.experiment import Experiment, ExperimentConfig  # noqa: E402
from benchmarl.models import CnnConfig  # noqa: E402
from torchrl.envs import StepCounter, TransformedEnv  # noqa: E402

from marl_render.envs import list_envs, registry  # noqa: E402
from marl_render.envs.spread import Spread  # noqa: E402
from marl_render.wrappers.benchmarl import MarlRenderTask, MarlRenderTaskClass, task_for  # noqa: E402
from marl_render.wrappers.torchrl import MarlRenderTorchRLEnv  # noqa: E402

RES = 16
pytestmark = pytest.mark.usefixtures("single_torch_thread")


def test_one_task_per_env():
    assert sorted(task.name.lower() for task in MarlRenderTask) == sorted(list_envs())
    task = MarlRenderTask.TAG.get_task()
    assert isinstance(task, MarlRenderTaskClass) and task.config == {} and task.env_name() == "marl_render"
    assert task.supports_discrete_actions() and task.supports_continuous_actions()


@pytest.mark.parametrize("name", list_envs())
def test_task_specs_are_the_env_specs(name):
    task = getattr(MarlRenderTask, name.upper()).get_task(config={"resolution": RES, "max_steps": 7})
    env = task.get_env_fun(num_envs=3, continuous_actions=False, seed=7, device="cpu")()
    assert isinstance(env, MarlRenderTorchRLEnv) and env.batch_size == (3,)
    assert env.core.seed == 7 and not env.core.continuous
    wrapped = TransformedEnv(env, StepCounter())  # BenchMARL hands its transformed env to the task
    assert task.max_steps(wrapped) == 7
    assert task.group_map(wrapped) == env.group_map
    obs, masks = task.observation_spec(wrapped), task.action_mask_spec(wrapped)
    assert set(obs.keys()) == set(masks.keys()) == set(env.group_map)
    for group, names in env.group_map.items():
        N = len(names)
        assert list(obs[group].keys()) == ["pixels"]  # the model input: no flags, no mask
        assert obs[group, "pixels"].shape == (N, RES, RES, 3) and obs[group, "pixels"].dtype == torch.uint8
        assert list(masks[group].keys()) == ["action_mask"]
        assert masks[group, "action_mask"].shape == (N, env.core.num_actions)
    assert task.action_spec(wrapped) == env.full_action_spec_unbatched
    assert task.state_spec(wrapped) is None and task.info_spec(wrapped) is None
    env.close()


def test_continuous_actions_and_state_inputs():
    task = MarlRenderTask.SPREAD.get_task(config={"resolution": RES, "state_obs": True})
    env = task.get_env_fun(num_envs=2, continuous_actions=True, seed=0, device="cpu")()
    assert env.core.continuous and task.action_mask_spec(env) is None
    obs = task.observation_spec(env)
    assert sorted(obs["agents"].keys()) == ["pixels", "state"]
    assert obs["agents", "state"].shape == (3, env.core.state_dim)
    assert task.action_spec(env)["agents", "action"].shape == (3, 2)
    env.close()


def test_env_fun_pickles_and_config_cannot_override_benchmarl():
    task = MarlRenderTask.PUSH.get_task(config={"resolution": RES})
    fun = pickle.loads(pickle.dumps(task.get_env_fun(num_envs=2, continuous_actions=False, seed=1, device="cpu")))
    env = fun()
    assert env.batch_size == (2,) and env.core.resolution == (RES, RES)
    env.close()
    for key in ("num_worlds", "continuous", "seed", "device", "autoreset"):
        bad = MarlRenderTask.PUSH.get_task(config={"resolution": RES, key: 1})
        with pytest.raises(ValueError, match=rf"may not set \['{key}'\]"):
            bad.get_env_fun(num_envs=2, continuous_actions=False, seed=1, device="cpu")


def test_render_callback_is_world_zero_from_above():
    task = MarlRenderTask.SPREAD.get_task(config={"resolution": RES})
    env = task.get_env_fun(num_envs=2, continuous_actions=False, seed=3, device="cpu")()
    wrapped = TransformedEnv(env, StepCounter())
    wrapped.reset()
    frame = MarlRenderTaskClass.render_callback(None, wrapped, None)
    assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.shape == (128, 128, 3)
    assert np.array_equal(frame, env.render_overview()[0].numpy())
    try:
        import torchvision  # noqa: F401
        videos = True
    except (ImportError, RuntimeError):
        videos = False
    if videos:
        assert task.has_render(wrapped)
    else:
        with pytest.warns(UserWarning, match="no evaluation videos, torchvision does not import"):
            assert not task.has_render(wrapped)
    env.close()


@pytest.mark.parametrize("name", ["SPREAD", "TAG"])  # one group; two teams with agents that leave
def test_mappo_with_a_cnn_trains_and_logs_the_statistics(name, tmp_path):
    config = ExperimentConfig.get_from_yaml()
    config.loggers = ["csv"]
    config.create_json = False
    config.save_folder = str(tmp_path)
    config.max_n_iters = 2
    config.on_policy_n_envs_per_worker = 4
    config.on_policy_collected_frames_per_batch = 4 * 20  # 20 steps of 4 worlds
    config.on_policy_n_minibatch_iters = 1
    config.on_policy_minibatch_size = 40
    config.evaluation_interval = 80
    config.evaluation_episodes = 2
    task = getattr(MarlRenderTask, name).get_task(config={"resolution": RES, "max_steps": 10})
    experiment = Experiment(task=task, algorithm_config=MappoConfig.get_from_yaml(),
                            model_config=CnnConfig.get_from_yaml(), critic_model_config=CnnConfig.get_from_yaml(),
                            seed=0, config=config)
    groups = list(experiment.group_map)
    before = {g: torch.nn.utils.parameters_to_vector(experiment.losses[g].parameters()).clone() for g in groups}
    experiment.run()
    assert experiment.n_iters_performed == 2 and experiment.total_frames == 160
    for group in groups:
        after = torch.nn.utils.parameters_to_vector(experiment.losses[group].parameters())
        assert not torch.equal(after, before[group]), group  # the optimiser stepped
    scalars = {p.stem for p in tmp_path.rglob("scalars/*.csv")}
    core_keys = {"SPREAD": ("collisions", "coverage"), "TAG": ("caught", "prey_left")}[name]
    for key in core_keys:
        assert f"collection_info_{key}" in scalars
    for group in groups:
        assert f"train_{group}_loss_objective" in scalars
    assert "eval_reward_episode_reward_mean" in scalars


class OwnTask(Spread):
    """A user's task, defined here and not in the package: spread under another name and team."""

    name = "own_task"

    def setup(self):
        super().setup()
        self.teams = {"scouts": [f"scout_{i}" for i in range(self.num_agents)]}


def test_a_registered_task_of_ones_own_is_a_benchmarl_task():
    registry.register_env("own_task", OwnTask, overwrite=True)
    try:
        task = task_for("own_task", {"resolution": RES, "max_steps": 5})
        assert isinstance(task, MarlRenderTaskClass) and task.name == "OWN_TASK"
        create = task.get_env_fun(num_envs=2, continuous_actions=False, seed=1, device="cpu")
        env = pickle.loads(pickle.dumps(create))()  # BenchMARL may hand the factory to workers
        assert task.group_map(env) == {"scouts": ["scout_0", "scout_1", "scout_2"]}
        assert task.observation_spec(env)["scouts", "pixels"].shape == (3, RES, RES, 3)
        rollout = env.rollout(5)
        assert rollout["next", "scouts", "reward"].shape == (2, 5, 3, 1)
        env.close()
        with pytest.raises(ValueError, match="no single registered environment is named 'nope'"):
            task_for("nope")
    finally:
        registry._REGISTRY.pop("own_task", None)


def test_the_readme_snippet_runs_as_written(tmp_path):
    """docs/benchmarl.md's BenchMARL block, copied as is: csv logs (no wandb), done in a few minutes."""
    from readme_snippets import run_snippet, side_venv_snippets

    (where, code), = side_venv_snippets("benchmarl")
    result = run_snippet(code, tmp_path, timeout=240)
    assert result.returncode == 0, f"{where}:\n{result.stderr[-3000:]}"
    rewards = list(tmp_path.rglob("scalars/collection_reward_episode_reward_mean.csv"))
    assert len(rewards) == 1 and len(rewards[0].read_text().splitlines()) == 3  # one row per iteration
    assert list(tmp_path.rglob("scalars/eval_reward_episode_reward_mean.csv"))
