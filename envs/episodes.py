"""Per-episode bookkeeping the driver does for some tasks: random episode ends and social outcomes.

**Random ends** (Melting Pot's): with ``episode_end`` on, an episode lasts at least ``min_steps``
steps; at that step and every ``interval`` steps after it, it ends with ``probability`` (a
truncation: the game is cut, no state is terminal), and at ``max_steps`` at the latest. So agents
cannot exploit a known last step. Each world's end is drawn once, when its episode starts, as
``min_steps + interval * K``, K geometric (failures before the first success): the same law as a
draw at every interval, and memoryless (history-free). The draw comes from the env's generator,
after the reset's own draws (so the first layouts and looks are those of a fixed end); with
``levels=`` it is a pure function of the world's level id (envs/levels.py), so a level names its
end too, in any world slot, at any batch size, after any history.

    make_env("commons")                                      # mixed-motive: random ends (the default)
    make_env("commons", episode_end=False)                   # the fixed end at max_steps, as before
    make_env("spread", episode_end=EpisodeEnd(50, 10, 0.2))  # any task

**Social outcomes** (Perolat et al. 2017, "A multi-agent reinforcement learning model of
common-pool resource appropriation"), for mixed-motive tasks (``Scenario.mixed_motive``): the info
entries ``efficiency``, ``equality``, ``sustainability`` and ``peace``, each float32 [W], of the
episode so far (at its last step, ``done_worlds``, the episode's):

* efficiency: the collective return, sum_i R_i;
* equality: 1 - Gini of the returns, 1 - sum_ij |R_i - R_j| / (2 A sum_i |R_i|) (|R_i|, so that
  negative returns keep it in [0, 1]; 1 when every return is 0);
* sustainability: the mean time at which rewards were earned: per agent the mean step (1-based)
  of its positive rewards, averaged over the agents that earned any (0 when none did);
* peace: the agent-steps not spent tagged out, sum_t sum_i [i in the episode and not
  ``Scenario.tagged_out``] after step t.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from marl_render.util.keyed_random import derive_keys
from marl_render.util.validation import describe

from . import levels as level_sets

SOCIAL_KEYS = ("efficiency", "equality", "sustainability", "peace")


@dataclasses.dataclass(frozen=True)
class EpisodeEnd:
    """A random episode end: at least `min_steps`, then at that step and every `interval` steps after
    it the episode ends with `probability` (and at max_steps at the latest)."""

    min_steps: int
    interval: int
    probability: float

    def __post_init__(self):
        for name in ("min_steps", "interval"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value < 2 ** 62:
                raise ValueError(f"EpisodeEnd's {name} must be an int in [1, 2**62), got {describe(value)}")
        p = self.probability
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 < p <= 1:
            raise ValueError(f"EpisodeEnd's probability must be a number in (0, 1], got {describe(p)}")

    @classmethod
    def for_length(cls, max_steps: int) -> EpisodeEnd:
        """The default random end of a task of `max_steps`: at least half of it, then probability 0.25
        every twentieth of it (mean 0.64 max_steps; max_steps itself in 0.75**10 = 6% of episodes)."""
        return cls(max(1, max_steps // 2), max(1, max_steps // 20), 0.25)

    def describe(self, max_steps: int) -> str:
        return (f"random (Melting Pot's): at least {self.min_steps} steps, then it ends with probability "
                f"{self.probability:g} at that step and every {self.interval} steps after it, at "
                f"max_steps={max_steps} at the latest")


def episode_end(value, scenario, max_steps: int) -> EpisodeEnd | None:
    """The env's random end (EnvOptions.episode_end), or None for the fixed end at max_steps. value:
    None (the task's default: on for mixed-motive tasks), False (fixed), True (the task's random end
    even where it is off by default), an EpisodeEnd or a tuple (min_steps, interval, probability)."""
    want = "None (the task's default), False (fixed), True, an EpisodeEnd or (min_steps, interval, probability)"
    if value is None:
        value = bool(scenario.mixed_motive)
    if isinstance(value, bool):
        if not value:
            return None
        declared = scenario.episode_end
        return EpisodeEnd(*declared) if declared is not None else EpisodeEnd.for_length(max_steps)
    if isinstance(value, tuple) and len(value) == 3:
        return EpisodeEnd(*value)
    if isinstance(value, EpisodeEnd):
        return value
    raise TypeError(f"episode_end must be {want}, got {describe(value)}")


def for_env(options, scenario, params, info_keys: dict, batch, max_steps: int) -> EpisodeBook:
    """The book of a driver built with `options` (EnvOptions) for the Scenario subclass `scenario`: its
    random ends (episode_end) and social tallies (social_metrics), none of whose info entries may be
    one of the task's `info_keys`; `batch` is the driver's BatchShape."""
    end = episode_end(options.episode_end, scenario, max_steps)
    social = options.social_metrics
    if social is not None and not isinstance(social, (bool, np.bool_)):
        raise TypeError(f"social_metrics must be a bool, got {describe(social)}")
    social = bool(scenario.mixed_motive) if social is None else bool(social)
    clash = sorted(set(info_keys) & set(SOCIAL_KEYS)) if social else []
    if clash:
        raise ValueError(f"{scenario.__name__}.info_keys names {clash}, which the social metrics' info entries use "
                         f"(envs/episodes.py); rename them, or pass social_metrics=False")
    return EpisodeBook(end, social, batch.num_worlds, batch.num_agents, max_steps, batch.device, scenario.name, params)


def describe_end(scenario, max_steps: int | None = None) -> str:
    """Which end a task's episodes have by default (for its card)."""
    max_steps = scenario.default_max_steps if max_steps is None else max_steps
    end = episode_end(None, scenario, max_steps)
    return f"fixed: truncated after max_steps={max_steps}" if end is None else end.describe(max_steps)


