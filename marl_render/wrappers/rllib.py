"""RLlib front end: an env creator for RLlib's new API stack that hands each EnvRunner one
batched vector env (marl_render.wrappers.gymnasium) with float pixels.

    from ray.rllib.algorithms.ppo import PPOConfig
    from marl_render.wrappers.rllib import make_rllib_env
    config = (PPOConfig().environment(make_rllib_env, env_config={"env": "spread", "num_worlds": 8})
              .env_runners(num_envs_per_env_runner=8 * 3, gym_env_vectorize_mode="vector_entry_point"))

With ``gym_env_vectorize_mode="vector_entry_point"`` RLlib calls the creator once per
EnvRunner with ``num_envs`` (its ``num_envs_per_env_runner``) and uses the vector env it
returns as is: one core and one renderer step all ``num_worlds x num_agents`` entries, one
shared policy (entry i is agent i % A of world i // A). Scaling out is RLlib's: more
EnvRunners (``num_env_runners``), each with its own batch of worlds, on a Ray cluster.

RLlib's default CNN takes float input, so pixels come as float32 in [0, 1]
(``Box(0, 1, (H, W, 3), float32)``; depth, when asked for, stays in metres in a Dict).
"""
from __future__ import annotations

from collections.abc import Mapping

import gymnasium
import numpy as np
from gymnasium.vector import VectorObservationWrapper

from marl_render.validation import describe
from marl_render.wrappers.common import closed_on_error
from marl_render.wrappers.gymnasium import make_vec_env


class FloatPixels(VectorObservationWrapper):
    """uint8 pixels [N, H, W, 3] -> float32 in [0, 1] (the key "pixels" of a Dict observation)."""

    def __init__(self, env):
        super().__init__(env)
        space = env.single_observation_space
        pixels = space["pixels"] if isinstance(space, gymnasium.spaces.Dict) else space
        floats = gymnasium.spaces.Box(0.0, 1.0, pixels.shape, np.float32)
        if isinstance(space, gymnasium.spaces.Dict):
            self.single_observation_space = gymnasium.spaces.Dict({**space.spaces, "pixels": floats})
        else:
            self.single_observation_space = floats
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, env.num_envs)

    def observations(self, observations):
        if isinstance(observations, dict):
            return {**observations, "pixels": self.observations(observations["pixels"])}
        return observations.astype(np.float32) * np.float32(1 / 255)


def make_rllib_env(env_config: Mapping) -> FloatPixels:
    """RLlib env creator. env_config (RLlib's ``env_config``, an EnvContext): "env" (the
    registered name), "num_worlds" (default 1) and any argument of make_vec_env; RLlib adds
    "num_envs", which must be num_worlds x num_agents. "seed" (default 0; None: unseeded) is
    offset by the EnvRunner's worker_index so that runners play different worlds."""
    if not isinstance(env_config, Mapping):
        raise TypeError(f"env_config must be a mapping (RLlib's env_config), got {describe(env_config)}")
    config = dict(env_config)
    if "env" not in config:
        raise ValueError(f"env_config must name the environment under 'env', got keys {sorted(config)}")
    name = config.pop("env")
    num_envs = config.pop("num_envs", None)
    seed = config.get("seed", 0)
    if seed is not None:  # None: unseeded, as in make_vec_env
        config["seed"] = seed + getattr(env_config, "worker_index", 0)
    with closed_on_error(make_vec_env(name, config.pop("num_worlds", 1), **config)) as envs:
        if num_envs is not None and num_envs != envs.num_envs:
            raise ValueError(f"num_envs_per_env_runner must be num_worlds x num_agents = {envs.num_envs} for "
                             f"env_config {dict(env_config)}, got {num_envs}")
        return FloatPixels(envs)
