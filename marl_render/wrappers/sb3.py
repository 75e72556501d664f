"""Stable-Baselines3 front end: the gymnasium vector env of marl_render.wrappers.gymnasium
as an SB3 ``VecEnv`` (SB3 has its own vector env class and does not take gymnasium's).

    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor
    from marl_render.envs import make_sb3_env
    venv = VecMonitor(make_sb3_env("cartpole", num_worlds=32, resolution=64))
    model = PPO("CnnPolicy", venv, n_steps=128, batch_size=256).learn(100_000)

One batched core and one renderer serve all ``num_envs = num_worlds x num_agents`` entries
(the layout of marl_render.wrappers.gymnasium: entry i is agent i % A of world i // A).
SB3's conventions are met: auto-reset in the same step, the ended episode's last
observation in ``infos[i]["terminal_observation"]`` and ``infos[i]["TimeLimit.truncated"]``
for a time limit; observations are uint8 ``(H, W, 3)`` images (PPO wraps them in
``VecTransposeImage`` by itself) or a Dict (``MultiInputPolicy``). Because the final frame
is needed, a step on which a world ends renders twice.

The batch is one environment, not ``num_envs`` copies: ``get_attr`` reads an attribute of
the vector env (or of its core) once and repeats it per index; ``env_method`` calls the
method once and repeats its result; ``set_attr`` sets it once (indices are checked against
``[0, num_envs)``); ``seed(s)`` (one int) seeds the next reset with ``s`` (the core's one
generator draws for every world); ``set_options(options)`` passes one options dict (e.g.
``{"reset_mask": mask}``, or ``{"level_ids": ids}`` for an env built with ``levels=``: see
marl_render.wrappers.gymnasium) to the next reset, the same for every entry.

Resolution: SB3's ``CnnPolicy`` uses its ``NatureCNN`` (8x8 stride 4, 4x4 stride 2, 3x3 stride 1
convolutions), which needs at least 36 pixels on each side: below that (e.g. 35 x 35 or 48 x 35) it
fails with torch's "Kernel size can't be greater than actual input size". For 8 to 48 pixels use
``SmallImageCNN``, this module's feature extractor::

    model = PPO("CnnPolicy", make_sb3_env("spread", num_worlds=16, resolution=16),
                policy_kwargs={"features_extractor_class": SmallImageCNN})
"""
from __future__ import annotations

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

from marl_render.extras import needs_extra
from marl_render.validation import describe, unpicklable

from .common import closed_on_error
from .gymnasium import MarlRenderVectorEnv, make_vec_env

with needs_extra("sb3", "make_sb3_env"):
    from stable_baselines3.common.preprocessing import is_image_space
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
    from stable_baselines3.common.vec_env import VecEnv


def make_sb3_env(name: str, num_worlds: int = 1, **kwargs) -> MarlRenderSB3VecEnv:
    """An SB3 VecEnv of the registered environment `name` (num_worlds x num_agents entries).

    kwargs go to ``marl_render.envs.make_vec_env`` (resolution, num_agents, max_steps,
    continuous, state_obs, depth, action_mask, render_mode, seed, ...); the autoreset
    mode is SB3's (same step) and may not be passed."""
    if "autoreset_mode" in kwargs or "autoreset" in kwargs:
        raise TypeError("make_sb3_env() does not accept 'autoreset_mode' or 'autoreset': SB3 resets "
                        "in the same step (AutoresetMode.SAME_STEP)")
    with closed_on_error(make_vec_env(name, num_worlds, autoreset_mode=AutoresetMode.SAME_STEP, **kwargs)) as venv:
        return MarlRenderSB3VecEnv(venv)