def ends_of(uniform: torch.Tensor, end: EpisodeEnd, max_steps: int) -> torch.Tensor:
    """int64: min_steps + interval * K, K = the failures before the first success of a probability-p
    trial, from uniform numbers in [0, 1) (inverse transform), capped at max_steps."""
    if end.probability >= 1:
        failures = torch.zeros_like(uniform)
    else:  # 1 - u in (0, 1]: log is finite; the quotient is >= 0
        failures = torch.floor(torch.log1p(-uniform) / math.log1p(-end.probability))
    steps = end.min_steps + end.interval * failures.clamp(max=float(max_steps))
    return steps.clamp(max=float(max_steps)).to(torch.int64)


def draw_ends(end: EpisodeEnd, max_steps: int, num_worlds: int, generator: torch.Generator, level_ids,
              task: str, params, num_agents: int) -> torch.Tensor:
    """int64 [W] (CPU): the step at which each world's new episode ends (see the module docstring):
    from the env's generator, or with levels on (level_ids [W]) from the level ids alone."""
    if level_ids is None:
        uniform = torch.rand(num_worlds, generator=generator, dtype=torch.float64)
    else:
        keys = derive_keys(level_ids.cpu(), "episode_end", task, repr(params), num_agents)
        uniform = level_sets.KeyedDraws(keys).rand("episode_end", (num_worlds,), dtype=torch.float64)
    return ends_of(uniform, end, max_steps)


def social_outcomes(returns: torch.Tensor, reward_time: torch.Tensor, rewarded: torch.Tensor,
                    peace: torch.Tensor) -> dict:
    """{efficiency, equality, sustainability, peace}: float32 [W] each, from the episode's tallies:
    returns [W, A], the sum of the steps of positive rewards [W, A], their count [W, A], and the
    agent-steps not tagged out [W] (see the module docstring)."""
    A = returns.shape[1]
    efficiency = returns.sum(1)
    spread = (returns[:, :, None] - returns[:, None, :]).abs().sum((1, 2))
    scale = 2 * A * returns.abs().sum(1)
    equality = torch.where(scale > 0, 1 - spread / scale.clamp_min(1e-300), torch.ones_like(scale))
    earned = rewarded > 0
    mean_time = torch.where(earned, reward_time / rewarded.clamp_min(1), torch.zeros_like(reward_time))
    earners = earned.sum(1)
    sustainability = torch.where(earners > 0, mean_time.sum(1) / earners.clamp_min(1), torch.zeros_like(efficiency))
    values = {"efficiency": efficiency, "equality": equality, "sustainability": sustainability, "peace": peace}
    return {key: value.to(torch.float32) for key, value in values.items()}


