"""What accuracy costs in learning: one task trained for the same env steps under each setting.

    python -m marl_render.baselines.learning_accuracy                  # runs + report
    python -m marl_render.baselines.learning_accuracy --report-only    # report from the runs there

Each setting changes one thing against the reference (the baseline's defaults: 32 px RGB, no
anti-aliasing, the task's own physics substeps, 2 for spread): the resolution (48, 64 px), MSAA 4, finer
physics (4, 8 substeps; coarser than 2 is refused by spread's no-tunnelling bound) and
grayscale pixels. Every run is ``python -m marl_render.baselines`` with the same budget in env
steps (``--env-steps``: "the same budget" means the same experience, whatever a step costs) and the
settings' options (``--env-option``: the training and evaluation envs both use the setting, as a
user who picked it would), for every seed. What a setting costs is its measured env steps per
second of training (one run at a time by default; with --jobs 2 two share the cores, which changes
the timings and not the results). A run whose result.json is complete and not truncated is kept, so
an interrupted study resumes; interrupting the study (Ctrl-C, SIGTERM) stops its running trainings
too. Options not listed below go to every run's ``python -m marl_render.baselines`` as they are
(e.g. ``--worlds 64``).

Writes OUT/<setting>-seed<S>/ (each run's result.json, curve.png, actor.pt) and the report:
OUT/../learning.json (per setting: each seed's greedy return, env steps, env steps per second,
and the mean over seeds), OUT/../learning.md (the table, the recommendation notes of
OUT/../learning_notes.md if present) and OUT/../learning.png (training return against
wall-clock and against env steps, mean over seeds).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

from .run import parse_args as learner_args

# name -> (what changes, the baselines CLI options that make it)
SETTINGS: dict = {
    "32px": ("reference: 32 px RGB, no AA, the task's substeps", ["--resolution", "32"]),
    "48px": ("resolution 48", ["--resolution", "48"]),
    "64px": ("resolution 64", ["--resolution", "64"]),
    "32px-msaa4": ("MSAA 4 samples", ["--resolution", "32", "--env-option", "multisamples=4"]),
    "32px-substeps4": ("physics substeps 4 (finer)", ["--resolution", "32", "--env-option", "physics_substeps=4"]),
    "32px-substeps8": ("physics substeps 8 (finer)", ["--resolution", "32", "--env-option", "physics_substeps=8"]),
    "32px-gray": ("grayscale pixels", ["--resolution", "32", "--grayscale"]),
}
REFERENCE = "32px"
CURVE_BINS = 12  # points of the averaged training curves


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.learning_accuracy", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="spread", help="the task (default: spread)")
    parser.add_argument("--env-steps", type=int, default=250_000,
                        help="budget of every run in env steps summed over worlds (default: %(default)s)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="training seeds (default: 0 1)")
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=list(SETTINGS),
                        help="settings to run (default: all)")
    parser.add_argument("--episodes", type=int, default=32, help="evaluation episodes (default: 32)")
    parser.add_argument("--jobs", type=int, choices=(1, 2), default=1, help="runs at a time (default: 1)")
    parser.add_argument("--out", default="docs/accuracy/learning", help="folder of the runs (default: %(default)s)")
    parser.add_argument("--report-only", action="store_true", help="only write the report from existing runs")
    args, args.learner = parser.parse_known_args(argv)
    if args.env_steps < 1:
        parser.error(f"--env-steps must be >= 1, got {args.env_steps}")
    if len(set(args.seeds)) != len(args.seeds):
        parser.error(f"--seeds must be distinct, got {' '.join(map(str, args.seeds))}")
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    for setting in args.settings:  # the learner's own checks, before any run starts
        learner_args(command(args, setting, args.seeds[0])[3:])
    return args


def run_folder(out: Path, setting: str, seed: int) -> Path:
    return out / f"{setting}-seed{seed}"


def command(args, setting: str, seed: int) -> list:
    return [sys.executable, "-m", "marl_render.baselines", "--env", args.env, "--seed", str(seed),
            "--env-steps", str(args.env_steps), "--episodes", str(args.episodes),
            *SETTINGS[setting][1], *args.learner, "--out", str(run_folder(Path(args.out), setting, seed))]


def finished(folder: Path) -> bool:
    """Whether the run in `folder` is complete: its result.json reads as a whole, with the final
    evaluation, and was not cut short by a safety cap."""
    try:
        result = json.loads((folder / "result.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(result, dict) and "policy" in result.get("evaluation", {}) and not result.get("truncated")


def stop(process: subprocess.Popen) -> None:
    """End a training run and everything it started (its own process group): SIGTERM, then SIGKILL."""
    if process.poll() is not None:
        return
    for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 10.0)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(wait)
            return
        except subprocess.TimeoutExpired:
            continue


def terminate_on_sigterm() -> None:
    """SIGTERM (as from `kill` or a job scheduler) unwinds like Ctrl-C, so that running trainings are stopped."""
    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")
    signal.signal(signal.SIGTERM, handler)


def run_all(args) -> None:
    """Every (setting, seed) not finished, `args.jobs` at a time, with progress lines. Each training
    runs in its own process group, stopped with the study however the study ends."""
    todo = [(s, seed) for seed in args.seeds for s in args.settings
            if not finished(run_folder(Path(args.out), s, seed))]
    total = len(todo)
    print(f"{total} run(s) of {args.env_steps:,} env steps to do, {args.jobs} at a time", flush=True)
    running: list = []
    done = 0
    terminate_on_sigterm()
    try:
        while todo or running:
            while todo and len(running) < args.jobs:
                setting, seed = todo.pop(0)
                folder = run_folder(Path(args.out), setting, seed)
                folder.mkdir(parents=True, exist_ok=True)
                (folder / "result.json").unlink(missing_ok=True)  # a partial or truncated one: the run starts over
                log = open(folder / "run.log", "w")  # noqa: SIM115 (closed when the run ends)
                process = subprocess.Popen(command(args, setting, seed), stdout=log, stderr=subprocess.STDOUT,
                                           start_new_session=True)
                running.append((setting, seed, process, log))
                print(f"started {setting} seed {seed} (pid {process.pid})", flush=True)
            time.sleep(0.5)
            for entry in list(running):
                setting, seed, process, log = entry
                if process.poll() is None:
                    continue
                running.remove(entry)
                log.close()
                done += 1
                state = "done" if process.returncode == 0 else f"FAILED (exit {process.returncode}, see run.log)"
                print(f"[{done}/{total}] {setting} seed {seed}: {state}", flush=True)
    finally:
        for _, _, process, log in running:
            stop(process)
            log.close()


def summarise(args) -> dict:
    """{setting: {"label", "runs": [per seed], "mean", ...}} of the runs in args.out."""
    summary: dict = {}
    for setting in args.settings:
        runs = []
        for seed in args.seeds:
            folder = run_folder(Path(args.out), setting, seed)
            if not finished(folder):
                continue
            r = json.loads((folder / "result.json").read_text())
            runs.append({"seed": seed, "return": r["evaluation"]["policy"]["mean"],
                         "return_std": r["evaluation"]["policy"]["std"], "env_steps": r["env_steps"],
                         "training_seconds": r["training_seconds"],
                         "env_steps_per_second": r["env_steps"] / r["training_seconds"],
                         "random": r["evaluation"]["random"]["mean"], "heuristic": r["evaluation"]["heuristic"]["mean"],
                         "command": r["command"], "curve": [(p["seconds"], p["env_steps"], p["episode_return"])
                                                            for p in r["curve"] if p["episode_return"] is not None]})
        if runs:
            returns = [r["return"] for r in runs]
            summary[setting] = {
                "label": SETTINGS[setting][0], "runs": runs, "seeds": len(runs),
                "return_mean": statistics.fmean(returns),
                "return_spread": statistics.stdev(returns) if len(returns) > 1 else 0.0,
                "env_steps_mean": statistics.fmean(r["env_steps"] for r in runs),
                "env_steps_per_second_mean": statistics.fmean(r["env_steps_per_second"] for r in runs)}
    return summary


def table(summary: dict) -> str:
    ref = summary.get(REFERENCE)
    rows = ["| setting | greedy return, mean over seeds (± spread) | per seed | env steps | env steps/s "
            "| steps/s vs reference |", "|---|---:|---|---:|---:|---:|"]
    for setting, s in summary.items():
        speed = s["env_steps_per_second_mean"] / ref["env_steps_per_second_mean"] if ref else float("nan")
        per_seed = " / ".join(f"{r['return']:.0f}" for r in s["runs"])
        rows.append(f"| {setting}: {s['label']} | {s['return_mean']:.1f} ± {s['return_spread']:.1f} | {per_seed} | "
                    f"{s['env_steps_mean'] / 1e3:,.0f} k | {s['env_steps_per_second_mean']:,.0f} | {speed:.2f}x |")
    return "\n".join(rows)


def mean_curve(runs: list, key: int) -> tuple:
    """(x, y) of the seeds' training returns averaged in CURVE_BINS bins of x (key 0: seconds, 1: steps)."""
    top = min(max(p[key] for p in r["curve"]) for r in runs if r["curve"])
    xs, ys = [], []
    for i in range(CURVE_BINS):
        low, high = top * i / CURVE_BINS, top * (i + 1) / CURVE_BINS
        values = [p[2] for r in runs for p in r["curve"] if low < p[key] <= high]
        if values:
            xs.append((low + high) / 2)
            ys.append(statistics.fmean(values))
    return xs, ys


