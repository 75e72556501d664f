"""TorchRL front end: all worlds of a BatchedEnv as one multi-agent ``torchrl.envs.EnvBase``.

    from marl_render.wrappers.torchrl import make_torchrl_env
    env = make_torchrl_env("spread", num_worlds=64, group_map="team", resolution=32)
    td = env.rollout(100, break_when_any_done=False)   # random policy, auto partial resets

Layout (batch_size [W], W = num_worlds; a group of N agents)::

    (group, "pixels")       uint8   [W, N, H, Wpx, C]  Bounded(0, 255); C = 3, or 1 with grayscale=True
    (group, "depth")        float32 [W, N, H, Wpx]     Bounded(0, far)       depth=True
    (group, "state")        float32 [W, N, state_dim]  Unbounded             state_obs=True
    (group, "lidar")        float32 [W, N, rays]       Bounded(0, 1)         lidar=rays (arena tasks)
    (group, "action_mask")  bool    [W, N, n]          Categorical(2, bool)  discrete envs
    (group, "done" | "terminated" | "truncated")  bool [W, N, 1]  per-agent flags (observations)
    ("info", name)          [W] of the env's info_keys dtype   episode statistics (observations)
    (group, "action")       int64   [W, N]             Categorical(n)        discrete
                            float32 [W, N, d]          Bounded(-1, 1)        continuous=True
    (group, "reward")       float32 [W, N, 1]
    "done" | "terminated" | "truncated"           bool [W, 1]   the done spec (one level)

The pixels are at ``(group, "pixels")``, not at the root ``"pixels"`` that TorchRL's image
transforms read by default: name the group key in their ``in_keys``. Frame stacking::

    from torchrl.envs import CatFrames, Compose, GrayScale, Resize, ToTensorImage, TransformedEnv
    key = ("agents", "pixels")
    env = TransformedEnv(make_torchrl_env("spread", num_worlds=64, resolution=84), Compose(
        ToTensorImage(in_keys=[key]),         # uint8 [W, N, H, W, 3] -> float [W, N, 3, H, W] in [0, 1]
        GrayScale(in_keys=[key]),             # [W, N, 1, H, W]
        CatFrames(N=4, dim=-3, in_keys=[key]),  # [W, N, 4, H, W]; restarts at each world's reset
    ))

``Resize`` (which needs torchvision) is rarely needed: ask for the resolution you want.

Per agent: ``terminated`` is True once the agent left the episode (``alive`` False in the
core, e.g. caught prey) and stays True until its world is reset; ``truncated`` is True for
the agents still alive when the world reaches ``max_steps``; ``done = terminated |
truncated``. Per world (root): ``done`` = every agent is done, ``terminated`` = every agent
terminated, ``truncated`` = done and not terminated. Agents that left keep appearing in
every tensor (reward 0; their actions are ignored but must be valid values).

Worlds are the unit of reset, so only the root flags form the done spec and the env has a
single reset key, the root ``"_reset"`` bool [W, 1]: TorchRL transforms that need one reset
key (``CatFrames``, ``RewardSum``, ``StepCounter``, ``TensorDictPrimer``) work with their
defaults. The per-agent flags are observations with the same names, so losses can still
read ``("next", group, "terminated")`` per agent.

Episode statistics: the env's ``info_keys`` (spread: collisions, coverage; forage:
collected, team_score; tag: caught, prey_left; push: goal) are copied from the core's step
info to the root ``"info"`` entry, one value per world. They describe the step just taken;
after a reset (no step yet) they read 0. BenchMARL logs them as ``collection/info/<name>``.

Group maps (``group_map=``): "team" (default: one group per team, ``env.groups`` of the
core), "one_group" (one group "agents" with every agent), "per_agent" (one group per
agent), a ``torchrl.envs.utils.MarlGroupMapType`` or an explicit ``{group: [agent names]}``
(every agent exactly once, in any order within a group).

Resets: the core is built with ``autoreset=False``; TorchRL decides when to reset.
``_reset`` reads the root ``"_reset"``, which must be a bool tensor [W, 1] (anything else
raises before anything changes); a world is reset where it is True. Worlds not reset are
left untouched (bit-identical state, the same pixels).

Levels (built with ``levels=``, envs/levels.py): a root ``"level_ids"`` int64 [W] in the reset
tensordict resets worlds to those levels (the core's ``reset_to_level``; read where ``"_reset"``
is True, all worlds without it): ``env.reset(TensorDict({"level_ids": ids}, batch_size=[W]))``.
``("info", "level")`` [W] is the level each world plays, after every reset and step.

Seeding: ``env.set_seed(s)`` re-seeds the core's generator at the next reset (full or
partial), so ``set_seed(s); reset()`` is reproducible. Device: the core's device (CPU by
default); every tensor is produced there.

The discrete action spec carries the current action mask (``Categorical.update_mask``)
after every reset / step, so ``env.rand_action()`` samples only valid actions. Inside a
``torchrl.envs.ParallelEnv`` only the workers' specs see it (the parent's spec stays
unmasked); use the (group, "action_mask") observation there.

Works with the pinned torchrl (constraints.txt) and with the torchrl that BenchMARL pins
(constraints-benchmarl.txt, ``make test-benchmarl``).
"""
from __future__ import annotations

