"""The one description of an env that every front end translates: ``env.spec``.

The driver publishes it; PettingZoo, gymnasium, SB3, TorchRL, JAX and BenchMARL build their
spaces from it and from nothing else, so no front end works out a shape, a channel count or
when an episode is over on its own (``BatchedEnv.episode_over`` answers that).

    spec = env.spec
    spec.observations["pixels"]   # ArraySpec(shape=(H, Wpx, C), dtype=torch.uint8, low=0, high=255)
    spec.action                   # ActionSpec(num_actions=5, ...) or ActionSpec(shape=(2,), ...)
    spec.info                     # {"coverage": torch.float32, ...}, each [W]

Shapes are per agent: the batch adds [W, A] in front (the core, TorchRL), one world's agents
(PettingZoo) or W x A entries (the gymnasium vector env).
"""
from __future__ import annotations

import dataclasses

import torch

# The observation keys an env can have, in the order obs dicts and specs list them.
OBS_KEYS = ("pixels", "depth", "state", "lidar", "agent_id", "action_mask")
DRIVER_INFO = ("step_count", "done_worlds", "autoreset_worlds", "final_obs", "level",
               "final_level")  # info names the driver fills in
# ... and those the gymnasium front ends fill in: the vector env's "final_info" and its mask "_" + key
# of every key, and RecordEpisodeStatistics' "episode"
GYMNASIUM_INFO = ("final_info", "episode")
RESERVED_INFO = DRIVER_INFO + GYMNASIUM_INFO  # no task may name an info entry of its own so


@dataclasses.dataclass(frozen=True)
class ArraySpec:
    """One observation entry of one agent: shape, dtype and bounds (inclusive; may be infinite)."""

    shape: tuple
    dtype: torch.dtype
    low: float
    high: float


@dataclasses.dataclass(frozen=True)
class ActionSpec:
    """One agent's action: discrete (num_actions, meanings) or continuous (shape, in [-1, 1])."""

    continuous: bool
    num_actions: int | None = None  # discrete: values in [0, num_actions)
    meanings: tuple | None = None  # discrete: a short name per action
    shape: tuple = ()  # continuous: (action_dim,)
    low: float = -1.0
    high: float = 1.0

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the actions (float32 for continuous actions, int64 for discrete ones)."""
        return torch.float32 if self.continuous else torch.int64


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """Everything a front end needs to know about an env; see the module docstring."""

    name: str
    num_worlds: int
    agent_names: tuple
    groups: dict  # team -> agent names, in agent order
    observations: dict  # key -> ArraySpec, in the order of obs_keys
    action: ActionSpec
    info: dict  # {name: dtype} of the env's own info entries, each [W]
    max_steps: int
    dt: float

    @property
    def num_agents(self) -> int:
        """The number of agents of each world, A."""
        return len(self.agent_names)

    @property
    def obs_keys(self) -> tuple:
        """The observation keys, in the order of ``observations``."""
        return tuple(self.observations)


def build(env) -> EnvSpec:
    """The spec of a built driver (``BatchedEnv``): the one place that decides its observation keys
    (the driver's ``obs_keys`` are the spec's)."""
    H, Wpx = env.resolution
    observations = {"pixels": ArraySpec((H, Wpx, env.pixel_channels), torch.uint8, 0, 255)}
    if env.depth:
        observations["depth"] = ArraySpec((H, Wpx), torch.float32, 0.0, float(env.far))
    if env.state_obs:
        observations["state"] = ArraySpec((env.state_dim,), torch.float32, -float("inf"), float("inf"))
    if env.lidar_rays:
        observations["lidar"] = ArraySpec((env.lidar_rays,), torch.float32, 0.0, 1.0)
    if env.agent_ids:  # the agent's one-hot index among A, then its team's
        observations["agent_id"] = ArraySpec((env.num_agents + len(env.groups),), torch.float32, 0.0, 1.0)
    for key, entry in env.vector_obs.items():  # the task's own vectors (Scenario.vector_obs)
        observations[key] = ArraySpec((entry.width,), torch.float32, float(entry.low), float(entry.high))
    if not env.continuous:
        observations["action_mask"] = ArraySpec((env.num_actions,), torch.bool, 0, 1)
    if env.continuous:
        action = ActionSpec(continuous=True, shape=(env.action_dim,))
    else:
        action = ActionSpec(continuous=False, num_actions=env.num_actions, meanings=env.action_meanings)
    return EnvSpec(name=env.name, num_worlds=env.num_worlds, agent_names=tuple(env.agent_names),
                   groups={team: list(names) for team, names in env.groups.items()}, observations=observations,
                   action=action, info=dict(env.info_keys), max_steps=env.max_steps, dt=env.dt)
