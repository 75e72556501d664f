"""BenchMARL tasks: every environment of the suite as a ``benchmarl`` task (BenchMARL is optional).

    from benchmarl.algorithms import MappoConfig
    from benchmarl.experiment import Experiment, ExperimentConfig
    from benchmarl.models import CnnConfig
    from marl_render.wrappers.benchmarl import MarlRenderTask

    task = MarlRenderTask.SPREAD.get_task(config={"resolution": 32, "max_steps": 50})
    experiment = Experiment(task=task, algorithm_config=MappoConfig.get_from_yaml(),
                            model_config=CnnConfig.get_from_yaml(), critic_model_config=CnnConfig.get_from_yaml(),
                            seed=0, config=ExperimentConfig.get_from_yaml())
    experiment.run()

One enum member per built-in env (``MarlRenderTask.CARTPOLE``, ``SPREAD``, ...); a task of
the user's own, registered with ``register_env``, is ``task_for("my_task", config)``. A
task's ``config`` holds the env's keyword arguments (``resolution``,
``num_agents``, ``max_steps``, ``state_obs``, ``group_map``, the env's own ones; see
``make_torchrl_env``); an empty config gives the env's defaults. BenchMARL itself chooses the
number of worlds (``num_envs``), discrete or continuous actions, the seed and the device, so
those may not be in the config. ``get_task()`` without a config gives the defaults (these
tasks have no yaml file in BenchMARL's own conf folder); BenchMARL's hydra command line does
not know them: use the Python API as above.

What BenchMARL sees, per group: the model inputs are ``pixels`` (uint8 [N, H, W, 3], which
BenchMARL's CNN reads as images), ``state`` when ``state_obs=True`` and ``lidar`` with
``lidar=rays``; the action mask is ``action_mask`` (discrete actions); the per-agent ``done`` /
``terminated`` flags are used by the losses (agents leave the episode in tag). The episode
statistics at ``("info", name)`` are logged as ``collection/info/<name>``. Evaluation videos
show world 0 from the overview camera; BenchMARL's loggers write them with torchvision, so
without torchvision (no CPU wheel on PyPI) ``has_render`` is False and a warning says so. Depth
is not a model input here (BenchMARL's CNN wants channels-last images).

Works with the torchrl that BenchMARL pins (``make test-benchmarl`` builds that venv).
"""
from __future__ import annotations

import functools
import warnings

from benchmarl.environments.common import Task, TaskClass
from torchrl.data import Composite

from marl_render.envs import list_envs
from marl_render.wrappers.torchrl import MarlRenderTorchRLEnv, make_torchrl_env

# Set by BenchMARL through get_env_fun, never by a task's config.
CHOSEN_BY_BENCHMARL = ("num_worlds", "continuous", "seed", "device", "autoreset")
MODEL_INPUTS = ("pixels", "state", "lidar")


def _core_env(env) -> MarlRenderTorchRLEnv:
    """The MarlRenderTorchRLEnv under BenchMARL's TransformedEnv wrappers."""
    while not isinstance(env, MarlRenderTorchRLEnv):
        env = env.base_env
    return env


def _per_group(spec: Composite, groups, keep) -> Composite:
    """A copy of `spec` with only its groups, each with only the keys in `keep` (empty groups dropped)."""
    out = Composite(shape=spec.shape, device=spec.device)
    for group in groups:
        entries = {key: spec[group, key].clone() for key in spec[group].keys() if key in keep}
        if entries:
            out[group] = Composite(entries, shape=spec[group].shape, device=spec.device)
    return out