import math
import numbers
from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.utils import MarlGroupMapType, check_marl_grouping

from marl_render.envs.levels import check_level_ids
from marl_render.envs.multiprocess import MultiProcessEnv
from marl_render.envs.registry import make_env
from marl_render.validation import describe, unpicklable
from marl_render.wrappers.common import CORES, check_core, closed_on_error, require_levels, reset_core

GROUP_MAPS = ("team", "one_group", "per_agent")
_DONE_KEYS = ("done", "terminated", "truncated")
_RESERVED = (*_DONE_KEYS, "_reset", "reward", "action", "info", "next")  # "next": TorchRL's step results


def make_torchrl_env(name: str, num_worlds: int = 1, group_map="team", **kwargs) -> MarlRenderTorchRLEnv:
    """A TorchRL env of the registered environment `name` with `num_worlds` worlds.

    kwargs go to ``marl_render.envs.registry.make_env`` (resolution, num_agents, max_steps,
    continuous, state_obs, depth, seed, device, num_processes (the worlds over that many worker
    processes: envs/multiprocess.py) and the env's own arguments); autoreset is always False
    (TorchRL resets) and may not be passed."""
    if "autoreset" in kwargs:
        raise TypeError("make_torchrl_env() does not accept 'autoreset': TorchRL resets done worlds itself "
                        "(env.rollout / collectors call reset with '_reset' masks), so the core is always "
                        "built with autoreset=False")
    _check_group_map_type(group_map)
    with closed_on_error(make_env(name, num_worlds=num_worlds, **kwargs)) as core:
        return MarlRenderTorchRLEnv(core, group_map=group_map)


def _check_group_map_type(group_map):
    if isinstance(group_map, (MarlGroupMapType, Mapping)):
        return
    if isinstance(group_map, str) and group_map in GROUP_MAPS:
        return
    raise ValueError(f"group_map must be one of {list(GROUP_MAPS)}, a torchrl MarlGroupMapType or a dict "
                     f"{{group: [agent names]}}, got {describe(group_map)}")


def resolve_group_map(group_map, agent_names: list[str], teams: dict) -> dict[str, list[str]]:
    """The explicit {group: [agent names]} of a group_map argument (checked)."""
    _check_group_map_type(group_map)
    if isinstance(group_map, MarlGroupMapType):
        resolved = group_map.get_group_map(list(agent_names))
    elif isinstance(group_map, str):
        if group_map == "team":
            resolved = {team: list(names) for team, names in teams.items()}
        elif group_map == "one_group":
            resolved = MarlGroupMapType.ALL_IN_ONE_GROUP.get_group_map(list(agent_names))
        else:
            resolved = MarlGroupMapType.ONE_GROUP_PER_AGENT.get_group_map(list(agent_names))
    else:
        resolved = {}
        for group, names in group_map.items():
            if not isinstance(group, str) or not group:
                raise TypeError(f"group_map keys must be non-empty str group names, got {describe(group)}")
            if isinstance(names, str) or not all(isinstance(n, str) for n in names):
                raise TypeError(f"group_map[{group!r}] must be a list of agent names (str), got {describe(names)}")
            resolved[group] = list(names)
        unknown = sorted({n for names in resolved.values() for n in names} - set(agent_names))
        if unknown:
            raise ValueError(f"group_map names unknown agent(s) {unknown}; the env's agents are {list(agent_names)}")
        missing = [n for n in agent_names if not any(n in names for names in resolved.values())]
        if missing:
            raise ValueError(f"group_map must place every agent in a group; missing: {missing}")
    empty = [group for group in resolved if not isinstance(group, str) or not group]
    if empty:
        raise ValueError(f"group names must be non-empty str (they become TensorDict keys), got {empty!r} from "
                         f"group_map={describe(group_map)}; rename the team or pass group_map={{name: [agents]}}")
    reserved = sorted(set(resolved) & set(_RESERVED))
    if reserved:
        raise ValueError(f"group names {reserved} clash with TorchRL's root keys {list(_RESERVED)}; "
                         f"rename the group(s)")
    check_marl_grouping(resolved, list(agent_names))
    return resolved