class MarlRenderSB3VecEnv(VecEnv):
    """A same-step ``MarlRenderVectorEnv`` as an SB3 VecEnv; see the module docstring."""

    def __init__(self, venv: MarlRenderVectorEnv):
        if not isinstance(venv, MarlRenderVectorEnv):
            raise TypeError(f"venv must be a MarlRenderVectorEnv (see marl_render.envs.make_vec_env), "
                            f"got {describe(venv)}")
        if venv.metadata["autoreset_mode"] != AutoresetMode.SAME_STEP:
            raise ValueError(f"venv must reset in the same step as SB3 does (autoreset_mode=AutoresetMode.SAME_STEP), "
                             f"got {venv.metadata['autoreset_mode']}")
        self.venv = venv
        self._actions = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    def seed(self, seed: int | None = None) -> list:
        """SB3's seed: entry i is given seed + i for the next reset; the core's one generator takes
        the first. One int (or None for a random one), as SB3's VecEnv.seed documents."""
        if seed is not None and (isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer))):
            raise TypeError(f"seed must be None or one int (entry i then gets seed + i, as SB3's VecEnv.seed does; "
                            f"per-entry seeds are not supported: one generator draws for every world), "
                            f"got {describe(seed)}")
        return super().seed(None if seed is None else int(seed))

    def set_options(self, options: list | dict | None = None) -> None:
        """Options for the next reset, as SB3's VecEnv.set_options (e.g. {"reset_mask": mask}, see
        marl_render.wrappers.gymnasium). One reset serves every entry, so a list must hold the same
        options for all of them."""
        if options is not None and not isinstance(options, (dict, list, tuple)):
            raise TypeError(f"options must be None, a dict or a list of {self.num_envs} dicts, got {describe(options)}")
        if isinstance(options, (list, tuple)):
            if len(options) != self.num_envs or not all(isinstance(o, dict) for o in options):
                raise ValueError(f"options must be None, a dict or a list of {self.num_envs} dicts (num_envs), "
                                 f"got {describe(options)}")
            if any(not _same_options(o, options[0]) for o in options[1:]):
                raise ValueError("options must be the same for every entry: one reset serves the whole batch "
                                 "(pass one dict)")
        super().set_options(options)

    def reset(self):
        seed = self._seeds[0]  # seed(s) gives entry i the seed s + i; the core takes one
        options = self._options[0] or None  # set_options keeps the same dict for every entry
        observations, _ = self.venv.reset(seed=seed, options=options)
        self._reset_seeds()
        self._reset_options()
        return observations

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        if self._actions is None:
            raise RuntimeError("call step_async(actions) before step_wait()")
        actions, self._actions = self._actions, None
        observations, rewards, terminations, truncations, info = self.venv.step(actions)
        dones = terminations | truncations
        infos = [{} for _ in range(self.num_envs)]  # SB3's API: one dict per entry
        for i in np.flatnonzero(dones):  # only the entries whose episode ended
            infos[i]["terminal_observation"] = info["final_obs"][i]
            infos[i]["TimeLimit.truncated"] = bool(truncations[i] and not terminations[i])
        return observations, rewards, dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self):
        frames = self.venv.render()
        return [None] * self.num_envs if frames is None else list(frames)

    def get_attr(self, attr_name: str, indices=None) -> list:
        indices = self._get_indices(indices)
        target = self.venv if hasattr(self.venv, attr_name) else self.venv.core
        value = getattr(target, attr_name)
        return [value for _ in indices]

    def set_attr(self, attr_name: str, value, indices=None) -> None:
        self._get_indices(indices)
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list:
        indices = self._get_indices(indices)
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result for _ in indices]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list:
        return [False for _ in self._get_indices(indices)]

    def __reduce__(self):
        raise unpicklable("a MarlRenderSB3VecEnv", "marl_render.envs.make_sb3_env")

    def __repr__(self):
        return f"MarlRenderSB3VecEnv({self.venv!r})"

    def _get_indices(self, indices) -> list:
        """SB3's indices (None, an int or ints) as a list, checked against [0, num_envs) (negative ones
        count from the end, as a list of envs would take them): an IndexError names a bad one."""
        n = self.num_envs
        given = range(n) if indices is None else [indices] if isinstance(indices, (int, np.integer)) else indices
        try:
            given = list(given)
        except TypeError:
            raise TypeError(f"indices must be None, an int or a sequence of ints, got {describe(indices)}") from None
        for index in given:
            if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)):
                raise TypeError(f"indices must be None, an int or a sequence of ints, got {describe(indices)}")
            if not -n <= index < n:
                raise IndexError(f"indices must be in [0, {n}) (num_envs = {n}), got {describe(indices)}")
        return [int(index) % n for index in given]


NATURE_CNN_MIN_SIZE = 36  # pixels a side that SB3's NatureCNN (the default CnnPolicy) needs
SMALL_IMAGE_MIN_SIZE = 8  # SmallImageCNN's two stride-2 convolutions leave 2 x 2 of an 8 x 8 image


class SmallImageCNN(BaseFeaturesExtractor):
    """A feature extractor for images of 8 to 48 pixels a side, where SB3's NatureCNN cannot go (see
    the module docstring): three 3x3 convolutions (32, 64, 64 channels; strides 1, 2, 2; padding 1;
    ReLU), then a linear layer to `features_dim` with ReLU. SB3 hands it channel-first images (it
    adds VecTransposeImage itself), scaled to [0, 1] unless normalize_images=False.

        PPO("CnnPolicy", venv, policy_kwargs={"features_extractor_class": SmallImageCNN,
                                              "features_extractor_kwargs": {"features_dim": 128}})

    Larger images work too, but the linear layer grows with their area (64 x 64: 16 x 16 x 64 inputs);
    NatureCNN suits them better."""

    def __init__(self, observation_space: spaces.Box, features_dim: int = 256, normalized_image: bool = False):
        if not is_image_space(observation_space, check_channels=False, normalized_image=normalized_image):
            raise ValueError(f"observation_space must be an image Box (channel-first, uint8 unless normalized_image)"
                             f" as SB3's CnnPolicy gets it, got {observation_space}")
        channels, height, width = observation_space.shape
        if min(height, width) < SMALL_IMAGE_MIN_SIZE:
            raise ValueError(f"SmallImageCNN needs images of at least {SMALL_IMAGE_MIN_SIZE} x {SMALL_IMAGE_MIN_SIZE} "
                             f"pixels, got {height} x {width}")
        super().__init__(observation_space, features_dim)
        self.cnn = torch.nn.Sequential(
            torch.nn.Conv2d(channels, 32, 3, stride=1, padding=1), torch.nn.ReLU(),
            torch.nn.Conv2d(32, 64, 3, stride=2, padding=1), torch.nn.ReLU(),
            torch.nn.Conv2d(64, 64, 3, stride=2, padding=1), torch.nn.ReLU(),
            torch.nn.Flatten())
        with torch.no_grad():
            flat = self.cnn(torch.zeros(1, channels, height, width)).shape[1]
        self.linear = torch.nn.Sequential(torch.nn.Linear(flat, features_dim), torch.nn.ReLU())

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.linear(self.cnn(observations))


__all__ = ["MarlRenderSB3VecEnv", "SmallImageCNN", "make_sb3_env"]


def _same_options(a: dict, b: dict) -> bool:
    """Whether two option dicts are equal, numpy arrays (e.g. a reset mask) compared by value."""
    if a.keys() != b.keys():
        return False
    return all(np.array_equal(a[k], b[k]) if isinstance(a[k], np.ndarray) or isinstance(b[k], np.ndarray)
               else a[k] == b[k] for k in a)
