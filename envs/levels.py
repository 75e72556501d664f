"""Levels: a world's episode named by an id, with train and test sets that never meet.

A **level** is everything a reset samples (layout, spawns, goals, landmarks and, with the
"appearance" option, the world's look), as a pure function of (task, task parameters, level id).
The same id gives a bit-identical reset in any world slot, at any batch size, after any history:
the reset draws come from counter-based numbers keyed per world (marl_render/keyed_random.py)
instead of the env's shared ``torch.Generator``.

    env = make_env("rooms", num_worlds=64, levels=200)          # train on levels 0..199
    env = make_env("rooms", num_worlds=64, levels="test")       # the unbounded test distribution
    env = make_env("rooms", num_worlds=64, levels="published")  # the frozen test set of reference results
    obs = env.reset(seed=0)
    env.level_ids                                               # int64 [W]: the level each world plays
    env.reset_to_level(mask, level_ids)                         # chosen worlds to chosen levels

Level ids are ints in [0, LEVEL_LIMIT). The id space is split once for every task:

* ``levels=n`` (the first n), a range or a list of ids: a finite **train set**; its ids must lie
  below TEST_START;
* ``levels="train"``: the unbounded train distribution, every id in [0, TEST_START);
* ``levels="test"``: the unbounded **test distribution**, every id in [TEST_START, LEVEL_LIMIT);
* ``levels="published"``: PUBLISHED_TEST_LEVELS, a frozen set of test ids for reference results.

So no train level is ever a test level. Which level a world plays next is the env's **level
sampler**'s choice: the sets above sample uniformly with the env's generator; any object with a
``sample(count, generator) -> int64 [count]`` method may be passed as ``levels=`` instead (a
curriculum), e.g. ``PrioritisedLevelReplay`` below, which the trainer feeds with per-level scores.

Randomness during a step (forage's item respawns, commons' regrowth, ...) stays on the env's
generator: a level fixes where an episode starts; what happens next depends on the policy anyway,
and keying step draws per world would add a per-world counter to the state of every task for no
gain in what can be named, held out or replayed.

Tasks: ``Scenario.spawn_level(draws)`` draws a reset from ``draws`` (a ``Draws``); the default
``Scenario.spawn(generator)`` calls it with ``GeneratorDraws(generator)``, which makes exactly the
calls ``torch.rand(..., generator=)`` would, so an env without ``levels=`` draws the numbers it
always drew. A task that only implements ``spawn(generator)`` still works, without levels.
"""
from __future__ import annotations

import argparse
import numbers

import numpy as np
import torch

from marl_render.keyed_random import KeyedRandom, derive_keys
from marl_render.validation import describe

TEST_START = 2 ** 40  # train ids lie in [0, TEST_START), test ids in [TEST_START, LEVEL_LIMIT)
LEVEL_LIMIT = 2 ** 62
# The frozen published test set: 1,000 ids of the test distribution, chosen once and never changed
# (reference results name it). Ids spaced by a large odd step, so that nothing suggests neighbours.
PUBLISHED_TEST_LEVELS = tuple(2 ** 41 + i * 1_000_003 for i in range(1000))
NAMED = ("train", "test", "published")
MAX_LISTED = 10_000_000  # ids of an explicit list (a list of more is a mistake or an absurd size)


class Draws:
    """What a reset draws from: ``rand``, ``randn`` and ``randint`` like torch's, with the worlds
    first, each call naming its stream (a str: one per purpose). CPU tensors."""

    def rand(self, stream: str, shape: tuple, dtype=torch.float32) -> torch.Tensor:
        raise NotImplementedError

    def randn(self, stream: str, shape: tuple, dtype=torch.float32) -> torch.Tensor:
        raise NotImplementedError

    def randint(self, stream: str, high: int, shape: tuple) -> torch.Tensor:
        raise NotImplementedError


class GeneratorDraws(Draws):
    """Draws from one shared torch.Generator, in call order (the stream names are ignored): what
    every task drew before levels existed, so the default path's numbers are unchanged."""

    def __init__(self, generator: torch.Generator):
        self.generator = generator

    def rand(self, stream, shape, dtype=torch.float32):
        return torch.rand(shape, generator=self.generator, dtype=dtype)

    def randn(self, stream, shape, dtype=torch.float32):
        return torch.randn(shape, generator=self.generator, dtype=dtype)

    def randint(self, stream, high, shape):
        return torch.randint(high, shape, generator=self.generator)


