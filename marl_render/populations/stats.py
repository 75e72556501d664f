"""Scores across seeds as rliable reports them (Agarwal et al. 2021, "Deep RL at the Edge of the
Statistical Precipice"), in numpy.

Scores are a ``(runs, tasks)`` array: one final score per independent run (training seed) and task.

- Aggregates: ``iqm`` (the interquartile mean of all runs and tasks, 25% cut from each end),
  ``mean`` and ``median`` (of the per-task means over runs) and ``optimality_gap`` (how far the
  runs fall short of a target score, scores above it clipped).
- ``stratified_bootstrap``: a 95% percentile confidence interval of any of them, resampling runs
  with replacement within each task (the tasks are kept; only the seeds are redrawn).
- ``performance_profile``: the fraction of runs whose score exceeds each threshold, with its
  interval.

The resampling is rliable's (``rliable.library.StratifiedBootstrap`` on arch's ``IIDBootstrap``,
percentile method): resample ``r`` takes ``scores[idx, task]`` with ``idx`` the next ``(runs,
tasks)`` draw of ``numpy.random.RandomState(seed).randint(0, runs, ...)``. rliable draws those
indices from numpy's global legacy generator, so after ``numpy.random.seed(seed)`` it returns the
very same intervals as these functions (tests/test_stats.py checks it). A fixed seed makes every
report reproducible.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

CONFIDENCE = 0.95
REPS = 50_000  # rliable's default for interval estimates
PROFILE_REPS = 2_000  # rliable's default for performance profiles
SEED = 0
# Resamples are drawn and reduced this many scores at a time (the same stream of draws as one
# block), so that memory stays bounded whatever the number of runs, tasks and resamples.
CHUNK_SCORES = 1 << 20


@dataclasses.dataclass(frozen=True)
class Estimate:
    """A point estimate and its confidence interval [low, high]."""
    point: float
    low: float
    high: float


def check_scores(scores) -> np.ndarray:
    """`scores` as a float64 (runs, tasks) array; ValueError naming what is wrong otherwise."""
    array = np.asarray(scores, dtype=np.float64)
    if array.ndim != 2 or 0 in array.shape:
        raise ValueError(f"scores must be a (runs, tasks) array with at least one of each, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"scores must be finite, got {array[~np.isfinite(array)][:3].tolist()} among them")
    return array


# Each aggregate reduces the last two axes (runs, tasks) of an array, so that it applies to one
# score matrix or to a stack of resampled ones at once.

def iqm(scores: np.ndarray) -> np.ndarray:
    """Interquartile mean over all runs and tasks: the mean of the middle half, cutting
    int(n / 4) scores from each end as scipy.stats.trim_mean(..., 0.25) does."""
    flat = scores.reshape(*scores.shape[:-2], -1)
    count = flat.shape[-1]
    cut = int(0.25 * count)
    return np.partition(flat, (cut, count - cut - 1), axis=-1)[..., cut:count - cut].mean(axis=-1)


def mean(scores: np.ndarray) -> np.ndarray:
    """Mean over tasks of each task's mean over runs."""
    return scores.mean(axis=-2).mean(axis=-1)


def median(scores: np.ndarray) -> np.ndarray:
    """Median over tasks of each task's mean over runs."""
    return np.median(scores.mean(axis=-2), axis=-1)


def optimality_gap(scores: np.ndarray, target: float = 1.0) -> np.ndarray:
    """target minus the mean of the scores clipped at target (0: every run reaches it)."""
    return target - np.minimum(scores, target).reshape(*scores.shape[:-2], -1).mean(axis=-1)


AGGREGATES: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "IQM": iqm, "mean": mean, "median": median, "optimality gap": optimality_gap,
}


def _check_reps_confidence(reps: int, confidence: float) -> None:
    if isinstance(reps, bool) or not isinstance(reps, (int, np.integer)) or reps < 1:
        raise ValueError(f"reps must be an int >= 1, got {reps!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")


def resampled(scores: np.ndarray, statistic: Callable[[np.ndarray], np.ndarray], reps: int, seed: int,
              width: int = 1) -> np.ndarray:
    """`statistic` of `reps` stratified resamples of `scores` (runs redrawn within each task),
    stacked along the first axis, in rliable's order of draws. `width`: the values `statistic`
    makes per score (the thresholds of a profile), to size the blocks."""
    runs, tasks = scores.shape
    rng = np.random.RandomState(seed)
    block = max(1, CHUNK_SCORES // (scores.size * width))
    columns = np.arange(tasks)
    values = []
    for start in range(0, reps, block):
        indices = rng.randint(0, runs, size=(min(block, reps - start), runs, tasks))
        values.append(np.asarray(statistic(scores[indices, columns])))
    return np.concatenate(values)


def percentile_interval(values: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """The two-sided percentile interval of bootstrap `values` along the first axis (numpy's
    linear interpolation, as arch's conf_int)."""
    tail = 100 * (1.0 - confidence) / 2
    low, high = np.percentile(values, [tail, 100 - tail], axis=0)
    return low, high


def stratified_bootstrap(scores, statistic: Callable[[np.ndarray], np.ndarray] = mean, *, reps: int = REPS,
                         confidence: float = CONFIDENCE, seed: int = SEED) -> Estimate:
    """`statistic` of the (runs, tasks) `scores` with its percentile interval over `reps`
    stratified bootstrap resamples. One run gives the interval [point, point]."""
    scores = check_scores(scores)
    _check_reps_confidence(reps, confidence)
    low, high = percentile_interval(resampled(scores, statistic, reps, seed), confidence)
    return Estimate(float(statistic(scores)), float(low), float(high))


def performance_profile(scores, thresholds, *, reps: int = PROFILE_REPS, confidence: float = CONFIDENCE,
                        seed: int = SEED) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The score distribution of rliable (``create_performance_profile`` with its defaults): for
    each threshold, the fraction of all (run, task) scores above it; with its interval.
    Returns (profile, low, high), each shaped like `thresholds`."""
    scores = check_scores(scores)
    _check_reps_confidence(reps, confidence)
    taus = np.asarray(thresholds, dtype=np.float64)
    if taus.ndim != 1 or taus.size == 0 or not np.isfinite(taus).all():
        raise ValueError(f"thresholds must be a non-empty 1-D list of finite numbers, got shape {taus.shape}")

    def fraction_above(s: np.ndarray) -> np.ndarray:
        flat = s.reshape(*s.shape[:-2], -1)
        return (flat[..., None] > taus).mean(axis=-2)

    low, high = percentile_interval(resampled(scores, fraction_above, reps, seed, taus.size), confidence)
    return fraction_above(scores), low, high
