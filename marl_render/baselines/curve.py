"""curve.png of a run (the training episodes' return against env steps and against wall-clock), and a
picture comparing runs of one task (`python -m marl_render.baselines.curve --compare ...`)."""
from __future__ import annotations

import argparse
import json

from marl_render.util.extras import needs_extra


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend; MissingExtraError naming the plots extra without it."""
    with needs_extra("plots", "the baselines' curves"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_curve(result: dict, path: str) -> None:
    plt = pyplot()

    points = [p for p in result["curve"] if p["episode_return"] is not None]
    shaped = ", ".join(f"{k}={v}" for k, v in result.get("train_options", {}).items())
    training = "training episodes (sampled actions)" + (f"\nwith the training reward: {shaped}" if shaped else "")
    evaluation = result["evaluation"]
    levels = (("random", "grey", "--"), ("heuristic", "orange", "-."), ("policy", "green", ":"))
    figure, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, key, scale, label in ((axes[0], "env_steps", 1e-6, "million env steps (all worlds)"),
                                  (axes[1], "seconds", 1 / 60, "wall-clock minutes of training (2 CPU cores)")):
        ax.plot([p[key] * scale for p in points], [p["episode_return"] for p in points], marker=".",
                label=training)
        checkpoints = result.get("checkpoints", [])
        if checkpoints:
            ax.errorbar([c[key] * scale for c in checkpoints], [c["mean"] for c in checkpoints],
                        yerr=[c["std"] for c in checkpoints], color="purple", marker="s", markersize=3,
                        linestyle="none", capsize=2, label="greedy checkpoints (development set, mean ± std)")
        for name, color, style in levels:
            r = evaluation[name]
            shown = "final policy, greedy" if name == "policy" else name
            ax.axhline(r["mean"], color=color, linestyle=style, label=f"{shown}: {r['mean']:.4g} ± {r['std']:.2g}")
        ax.set_xlabel(label)
    axes[0].set_ylabel("episode return (mean over evaluated agents)")
    axes[1].legend(fontsize=8, loc="best")
    hp = result["hyperparameters"]
    source = f"{hp['resolution']}x{hp['resolution']} pixels" if result["obs"] == "pixels" else "state"
    scored = result.get("evaluation_set", f"seed {result['seeds']['evaluation']}")
    figure.suptitle(f"MAPPO on {result['env']} from {source}, {hp['worlds']} worlds, "
                    f"{result['wall_clock_seconds'] / 60:.1f} min; final policy and references on the {scored} "
                    "evaluation set", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def plot_comparison(results: dict, path: str) -> None:
    """One picture of several runs of a task ({label: result}): the training episodes' return against
    env steps and against wall-clock, each run's greedy checkpoints (if any) and its final greedy
    evaluation as a marker at its end."""
    plt = pyplot()

    figure, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for (label, result), color in zip(results.items(), ("tab:blue", "tab:red", "tab:green", "tab:purple"),
                                      strict=False):
        points = [p for p in result["curve"] if p["episode_return"] is not None]
        final = result["evaluation"]["policy"]
        for ax, key, scale in ((axes[0], "env_steps", 1e-6), (axes[1], "seconds", 1 / 60)):
            ax.plot([p[key] * scale for p in points], [p["episode_return"] for p in points], color=color,
                    linewidth=0.8, label=f"{label}: training episodes")
            checkpoints = result.get("checkpoints", [])
            if checkpoints:
                ax.plot([c[key] * scale for c in checkpoints], [c["mean"] for c in checkpoints], color=color,
                        marker="s", markersize=3, linestyle="none", label=f"{label}: greedy checkpoints")
            end = (result["env_steps"] if key == "env_steps" else result["training_seconds"]) * scale
            ax.errorbar([end], [final["mean"]], yerr=[final["std"]], color=color, marker="o", capsize=3,
                        label=f"{label}: final greedy {final['mean']:.4g} ± {final['std']:.2g}")
    first = next(iter(results.values()))
    axes[0].axhline(first["evaluation"]["random"]["mean"], color="grey", linestyle="--", label="random")
    axes[0].set_xlabel("million env steps (all worlds)")
    axes[1].set_xlabel("wall-clock minutes of training")
    axes[0].set_ylabel("episode return")
    axes[1].legend(fontsize=7, loc="best")
    figure.suptitle(f"MAPPO on {first['env']} from {first['obs']}: " + " against ".join(results), fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.curve",
                                     description="One picture comparing runs of a task: "
                                                 "--compare old=A/result.json new=B/result.json --out cmp.png")
    parser.add_argument("--compare", nargs="+", required=True, metavar="LABEL=RESULT_JSON")
    parser.add_argument("--out", required=True, help="the picture (.png)")
    args = parser.parse_args(argv)
    results = {}
    for item in args.compare:
        label, sep, path = item.partition("=")
        if not sep:
            parser.error(f"--compare takes LABEL=RESULT_JSON, got {item!r}")
        with open(path) as f:
            results[label] = json.load(f)
    plot_comparison(results, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