def plot(summary: dict, path: Path, env: str, env_steps: int) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for setting, s in summary.items():
        axes[2].errorbar(s["env_steps_per_second_mean"], s["return_mean"], yerr=s["return_spread"], marker="o",
                         capsize=3, label=setting)
        runs = [r for r in s["runs"] if r["curve"]]  # a run too short for an episode to end has none
        for ax, key, scale in ((axes[0], 0, 1 / 60), (axes[1], 1, 1e-6)):
            xs, ys = mean_curve(runs, key) if runs else ([], [])
            ax.plot([x * scale for x in xs], ys, marker=".", label=setting)
    axes[0].set_xlabel("wall-clock minutes of training")
    axes[1].set_xlabel("million env steps")
    axes[2].set_xlabel("env steps per second of training")
    axes[0].set_ylabel("training episode return (mean over seeds)")
    axes[2].set_ylabel("final greedy return (mean ± spread over seeds)")
    first = next(iter(summary.values()))["runs"][0]
    for ax in axes:
        ax.axhline(first["random"], color="grey", linestyle="--", linewidth=0.8)
    axes[2].legend(fontsize=8)
    figure.suptitle(f"MAPPO on {env} for the same env steps ({env_steps:,} per run); grey: random policy", fontsize=10)
    figure.tight_layout(rect=(0, 0, 1, 0.95))  # room for the title above the plots
    figure.savefig(path, dpi=100)
    plt.close(figure)


