"""rliable's own numbers on fixed inputs, for tests/test_stats.py.

    python tests/rliable_reference.py        # in a venv with rliable, prints REFERENCE for test_stats.py

The venv the recorded values came from (rliable and arch do not import with pandas 3):
    python -m venv /tmp/rliable-venv
    /tmp/rliable-venv/bin/pip install -c constraints.txt rliable==1.2.0 arch==7.2.0 "pandas<3"
    /tmp/rliable-venv/bin/python tests/rliable_reference.py
"""
import json

import numpy as np

# (runs, tasks) scores: 5 runs of 4 tasks, some tied, some negative, some above 1.
SMALL = [[0.12, 0.95, 1.30, -0.20],
         [0.40, 0.95, 0.88, 0.05],
         [0.33, 0.61, 1.02, 0.10],
         [0.90, 0.70, 0.75, -0.05],
         [0.15, 0.82, 1.10, 0.30]]
# 3 runs of 9 tasks at rliable's default 50,000 resamples: more scores than one block of ours.
WIDE = (np.arange(27.0) % 7 / 6 + np.linspace(-0.3, 0.4, 27)).round(4).reshape(3, 9).tolist()
THRESHOLDS = [0.0, 0.25, 0.5, 0.75, 1.0, 1.25]
CASES = [  # (name, scores, aggregate, reps, seed)
    ("small", SMALL, "IQM", 2000, 7), ("small", SMALL, "mean", 2000, 7), ("small", SMALL, "median", 2000, 7),
    ("small", SMALL, "optimality gap", 2000, 7), ("wide", WIDE, "IQM", 50_000, 0),
]
PROFILE_CASE = ("small", SMALL, 2000, 3)


def reference() -> dict:
    """{"name/aggregate": [point, low, high]} and {"profile": [profile, low, high]} from rliable."""
    from rliable import library, metrics

    functions = {"IQM": metrics.aggregate_iqm, "mean": metrics.aggregate_mean,
                 "median": metrics.aggregate_median, "optimality gap": metrics.aggregate_optimality_gap}
    out = {}
    for name, scores, aggregate, reps, seed in CASES:
        np.random.seed(seed)  # rliable draws its resamples from numpy's global generator
        points, intervals = library.get_interval_estimates(
            {"x": np.array(scores)}, lambda s, f=functions[aggregate]: np.array([f(s)]), reps=reps)
        out[f"{name}/{aggregate}"] = [float(points["x"][0]), *map(float, intervals["x"][:, 0])]
    name, scores, reps, seed = PROFILE_CASE
    np.random.seed(seed)
    profiles, intervals = library.create_performance_profile({"x": np.array(scores)}, THRESHOLDS, reps=reps)
    out["profile"] = [profiles["x"].tolist(), intervals["x"][0].tolist(), intervals["x"][1].tolist()]
    return out


if __name__ == "__main__":
    print(json.dumps(reference(), indent=1))