class KeyedDraws(Draws):
    """Draws of world w from its key alone (KeyedRandom): a stream's numbers do not depend on the
    batch, the slot, the order of calls or what was drawn before."""

    def __init__(self, keys: torch.Tensor):
        self.random = KeyedRandom(keys)

    def _per_world(self, shape) -> tuple:
        shape = tuple(shape)
        if not shape or shape[0] != self.random.num_worlds:
            raise ValueError(f"a keyed draw's shape must start with the worlds ({self.random.num_worlds}), "
                             f"got {shape}")
        return shape[1:]

    def rand(self, stream, shape, dtype=torch.float32):
        return self.random.uniform(stream, self._per_world(shape), dtype=dtype)

    def randn(self, stream, shape, dtype=torch.float32):
        return self.random.normal(stream, self._per_world(shape), dtype=dtype)

    def randint(self, stream, high, shape):
        return self.random.randint(stream, 0, high, self._per_world(shape))


def level_keys(level_ids: torch.Tensor, task: str, params, num_agents: int) -> torch.Tensor:
    """[W] int64 keys of the levels: a pure function of the task, its parameters and the level id."""
    return derive_keys(level_ids.cpu(), "level", task, repr(params), num_agents)


class LevelSet:
    """Uniform over a set of level ids: the ids [start, stop) or an explicit list."""

    def __init__(self, name: str, *, start: int | None = None, stop: int | None = None, ids=None):
        self.name, self.start, self.stop = name, start, stop
        self.ids = None if ids is None else torch.as_tensor(ids, dtype=torch.int64)

    def __len__(self) -> int:
        return self.stop - self.start if self.ids is None else self.ids.numel()

    def sample(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """int64 [count]: ids drawn uniformly (with replacement) with `generator`."""
        if self.ids is None:
            return torch.randint(self.start, self.stop, (count,), generator=generator)
        return self.ids[torch.randint(self.ids.numel(), (count,), generator=generator)]

    def __contains__(self, level: int) -> bool:
        if self.ids is None:
            return self.start <= level < self.stop
        return bool((self.ids == level).any())

    def __repr__(self) -> str:
        return f"LevelSet({self.name!r}, {len(self)} levels)"


def train_set(count: int) -> LevelSet:
    """The first `count` train levels, ids 0 .. count - 1."""
    return LevelSet(f"train[:{count}]", start=0, stop=count)


def named_set(name: str) -> LevelSet:
    if name == "train":
        return LevelSet("train", start=0, stop=TEST_START)
    if name == "test":
        return LevelSet("test", start=TEST_START, stop=LEVEL_LIMIT)
    return LevelSet("published", ids=PUBLISHED_TEST_LEVELS)


def as_sampler(value):
    """The levels= option as a level sampler (None: off); TypeError / ValueError naming `levels`."""
    want = (f"None, an int n >= 1 (train levels 0..n-1), a range or list of train ids in [0, {TEST_START}), "
            f"one of {list(NAMED)}, or a level sampler (an object with sample(count, generator))")
    if value is None:
        return None
    if isinstance(value, str):
        if value not in NAMED:
            raise ValueError(f"levels must be {want}, got {value!r}")
        return named_set(value)
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"levels must be {want}, got {describe(value)}")
    if isinstance(value, numbers.Integral):
        if not 1 <= int(value) <= TEST_START:
            raise ValueError(f"levels must be {want}, got {value}")
        return train_set(int(value))
    if callable(getattr(value, "sample", None)) and not isinstance(value, (list, tuple, range, torch.Tensor)):
        return value
    if isinstance(value, range) and value.step == 1:
        if not 0 <= value.start < value.stop <= TEST_START:
            raise ValueError(f"levels must be {want}, got {value} (empty, or reaching the test ids)")
        return LevelSet(f"train[{value.start}:{value.stop}]", start=value.start, stop=value.stop)
    if isinstance(value, (np.ndarray, torch.Tensor)) and value.ndim == 0:  # a scalar array has no len()
        raise TypeError(f"levels must be {want}, got a 0-d {type(value).__name__} {describe(value)}: pass "
                        f"int(levels) for a count, or a 1-d array of ids")
    if isinstance(value, (range, list, tuple, torch.Tensor)) or type(value).__module__ == "numpy":
        if len(value) > MAX_LISTED:
            raise ValueError(f"levels must list at most {MAX_LISTED} ids, got {len(value)}")
        try:
            ids = torch.as_tensor(list(value) if isinstance(value, range) else value)
        except (TypeError, ValueError, RuntimeError, OverflowError) as error:
            raise TypeError(f"levels must be {want}, got {describe(value)}") from error
        if ids.ndim != 1 or ids.numel() == 0 or ids.is_floating_point() or ids.is_complex() or ids.dtype == torch.bool:
            raise ValueError(f"levels as ids must be a non-empty 1-d list of ints, got {describe(value)}")
        ids = ids.to(torch.int64)
        if bool(((ids < 0) | (ids >= TEST_START)).any()):
            raise ValueError(f"levels as a train set must hold ids in [0, {TEST_START}) (test ids start there: "
                             f"use levels='test' or 'published', or reset_to_level), got values in "
                             f"[{int(ids.min())}, {int(ids.max())}]")
        return LevelSet(f"train[{ids.numel()} ids]", ids=ids.unique())
    raise TypeError(f"levels must be {want}, got {describe(value)}")