class MarlRenderTorchRLEnv(EnvBase):
    """TorchRL multi-agent env over all worlds of a ``BatchedEnv``; see the module docstring.

    ``core`` is the wrapped BatchedEnv (owned: closed by ``close()``); ``group_map`` the
    resolved {group: [agent names]}."""

    def __init__(self, env, group_map="team"):
        check_core(env, kinds=(*CORES, MultiProcessEnv), no_autoreset="TorchRL resets done worlds itself")
        resolved = resolve_group_map(group_map, env.agent_names, env.groups)
        super().__init__(device=env.device, batch_size=torch.Size([env.num_worlds]))
        self.core = env
        self.group_map = resolved
        index = {name: i for i, name in enumerate(env.agent_names)}
        self._group_index = {g: torch.tensor([index[n] for n in names], dtype=torch.long, device=env.device)
                             for g, names in resolved.items()}
        # A group covering all agents in core order needs no gather.
        self._identity = {g: names == list(env.agent_names) for g, names in resolved.items()}
        self._obs_keys = env.spec.obs_keys  # every key of the spec, the action mask included
        self._next_seed = None
        self._started = False  # the core needs a full reset() before reset_worlds()
        self._make_specs()

    # ------------------------------------------------------------------ specs
    def _make_specs(self):
        core, W, dev = self.core, self.core.num_worlds, self.device
        obs_spec, act_spec, rew_spec, done_spec = (Composite(shape=(W,), device=dev) for _ in range(4))
        for key in _DONE_KEYS:
            done_spec[key] = Categorical(2, shape=(W, 1), dtype=torch.bool, device=dev)
        spec = core.spec
        for group, names in self.group_map.items():
            N = len(names)
            obs = {key: _tensor_spec(key, entry, (W, N), dev) for key, entry in spec.observations.items()}
            for key in _DONE_KEYS:
                obs[key] = Categorical(2, shape=(W, N, 1), dtype=torch.bool, device=dev)
            obs_spec[group] = Composite(obs, shape=(W, N), device=dev)
            action = spec.action
            if action.continuous:
                act = Bounded(action.low, action.high, shape=(W, N, *action.shape), dtype=action.dtype, device=dev)
            else:
                act = Categorical(action.num_actions, shape=(W, N), dtype=action.dtype, device=dev)
            act_spec[group] = Composite(action=act, shape=(W, N), device=dev)
            rew_spec[group] = Composite(reward=Unbounded(shape=(W, N, 1), dtype=torch.float32, device=dev),
                                        shape=(W, N), device=dev)
        if spec.info:
            obs_spec["info"] = Composite({name: Unbounded(shape=(W,), dtype=dtype, device=dev)
                                          for name, dtype in spec.info.items()}, shape=(W,), device=dev)
        self.observation_spec = obs_spec
        self.action_spec = act_spec
        self.reward_spec = rew_spec
        self.done_spec = done_spec

    # ------------------------------------------------------------------ EnvBase hooks
    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            return
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not 0 <= seed < 2 ** 63:
            raise ValueError(f"seed must be None or an int in [0, 2**63), got {describe(seed)}")
        self._next_seed = int(seed)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        core = self.core
        mask = self._reset_mask(tensordict)
        levels = self._level_ids(tensordict, mask)
        seed, self._next_seed = self._next_seed, None
        obs = reset_core(core, seed, worlds=mask, levels=levels, full=not self._started)
        self._started = True
        terminated = ~core.alive
        truncated = core.alive & core.episode_over()[:, None]
        info = {name: torch.zeros(core.num_worlds, dtype=dtype, device=self.device)
                for name, dtype in core.info_keys.items()}
        if core.levels is not None:
            info["level"] = core.level_ids.to(self.device)
        return self._output(obs, None, terminated, truncated, info)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        core = self.core
        W, A = core.num_worlds, core.num_agents
        if core.continuous:
            actions = torch.zeros(W, A, core.action_dim, dtype=torch.float32, device=self.device)
        else:
            actions = torch.zeros(W, A, dtype=torch.int64, device=self.device)
        for group, idx in self._group_index.items():
            action = tensordict.get((group, "action"))
            if action is None:
                raise KeyError(f"the tensordict has no ({group!r}, 'action') entry; every group needs its actions")
            if self._identity[group]:
                actions = action  # the core checks dtype, shape, range and NaN
                break
            actions[:, idx] = self._check_group_action(group, action).to(actions.dtype)
        obs, reward, terminated, truncated, info = core.step(actions)
        return self._output(obs, reward, terminated, truncated, info)

    # ------------------------------------------------------------------ helpers
    def _check_group_action(self, group, action) -> torch.Tensor:
        """Dtype / shape check of one group's actions before they are gathered (values are
        checked by the core), so nothing is silently cast."""
        core, W, N = self.core, self.core.num_worlds, len(self.group_map[group])
        if core.continuous:
            shape, ok, want = (W, N, core.action_dim), action.is_floating_point(), "a float tensor"
        else:
            shape = (W, N)
            ok = not action.is_floating_point() and not action.is_complex() and action.dtype != torch.bool
            want = "an integer tensor"
        if not ok or tuple(action.shape) != shape:
            raise ValueError(f"({group!r}, 'action') must be {want} of shape {list(shape)}, got {describe(action)}")
        return action

    def _level_ids(self, tensordict, mask: torch.Tensor | None) -> torch.Tensor | None:
        """int64 [W] from the root "level_ids" of the reset tensordict (checked), or None."""
        if tensordict is None or "level_ids" not in tensordict.keys():
            return None
        require_levels(self.core, "a 'level_ids' reset entry")
        return check_level_ids("tensordict['level_ids']", tensordict.get("level_ids"), self.core.num_worlds,
                               where=None if mask is None else mask.cpu())

    def _reset_mask(self, tensordict) -> torch.Tensor | None:
        """[W] bool of the worlds to reset, or None for a full reset. Raises on a malformed
        "_reset" before anything changes."""
        if tensordict is None:
            return None
        W = self.core.num_worlds
        nested = [group for group in self.group_map if (group, "_reset") in tensordict.keys(True)]
        if nested:
            raise ValueError(f"(group, '_reset') entries are not reset keys of this env (got them for {nested}): "
                             f"worlds are the unit of reset; set the root '_reset', a bool tensor of shape "
                             f"[{W}, 1] (worlds, 1)")
        reset = tensordict.get("_reset", None)
        if reset is None:
            return None
        want = f"'_reset' must be a bool tensor of shape [{W}, 1] (worlds, 1), True where a world is reset"
        if not isinstance(reset, torch.Tensor) or reset.dtype != torch.bool:
            raise TypeError(f"{want}, got {describe(reset)}")
        if tuple(reset.shape) != (W, 1):
            raise ValueError(f"{want}, got {describe(reset)}")
        return reset[:, 0].to(self.device)

    def _output(self, obs, reward, terminated, truncated, info) -> TensorDict:
        W = self.core.num_worlds
        done = terminated | truncated
        source = {"done": done.all(1, keepdim=True), "terminated": terminated.all(1, keepdim=True)}
        source["truncated"] = source["done"] & ~source["terminated"]
        for group, idx in self._group_index.items():
            N = len(idx)
            if self._identity[group]:
                pick = lambda t: t  # noqa: E731
            else:
                pick = lambda t, idx=idx: t.index_select(1, idx)  # noqa: E731
            entries = {key: pick(obs[key]) for key in self._obs_keys}
            entries["done"] = pick(done)[..., None]
            entries["terminated"] = pick(terminated)[..., None]
            entries["truncated"] = pick(truncated)[..., None]
            if reward is not None:
                entries["reward"] = pick(reward)[..., None]
            if "action_mask" in entries:
                spec = self.full_action_spec[group, "action"]
                spec.update_mask(entries["action_mask"].clone())
            source[group] = TensorDict(entries, batch_size=(W, N), device=self.device)
        if self.core.info_keys:
            source["info"] = TensorDict({name: info[name] for name in self.core.info_keys}, batch_size=(W,),
                                        device=self.device)
        return TensorDict(source, batch_size=(W,), device=self.device)

    # ------------------------------------------------------------------ extras
    def render_overview(self, resolution=None) -> torch.Tensor:
        """uint8 [W, H2, W2, 3]: each world seen from the core's overview camera (for humans)."""
        return self.core.render_overview(resolution)

    @property
    def agent_names(self) -> list[str]:
        return list(self.core.agent_names)

    def close(self, *, raise_if_closed: bool = True) -> None:
        self.core.close()
        super().close(raise_if_closed=raise_if_closed)

    def __reduce__(self):
        raise unpicklable("a MarlRenderTorchRLEnv", "marl_render.envs.make_torchrl_env")

    def __repr__(self):
        return f"MarlRenderTorchRLEnv({self.core!r}, group_map={self.group_map})"


__all__ = ["MarlRenderTorchRLEnv", "make_torchrl_env", "resolve_group_map", "GROUP_MAPS"]


def _tensor_spec(key: str, entry, batch: tuple, device):
    """The TorchRL spec of one observation entry (an ArraySpec of envs/spec.py) for a batch [W, N]."""
    shape = (*batch, *entry.shape)
    if key == "action_mask":
        return Categorical(2, shape=shape, dtype=torch.bool, device=device)
    if math.isinf(entry.low) or math.isinf(entry.high):
        return Unbounded(shape=shape, dtype=entry.dtype, device=device)
    return Bounded(entry.low, entry.high, shape=shape, dtype=entry.dtype, device=device)
