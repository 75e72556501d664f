"""The report's pictures across seeds: one per task and observation (training return with its band
over seeds against env steps and against wall-clock, the greedy checkpoints, the final policies)
and one across tasks (normalised scores with their intervals and the performance profile)."""
from __future__ import annotations

import numpy as np

from marl_render.populations import stats

LEVELS = (("random", "grey", "--"), ("heuristic", "orange", "-."))
SEED_COLORS = ("tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
OBS_COLORS = {"pixels": "tab:blue", "state": "tab:red"}


def _pyplot():
    try:
        import matplotlib
    except ImportError as exc:  # an optional dependency (the "bench" extra)
        raise ImportError("the report's pictures need matplotlib: pip install 'marl-render[bench]'") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def training_curve(result: dict, key: str) -> tuple[np.ndarray, np.ndarray]:
    """(x, return) of a run's training episodes, x being `key` ("env_steps" or "seconds");
    updates in which no episode ended are left out."""
    points = [(p[key], p["episode_return"]) for p in result.get("curve", []) if p.get("episode_return") is not None]
    x, y = (np.array(values, dtype=np.float64) for values in zip(*points, strict=True)) if points else ([], [])
    return np.asarray(x), np.asarray(y)


def band(curves: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(grid, mean, min, max) over the (x, y) curves, each interpolated at every x of any of them
    inside the range all of them cover; None where they share no range."""
    curves = [(x, y) for x, y in curves if len(x)]
    if not curves:
        return None
    start, stop = max(x[0] for x, _ in curves), min(x[-1] for x, _ in curves)
    grid = np.unique(np.concatenate([x for x, _ in curves]))
    grid = grid[(grid >= start) & (grid <= stop)]
    if grid.size == 0:
        return None
    values = np.stack([np.interp(grid, x, y) for x, y in curves])
    return grid, values.mean(axis=0), values.min(axis=0), values.max(axis=0)


def plot_task(env: str, obs: str, results: list, path) -> None:
    """The training return of every seed of `env` from `obs`: mean and min-max band, against
    env steps (with each seed's greedy checkpoints and final policy) and against wall-clock."""
    plt = _pyplot()
    figure, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    seeds = [r["seeds"]["train"] for r in results]
    for ax, key, scale, label in ((axes[0], "env_steps", 1e-6, "million env steps (all worlds)"),
                                  (axes[1], "seconds", 1 / 60, "wall-clock minutes of training")):
        named = ax is axes[1]  # the band and the levels are named in the right legend, the seeds in the left
        spread = band([training_curve(r, key) for r in results])
        if spread is not None:
            grid, mean, low, high = spread
            several = len(results) > 1
            if several:
                ax.fill_between(grid * scale, low, high, alpha=0.25, color="tab:blue",
                                label=f"training episodes, min-max over {len(results)} seeds" if named else None)
            ax.plot(grid * scale, mean, color="tab:blue",
                    label=f"training episodes{', mean over seeds' if several else ''}" if named else None)
        for name, color, style in LEVELS:
            level = np.mean([r["evaluation"][name]["mean"] for r in results])
            ax.axhline(level, color=color, linestyle=style, label=f"{name}: {level:.4g}" if named else None)
        ax.set_xlabel(label)
    for seed, result, color in zip(seeds, results, SEED_COLORS * len(results), strict=False):
        checkpoints = result.get("checkpoints", [])
        if checkpoints:
            axes[0].plot([c["env_steps"] * 1e-6 for c in checkpoints], [c["mean"] for c in checkpoints], marker="o",
                         markersize=3, linestyle=":", color=color, label=f"seed {seed}: greedy, development worlds")
        axes[0].plot(result["env_steps"] * 1e-6, result["evaluation"]["policy"]["mean"], marker="*", markersize=11,
                     linestyle="none", color=color,
                     label=f"seed {seed}: final greedy policy, {result['evaluation_set']} worlds (the row)")
    axes[0].set_ylabel("episode return (mean over evaluated agents)")
    for ax in axes:
        ax.legend(fontsize=7, loc="best")
    figure.suptitle(f"MAPPO on {env} from {obs}: seed{'s' if len(seeds) > 1 else ''} "
                    f"{', '.join(map(str, seeds))}", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def plot_aggregate(estimates: dict, profiles: dict, path) -> None:
    """Left: each aggregate of the normalised scores per observation, its point and 95% interval.
    Right: the performance profiles (fraction of runs above each normalised score) with bands.
    `estimates`: {obs: {aggregate: stats.Estimate}}; `profiles`: {obs: (thresholds, profile, low, high)}."""
    plt = _pyplot()
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    names = list(stats.AGGREGATES)
    offsets = np.linspace(-0.15, 0.15, max(len(estimates), 1))
    for offset, (obs, by_name) in zip(offsets, estimates.items(), strict=True):
        y = np.arange(len(names)) + offset
        points = np.array([by_name[n].point for n in names])
        lows, highs = np.array([by_name[n].low for n in names]), np.array([by_name[n].high for n in names])
        left.errorbar(points, y, xerr=[points - lows, highs - points], fmt="o", capsize=4, color=OBS_COLORS[obs],
                      label=f"from {obs}")
    left.set_yticks(range(len(names)), names)
    left.invert_yaxis()
    left.set_xlabel("normalised score (random 0, heuristic 1), 95% interval")
    left.legend(fontsize=8)
    for obs, (taus, profile, low, high) in profiles.items():
        right.plot(taus, profile, color=OBS_COLORS[obs], label=f"from {obs}")
        right.fill_between(taus, low, high, color=OBS_COLORS[obs], alpha=0.2)
    right.set_xlabel("normalised score τ")
    right.set_ylabel("fraction of runs with score > τ")
    right.legend(fontsize=8)
    figure.suptitle("MAPPO across tasks: stratified bootstrap over seeds", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