def levels_option(text: str):
    """A command line's ``--levels`` / ``--eval-levels``: a count n >= 1, or one of the named sets."""
    if text.isdigit() and int(text) >= 1:
        return int(text)
    if text in NAMED:
        return text
    raise argparse.ArgumentTypeError(f"expected a count n >= 1 or one of {list(NAMED)}, got {text!r}")


def require_levels(env, what: str) -> None:
    """ValueError unless `env` (a driver or a front end's core) was built with levels=: `what` (a
    method, a reset option) names what needs them. The one wording of this guard."""
    if env.levels is None:
        raise ValueError(f"{what} needs an env built with levels= (envs/levels.py), and this {env.name!r} env "
                         f"has levels=None")


def check_level_ids(name: str, ids: torch.Tensor, num_worlds: int, where: torch.Tensor | None = None) -> torch.Tensor:
    """ids as int64 [W] on the CPU, each in [0, LEVEL_LIMIT) (only those where `where` [W] is True are
    read; the others are returned as 0); else TypeError / ValueError naming `name`."""
    if not isinstance(ids, torch.Tensor):
        raise TypeError(f"{name} must be an int64 tensor of shape [{num_worlds}], got {describe(ids)}")
    if ids.is_floating_point() or ids.is_complex() or ids.dtype == torch.bool or ids.dtype in (
            torch.uint16, torch.uint32, torch.uint64):
        raise TypeError(f"{name} must be an int64 tensor of shape [{num_worlds}], got dtype {ids.dtype}")
    if tuple(ids.shape) != (num_worlds,):
        raise ValueError(f"{name} must be an int64 tensor of shape [{num_worlds}], got shape {list(ids.shape)}")
    ids = ids.detach().to("cpu", torch.int64)
    if where is not None:
        ids = torch.where(where, ids, 0)
    if bool(((ids < 0) | (ids >= LEVEL_LIMIT)).any()):
        raise ValueError(f"{name} must hold level ids in [0, {LEVEL_LIMIT}), got values in "
                         f"[{int(ids.min())}, {int(ids.max())}]")
    return ids


