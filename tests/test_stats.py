"""marl_render.baselines.stats against rliable's own numbers: the same point estimates and, with the
same resamples, the same 95% stratified bootstrap intervals, to the last bit."""
import importlib.util

import numpy as np
import pytest

from marl_render.baselines import stats
from rliable_reference import CASES, PROFILE_CASE, THRESHOLDS, reference

# Printed by `python tests/rliable_reference.py` with rliable 1.2.0, arch 7.2.0, numpy 2.4.6,
# scipy 1.17.1, pandas 2.3.3 (Python 3.11): [point, low, high] per case.
RECORDED = {
    "small/IQM": [0.584, 0.465, 0.7310249999999999],
    "small/mean": [0.559, 0.47448750000000006, 0.6515249999999998],
    "small/median": [0.593, 0.46900000000000003, 0.7400249999999998],
    "small/optimality gap": [0.46199999999999997, 0.37749999999999995, 0.5385],
    "wide/IQM": [0.5435933333333334, 0.35104650000000004, 0.7246],
    "profile": [[0.9, 0.7, 0.55, 0.4, 0.15, 0.05], [0.8, 0.55, 0.5, 0.25, 0.05, 0.0],
                [1.0, 0.85, 0.65, 0.55, 0.25, 0.15]],
}


def ours() -> dict:
    out = {}
    for name, scores, aggregate, reps, seed in CASES:
        e = stats.stratified_bootstrap(scores, stats.AGGREGATES[aggregate], reps=reps, seed=seed)
        out[f"{name}/{aggregate}"] = [e.point, e.low, e.high]
    _, scores, reps, seed = PROFILE_CASE
    out["profile"] = [a.tolist() for a in stats.performance_profile(scores, THRESHOLDS, reps=reps, seed=seed)]
    return out


def test_equal_to_rliable_recorded():
    assert ours() == RECORDED


@pytest.mark.skipif(importlib.util.find_spec("rliable") is None, reason="rliable is not installed (the recorded "
                    "values above are checked without it)")
def test_equal_to_rliable_live():
    assert ours() == reference()


def test_wide_case_spans_several_blocks():
    """The 50,000-resample case draws in more than one block: the blocks continue one stream."""
    name, scores, aggregate, reps, seed = CASES[-1]
    assert reps * np.size(scores) > stats.CHUNK_SCORES


def test_three_seeds_interval_is_their_range():
    """With 3 runs of one task, the mean of a resample of three copies of the lowest run has
    probability 1/27 > 2.5%: the 95% interval of the mean is exactly [min, max]."""
    e = stats.stratified_bootstrap([[3.0], [7.5], [4.0]], stats.mean, reps=10_000)
    assert (e.point, e.low, e.high) == (14.5 / 3, 3.0, 7.5)


def test_one_run_has_a_point_interval():
    e = stats.stratified_bootstrap([[2.0, -1.0]], stats.iqm, reps=50)
    assert e == stats.Estimate(0.5, 0.5, 0.5)


def test_iqm_cuts_a_quarter_from_each_end():
    scores = np.array([[1.0, 100.0], [2.0, 3.0], [-50.0, 4.0], [5.0, 6.0]])  # 8 scores: 2 cut each end
    assert stats.iqm(scores) == np.mean([2.0, 3.0, 4.0, 5.0])
    assert stats.optimality_gap(np.array([[0.5, 2.0]])) == 1 - (0.5 + 1.0) / 2


def test_same_seed_same_interval_other_seed_other_interval():
    scores = np.arange(20.0).reshape(5, 4) ** 1.5
    first, again = (stats.stratified_bootstrap(scores, stats.iqm, reps=500, seed=1) for _ in range(2))
    other = stats.stratified_bootstrap(scores, stats.iqm, reps=500, seed=2)
    assert first == again and first.point == other.point and (first.low, first.high) != (other.low, other.high)


@pytest.mark.parametrize("scores, kwargs, message", [
    ([1.0, 2.0], {}, r"scores must be a \(runs, tasks\) array .* got shape \(2,\)"),
    (np.zeros((0, 3)), {}, r"got shape \(0, 3\)"),
    ([[1.0, float("nan")]], {}, "scores must be finite"),
    ([[1.0]], {"reps": 0}, "reps must be an int >= 1, got 0"),
    ([[1.0]], {"reps": 2.5}, "reps must be an int >= 1, got 2.5"),
    ([[1.0]], {"confidence": 95}, r"confidence must be in \(0, 1\), got 95"),
])
def test_bad_input_is_named(scores, kwargs, message):
    with pytest.raises(ValueError, match=message):
        stats.stratified_bootstrap(scores, **kwargs)


def test_bad_thresholds_are_named():
    with pytest.raises(ValueError, match="thresholds must be a non-empty 1-D list"):
        stats.performance_profile([[1.0]], [])
