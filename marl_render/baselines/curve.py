"""curve.png of a run: the training episodes' return against env steps and against wall-clock."""
from __future__ import annotations


def plot_curve(result: dict, path: str) -> None:
    try:
        import matplotlib
    except ImportError as exc:  # an optional dependency (the "bench" extra)
        raise ImportError("curve.png needs matplotlib: pip install 'marl-render[bench]'") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
