"""Front ends of the batched environment core (envs/core.py) for RL libraries.

    from marl_render.wrappers import make_parallel_env, make_torchrl_env, make_vec_env, make_sb3_env
    env = make_parallel_env("spread", resolution=32)                # pettingzoo.ParallelEnv, one world
    env = make_torchrl_env("spread", num_worlds=64, group_map="team") # torchrl EnvBase, batch_size [64]
    env = make_vec_env("spread", num_worlds=64)                     # gymnasium VectorEnv, 64 x 3 entries
    env = make_sb3_env("cartpole", num_worlds=64)                   # stable-baselines3 VecEnv, 64 entries

Each module imports its library (pettingzoo, torchrl, gymnasium, stable_baselines3); names
are resolved lazily so that importing ``marl_render.wrappers`` imports none of them until
one is used.

What they share (building and closing the core, the checks of their own arguments, the choice of
observation keys, the level guard and the reset dispatch) is written once, in ``common.py``.
"""
from __future__ import annotations

import importlib

_LAZY_EXPORTS = {
    "MarlRenderParallelEnv": "marl_render.wrappers.pettingzoo",
    "make_parallel_env": "marl_render.wrappers.pettingzoo",
    "MarlRenderTorchRLEnv": "marl_render.wrappers.torchrl",
    "make_torchrl_env": "marl_render.wrappers.torchrl",
    "MarlRenderVectorEnv": "marl_render.wrappers.gymnasium",
    "make_vec_env": "marl_render.wrappers.gymnasium",
    "MarlRenderSB3VecEnv": "marl_render.wrappers.sb3",
    "make_sb3_env": "marl_render.wrappers.sb3",
    "make_rllib_env": "marl_render.wrappers.rllib",
}

__all__ = list(_LAZY_EXPORTS)


def __getattr__(name):
    module = _LAZY_EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'marl_render.wrappers' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