class EpisodeBook:
    """The driver's per-episode bookkeeping of one env: each world's end (random ends on) and its
    social tallies (social metrics on). Its tensors are replaced, never written into, so that a
    snapshot (a tuple of references) restores it after a failed call."""

    def __init__(self, end: EpisodeEnd | None, social: bool, num_worlds: int, num_agents: int, max_steps: int,
                 device: torch.device, task: str, params):
        self.end, self.social, self.max_steps = end, social, max_steps
        self.task, self.params, self.num_agents = task, params, num_agents
        W, A = num_worlds, num_agents
        self.ends = torch.full((W,), max_steps, dtype=torch.int64, device=device) if end is not None else None
        self.tallies = {"social_returns": torch.zeros(W, A, dtype=torch.float64, device=device),
                        "social_reward_time": torch.zeros(W, A, dtype=torch.float64, device=device),
                        "social_rewarded": torch.zeros(W, A, dtype=torch.int64, device=device),
                        "social_peace": torch.zeros(W, dtype=torch.int64, device=device)} if social else {}

    @property
    def info_keys(self) -> dict:
        return {key: torch.float32 for key in SOCIAL_KEYS} if self.social else {}

    def limit(self, max_steps: int):
        """What the step count is compared with for truncation: [W] ends, or max_steps (an int)."""
        return max_steps if self.ends is None else self.ends

    def counters(self) -> dict:
        """The book's part of get_state()."""
        return {**({"episode_end": self.ends} if self.ends is not None else {}), **self.tallies}

    def snapshot(self) -> tuple:
        return self.ends, dict(self.tallies)

    def restore(self, snapshot: tuple) -> None:
        self.ends, self.tallies = snapshot[0], dict(snapshot[1])

    def start(self, mask: torch.Tensor, generator: torch.Generator, level_ids) -> None:
        """New episodes in the worlds of mask [W]: a new end drawn there (after the reset's draws),
        the tallies zeroed there."""
        if self.ends is not None:
            drawn = draw_ends(self.end, self.max_steps, mask.numel(), generator, level_ids, self.task, self.params,
                              self.num_agents).to(self.ends.device)
            self.ends = torch.where(mask, drawn, self.ends)
        self.tallies = {key: torch.where(mask.view(-1, *[1] * (value.ndim - 1)), torch.zeros_like(value), value)
                        for key, value in self.tallies.items()}

    def record(self, reward: torch.Tensor, acting: torch.Tensor, tagged_out: torch.Tensor | None,
               step_count: torch.Tensor) -> dict:
        """Add a step to the tallies (reward [W, A] of the agents `acting` [W, A], tagged_out [W, A]
        after it, step_count [W] its 1-based index); the social info entries of the episode so far."""
        if not self.social:
            return {}
        t = self.tallies
        positive = (reward > 0) & acting
        in_peace = acting & ~tagged_out
        when = positive * step_count[:, None].to(torch.float64)
        self.tallies = {"social_returns": t["social_returns"] + reward.to(torch.float64),
                        "social_reward_time": t["social_reward_time"] + when,
                        "social_rewarded": t["social_rewarded"] + positive,
                        "social_peace": t["social_peace"] + in_peace.sum(1)}
        return self.outcomes()

    def outcomes(self) -> dict:
        t = self.tallies
        return social_outcomes(t["social_returns"], t["social_reward_time"], t["social_rewarded"], t["social_peace"])

    def checked(self, state: dict) -> tuple:
        """The book's keys taken out of a set_state dict (already checked for shapes and dtypes), their
        values checked, as a snapshot for restore(); the book itself is unchanged."""
        ends = state.pop("episode_end", None)
        tallies = {key: state.pop(key) for key in list(self.tallies)}
        if ends is not None and bool(((ends < 1) | (ends > self.max_steps)).any()):
            raise ValueError(f"state['episode_end'] must be in [1, max_steps={self.max_steps}], got values in "
                             f"[{int(ends.min())}, {int(ends.max())}]")
        for key, value in tallies.items():
            bad = ~torch.isfinite(value) if value.is_floating_point() else value < 0
            if bool(bad.any()):
                raise ValueError(f"state[{key!r}] must be finite (sums) and >= 0 (counts), got {describe(value)}")
        return ends, tallies


class EpisodeOutcomes:
    """Each world's social outcomes at the end of its episode, collected step by step (the evaluation
    CLI's rows: marl_render.evaluate.play): keeps the info values of the step a world's episode ended.

        outcomes = EpisodeOutcomes(env)
        ... obs, reward, terminated, truncated, info = env.step(actions); outcomes.add(info, running)
        row.update(outcomes.fields())  # {"efficiency_mean": ..., ...}; {} for a task without them
    """

    def __init__(self, env):
        self.keys = tuple(key for key in SOCIAL_KEYS if key in env.spec.info)
        self.values = {key: torch.full((env.num_worlds,), math.nan, dtype=torch.float64) for key in self.keys}

    def add(self, info: dict, running: torch.Tensor) -> None:
        """Keep the values of the worlds whose episode ended at this step (done_worlds among `running`)."""
        ended = (info["done_worlds"] & running).cpu()
        for key in self.keys:
            self.values[key] = torch.where(ended, info[key].cpu().to(torch.float64), self.values[key])

    def fields(self) -> dict:
        """{"<outcome>_mean": mean over the episodes that ended}; {} for a task without social outcomes."""
        return {f"{key}_mean": float(values[~values.isnan()].mean()) for key, values in self.values.items()}