class MarlRenderTaskClass(TaskClass):
    """A marl_render env as a BenchMARL task; ``name`` is the enum member's name (the env's
    name in upper case) and ``config`` the env's keyword arguments."""

    def get_env_fun(self, num_envs, continuous_actions, seed, device):
        chosen = sorted(set(self.config) & set(CHOSEN_BY_BENCHMARL))
        if chosen:
            raise ValueError(f"the task config may not set {chosen}: BenchMARL chooses the number of worlds "
                             f"(num_envs), the action kind, the seed and the device; got config {self.config}")
        # A partial, not a lambda: it pickles, so BenchMARL may hand it to worker processes.
        return functools.partial(make_torchrl_env, _registered_name(self.name), num_worlds=num_envs,
                                 continuous=bool(continuous_actions), seed=seed, device=device, **self.config)

    def supports_continuous_actions(self) -> bool:
        return True

    def supports_discrete_actions(self) -> bool:
        return True

    def max_steps(self, env) -> int:
        return _core_env(env).core.max_steps

    def has_render(self, env) -> bool:
        """True where BenchMARL can write evaluation videos: its loggers encode them with
        torchvision, which has no wheel for a CPU torch on PyPI. Without it BenchMARL would fail
        at the first evaluation, so rendering is turned off with a warning instead."""
        try:
            import torchvision  # noqa: F401
        except (ImportError, RuntimeError) as exc:  # RuntimeError: a CUDA torchvision next to a CPU torch
            warnings.warn(f"marl_render BenchMARL task: no evaluation videos, torchvision does not import "
                          f"({type(exc).__name__}: {exc}); BenchMARL's loggers need it to write videos",
                          stacklevel=2)
            return False
        return True

    def group_map(self, env) -> dict:
        return {group: list(names) for group, names in _core_env(env).group_map.items()}

    def observation_spec(self, env) -> Composite:
        inputs = MODEL_INPUTS + tuple(_core_env(env).core.vector_obs)  # and the task's own vectors (matrix's inventory)
        return _per_group(env.full_observation_spec_unbatched, self.group_map(env), inputs)

    def action_mask_spec(self, env) -> Composite | None:
        spec = _per_group(env.full_observation_spec_unbatched, self.group_map(env), ("action_mask",))
        return None if spec.is_empty() else spec

    def action_spec(self, env) -> Composite:
        return env.full_action_spec_unbatched

    def state_spec(self, env) -> Composite | None:
        return None  # no global state: a centralised critic reads every agent's pixels

    def info_spec(self, env) -> Composite | None:
        return None  # the statistics are per world at the root ("info", name), not per group

    @staticmethod
    def env_name() -> str:
        return "marl_render"

    @staticmethod
    def render_callback(experiment, env, data):
        """uint8 [H, W, 3] numpy: world 0 seen from the overview camera."""
        return _core_env(env).render_overview()[0].cpu().numpy()


class MarlRenderTask(Task):
    """Enum of the suite's envs as BenchMARL tasks (``tests`` check it lists every registered env)."""

    CAPTURE_FLAG = None
    CARTPOLE = None
    COMMONS = None
    FORAGE = None
    PUSH = None
    SPREAD = None
    TAG = None
    SPEAKER_LISTENER = None
    ROOMS = None

    @staticmethod
    def associated_class():
        return MarlRenderTaskClass

    def get_from_yaml(self, path: str | None = None) -> MarlRenderTaskClass:
        """The task with the env's defaults; with `path`, the config read from that yaml file."""
        if path is None:
            return self.get_task(config={})
        return super().get_from_yaml(path)


def task_for(name: str, config: dict | None = None) -> MarlRenderTaskClass:
    """The BenchMARL task of any registered env, a user's own (register_env) included; `config`
    holds its keyword arguments as for the enum's tasks."""
    _registered_name(name.upper())  # an unknown name fails here, listing the known ones
    return MarlRenderTaskClass(name=name.upper(), config=dict(config or {}))


def _registered_name(task_name: str) -> str:
    """The registered env whose name is `task_name` in upper case (BenchMARL's task names)."""
    matches = [name for name in list_envs() if name.upper() == task_name]
    if len(matches) != 1:
        raise ValueError(f"no single registered environment is named {task_name.lower()!r} (BenchMARL task "
                         f"{task_name!r}); known environments: {list_envs()}")
    return matches[0]


__all__ = ["MarlRenderTask", "MarlRenderTaskClass", "task_for"]