class PrioritisedLevelReplay:
    """A level sampler for curricula: prioritised level replay (Jiang, Grefenstette & Rocktaeschel
    2021) over a finite set of levels, scored by the trainer.

        plr = PrioritisedLevelReplay(range(200))
        env = make_env("rooms", num_worlds=64, levels=plr)
        ...
        plr.update(info["level"][done], score[done])   # e.g. mean positive value loss of each episode

    ``sample`` draws levels by rank of score (weight 1 / rank ** (1 / temperature)) mixed with
    staleness (levels not sampled for a long time), and levels never scored first. ``update`` is
    the hook: any per-world statistic [W] of the episodes that ended may be the score."""

    def __init__(self, levels, *, temperature: float = 0.3, staleness: float = 0.1):
        ids = as_sampler(levels)
        if isinstance(ids, LevelSet) and ids.name in ("test", "published"):  # a curriculum trains on its levels
            raise ValueError(f"PrioritisedLevelReplay needs a finite train set, got levels={levels!r}: the test "
                             f"levels are for evaluation only (make_env(..., levels={levels!r})), never a training "
                             f"curriculum; pass a count n or a list of train ids")
        if not isinstance(ids, LevelSet) or ids.ids is None and len(ids) > MAX_LISTED:
            raise ValueError(f"PrioritisedLevelReplay needs a finite train set of at most {MAX_LISTED} levels, "
                             f"got {describe(levels)}")
        for name, value in (("temperature", temperature), ("staleness", staleness)):
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
                raise TypeError(f"PrioritisedLevelReplay needs {name} to be a number, got {describe(value)}")
        if not (0 < temperature < float("inf")) or not 0 <= staleness <= 1:
            raise ValueError(f"PrioritisedLevelReplay needs temperature > 0 and staleness in [0, 1], got "
                             f"temperature={temperature!r}, staleness={staleness!r}")
        self.ids = ids.ids if ids.ids is not None else torch.arange(ids.start, ids.stop)
        self.temperature, self.staleness = temperature, staleness
        self.scores = torch.zeros(self.ids.numel(), dtype=torch.float64)
        self.seen = torch.zeros(self.ids.numel(), dtype=torch.bool)
        self.last_sampled = torch.zeros(self.ids.numel(), dtype=torch.int64)
        self.clock = 0

    def update(self, level_ids, scores) -> None:
        """Record the score of each level in level_ids [n] (the latest episode's score replaces the old)."""
        level_ids = torch.as_tensor(level_ids).reshape(-1)
        scores = torch.as_tensor(scores, dtype=torch.float64).detach().reshape(-1)  # a value loss's graph stays out
        if level_ids.is_floating_point() or level_ids.dtype == torch.bool:
            raise TypeError(f"update needs integer level_ids, got dtype {level_ids.dtype}")
        level_ids = level_ids.to(torch.int64)
        if level_ids.shape != scores.shape or not bool(torch.isfinite(scores).all()):
            raise ValueError(f"update needs level_ids and finite scores of the same shape [n], got shapes "
                             f"{list(level_ids.shape)} and {list(scores.shape)}")
        slot = torch.searchsorted(self.ids, level_ids)
        known = (slot < self.ids.numel()) & (self.ids[slot.clamp_max(self.ids.numel() - 1)] == level_ids)
        if not bool(known.all()):
            raise ValueError(f"update got level ids outside this sampler's set: {level_ids[~known][:5].tolist()}")
        # A level given twice keeps its last score (the latest episode); torch leaves duplicate writes unordered.
        last = torch.full((self.ids.numel(),), -1, dtype=torch.int64).scatter_reduce(
            0, slot, torch.arange(slot.numel()), "amax")
        written = last >= 0
        self.scores[written], self.seen[written] = scores[last[written]], True

    def weights(self) -> torch.Tensor:
        """[n] sampling probabilities of the levels (unscored levels first, while any are left)."""
        if not bool(self.seen.all()):
            return (~self.seen).double() / (~self.seen).sum()
        rank = torch.empty_like(self.scores)
        rank[self.scores.argsort(descending=True, stable=True)] = torch.arange(1, rank.numel() + 1,
                                                                                dtype=torch.float64)
        score = rank ** (-1 / self.temperature)
        stale = (self.clock - self.last_sampled).double()
        stale = stale / stale.sum() if bool(stale.sum() > 0) else torch.full_like(stale, 1 / stale.numel())
        return (1 - self.staleness) * score / score.sum() + self.staleness * stale

    def sample(self, count: int, generator: torch.Generator) -> torch.Tensor:
        pick = torch.multinomial(self.weights(), count, replacement=True, generator=generator)
        self.clock += 1
        self.last_sampled[pick] = self.clock
        return self.ids[pick]