def report(args) -> None:
    summary = summarise(args)
    if not summary:
        raise SystemExit(f"no runs under {args.out}: run without --report-only first")
    docs = Path(args.out).parent
    stripped = {k: {**v, "runs": [{n: x for n, x in r.items() if n != "curve"} for r in v["runs"]]}
                for k, v in summary.items()}
    (docs / "learning.json").write_text(json.dumps({"env": args.env, "env_steps": args.env_steps,
                                                    "seeds": args.seeds, "settings": stripped}, indent=1))
    plot(summary, docs / "learning.png", args.env, args.env_steps)
    notes = docs / "learning_notes.md"
    first = next(iter(summary.values()))["runs"][0]
    text = "\n".join([
        f"# What accuracy costs in learning ({args.env})",
        "",
        "Generated by `python -m marl_render.baselines.learning_accuracy --report-only` from the runs in",
        f"`{args.out}/` (made by the same command without `--report-only`). MAPPO from pixels, "
        f"{args.env_steps:,} env steps per run (the same experience for every setting; what a setting costs is",
        f"its env steps per second), seeds {', '.join(map(str, args.seeds))};",
        "each setting changes one thing against the reference and is used for training and evaluation. The",
        f"greedy return is over {args.episodes} evaluation episodes; \"± spread\" is the standard deviation",
        "between seeds.",
        f"Random scores {first['random']:.1f}, the scripted heuristic {first['heuristic']:.1f}.",
        "",
        table(summary),
        "",
        "![training return against wall-clock and env steps; greedy return against speed](learning.png)",
        "",
        *([notes.read_text().strip(), ""] if notes.is_file() else []),
        "Each run's command is in its result.json (`command`).",
        "",
    ])
    (docs / "learning.md").write_text(text)
    print(f"wrote {docs / 'learning.md'}, learning.json and learning.png ({len(summary)} settings)", flush=True)


def main(argv=None) -> int:
    args = parse_args(argv)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        run_all(args)
    report(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
