"""gymnasium spaces from the driver's spec (envs/spec.py): the one translation that the
PettingZoo, gymnasium vector and SB3 front ends share.

    observation_space(env.spec, keys)   # Box of the pixels alone, or a Dict of `keys`
    action_space(env.spec)              # Discrete(num_actions) or Box(-1, 1, (action_dim,))

"action_mask" becomes ``MultiBinary(num_actions)`` (int8, the dtype gymnasium's MultiBinary
holds), every other entry a Box with the spec's bounds and dtype.
"""
from __future__ import annotations

import numpy as np
from gymnasium import spaces

NUMPY_DTYPES = {"uint8": np.uint8, "float32": np.float32, "float64": np.float64, "int64": np.int64, "bool": np.bool_}


def entry_space(key: str, spec) -> spaces.Space:
    """The space of one observation entry (an ArraySpec)."""
    if key == "action_mask":
        return spaces.MultiBinary(spec.shape[0])
    dtype = NUMPY_DTYPES[str(spec.dtype).removeprefix("torch.")]
    return spaces.Box(spec.low, spec.high, spec.shape, dtype)


def observation_space(spec, keys: tuple) -> spaces.Space:
    """The pixels' Box when `keys` is ("pixels",), else a Dict of every key in `keys`."""
    if tuple(keys) == ("pixels",):
        return entry_space("pixels", spec.observations["pixels"])
    return spaces.Dict({key: entry_space(key, spec.observations[key]) for key in keys})


def action_space(spec) -> spaces.Space:
    action = spec.action
    if action.continuous:
        return spaces.Box(action.low, action.high, action.shape, np.float32)
    return spaces.Discrete(action.num_actions)
