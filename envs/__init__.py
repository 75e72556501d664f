"""marl_render.envs: the environment suite (top-level folder envs/ of the repository).

    from marl_render.envs import list_envs, make_env
    env = make_env("spread", num_worlds=256, num_agents=4, resolution=64)
    obs = env.reset(seed=0)                      # obs["pixels"]: uint8 [W, A, H, Wpx, 3]
    obs, reward, terminated, truncated, info = env.step(actions)

make_env returns the batched core (BatchedEnv, see envs/core.py). The front ends
(make_parallel_env, make_aec_env, make_vec_env, make_gym_env, make_sb3_env, make_torchrl_env,
make_jax_env) wrap that core. Importing this package registers the gymnasium ids
"marl_render/<name>-v0" (see marl_render/wrappers/gymnasium.py).
"""
from .core import OBS_KEYS, BatchedEnv
from .registry import env_class, list_envs, make_env, register

__all__ = ["BatchedEnv", "OBS_KEYS", "env_class", "list_envs", "make_env", "register"]

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


def _register_gymnasium_ids() -> None:
    """gymnasium ids "marl_render/<name>-v0" of the suite's envs, so that after ``import
    marl_render.envs``, ``gymnasium.make_vec(id, num_envs=N)`` builds make_vec_env (N entries =
    worlds x agents) and, for single-agent envs, ``gymnasium.make(id)`` builds make_gym_env.
    Strings, not imports: no env module or front end is loaded here."""
    from gymnasium.envs.registration import register as register_id
    from gymnasium.envs.registration import registry as ids

    for name in list_envs():
        env_id = f"marl_render/{name}-v0"
        if env_id not in ids:  # importing twice (a reload) must not warn about overriding
            register_id(env_id, entry_point="marl_render.wrappers.gymnasium:make_gym_env",
                        vector_entry_point="marl_render.wrappers.gymnasium:gymnasium_vector_entry_point",
                        kwargs={"name": name})


_register_gymnasium_ids()
