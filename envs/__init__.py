"""marl_render.envs: the environment suite (top-level folder envs/ of the repository).

    from marl_render.envs import list_envs, make_env
    env = make_env("spread", num_worlds=256, num_agents=4, resolution=64)
    obs = env.reset(seed=0)                      # obs["pixels"]: uint8 [W, A, H, Wpx, 3]
    obs, reward, terminated, truncated, info = env.step(actions)

make_env returns the batched core (BatchedEnv, the driver: see envs/core.py); the front ends
(make_parallel_env, make_aec_env, make_vec_env, make_gym_env, make_sb3_env, make_torchrl_env,
make_jax_env) wrap it. A task is a Scenario (envs/scenario.py) or, for agents on a floor, an
ArenaScenario (envs/arena.py); register_env makes one known to all front ends, and
docs/authoring.md builds one step by step. Importing this package registers the gymnasium ids
"marl_render/<name>-v0" of the built-in tasks (see marl_render/wrappers/gymnasium.py).
"""
from .arena import ArenaScenario, ArenaState, Prop, Static
from .core import BatchedEnv
from .episodes import EpisodeEnd
from .focal import FocalEnv, Population
from .multiprocess import MultiProcessEnv
from .options import EnvOptions
from .registry import env_class, list_envs, make_env, register_env
from .scenario import BatchShape, Layout, NoParams, Scenario, Step, VectorObs, numbered
from .spec import OBS_KEYS, ActionSpec, ArraySpec, EnvSpec

__all__ = ["ActionSpec", "ArenaScenario", "ArenaState", "ArraySpec", "BatchShape", "BatchedEnv", "EnvOptions",
           "EnvSpec", "FocalEnv", "Layout", "MultiProcessEnv", "NoParams", "OBS_KEYS", "Population", "Prop", "Scenario",
           "Static", "Step", "env_class", "list_envs", "make_env", "numbered", "register_env", "EpisodeEnd",
           "VectorObs"]

# The front ends (marl_render/wrappers/) are exported lazily, so that importing
# marl_render.envs never imports pettingzoo or torchrl: public name -> "module:attribute".
_LAZY_EXPORTS: dict = {
    "make_parallel_env": "marl_render.wrappers.pettingzoo:make_parallel_env",
    "make_aec_env": "marl_render.wrappers.pettingzoo:make_aec_env",
    "make_torchrl_env": "marl_render.wrappers.torchrl:make_torchrl_env",
    "make_jax_env": "marl_render.wrappers.jax:make_jax_env",
    "make_vec_env": "marl_render.wrappers.gymnasium:make_vec_env",
    "make_sb3_env": "marl_render.wrappers.sb3:make_sb3_env",
    "make_gym_env": "marl_render.wrappers.gymnasium:make_gym_env",
}
__all__ += list(_LAZY_EXPORTS)


def __getattr__(name):
    target = _LAZY_EXPORTS.get(name)
    if target is None:
        raise AttributeError(f"module 'marl_render.envs' has no attribute {name!r}")
    import importlib

    module, attribute = target.split(":")
    value = getattr(importlib.import_module(module), attribute)
    globals()[name] = value
    return value
