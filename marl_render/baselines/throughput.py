"""Training throughput of learner variants, measured side by side: each round runs every variant once,
in turn (A B C A B C ...), so that a machine whose speed drifts slows them alike.

    python -m marl_render.baselines.throughput --rounds 3 --out out/throughput \\
        --variant "old=/path/to/old/checkout::--env spread --updates 12 --torch-threads 1" \\
        --variant "new=::--env spread --updates 12"

A variant is LABEL=PYTHONPATH::ARGS: ARGS go to ``python -m marl_render.baselines`` (with
``--episodes 2 --checkpoint-every 0`` added: only training is timed), PYTHONPATH (may be empty:
this checkout) picks the code, so an older commit's worktree can run beside this one. The figures
come from each run's result.json: env steps per second of training (env_steps / training_seconds),
the env's share of it, and the stage shares. Prints one JSON object (medians and every round) and
writes it to OUT/throughput.json.

``--cpus 1`` pins every run to CPU 1 (``os.sched_setaffinity``; torch's threads, the renderer's and
the overlapped update then share that core): two instances on CPUs 0 and 1 measure the setting of
two trainings at a time, one core each.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.throughput", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variant", action="append", required=True, metavar="LABEL=PYTHONPATH::ARGS")
    parser.add_argument("--rounds", type=int, default=3, help="runs of each variant (default: 3)")
    parser.add_argument("--out", required=True, help="folder of the runs and throughput.json")
    parser.add_argument("--cpus", type=int, nargs="+", default=None, help="CPUs every run is pinned to "
                                                                         "(default: those of this process)")
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")
    available = os.sched_getaffinity(0)
    if args.cpus is not None and not set(args.cpus) <= available:
        parser.error(f"--cpus must be among this process's CPUs {sorted(available)}, got {args.cpus}")
    variants = {}
    for text in args.variant:
        label, sep, rest = text.partition("=")
        path, sep2, options = rest.partition("::")
        if not (sep and sep2 and label.isidentifier()) or label in variants:
            parser.error(f"--variant must be LABEL=PYTHONPATH::ARGS with a new identifier LABEL, got {text!r}")
        variants[label] = (path, options.split())
    args.variants = variants
    return args


def run_once(path: str, options: list, folder: Path, cpus: list | None) -> dict:
    env = dict(os.environ, **({"PYTHONPATH": path} if path else {}))
    load = os.getloadavg()[0]
    command = [sys.executable, "-m", "marl_render.baselines", *options, "--episodes", "2", "--checkpoint-every", "0",
               "--out", str(folder.resolve())]
    subprocess.run(command, env=env, check=True, capture_output=True, cwd=path or None,
                   preexec_fn=None if cpus is None else lambda: os.sched_setaffinity(0, cpus))
    result = json.loads((folder / "result.json").read_text())
    seconds = result["training_seconds"]
    return {"env_steps_per_second": result["env_steps"] / seconds, "env_share": result["env_seconds_in_training"]
            / seconds, "stage_shares": {k: v / seconds for k, v in result.get("stage_seconds", {}).items()},
            "training_seconds": seconds, "training_cpu_seconds": result.get("training_cpu_seconds"),
            "env_steps": result["env_steps"], "load_average_1min": load,
            "torch_threads": result["hyperparameters"].get("torch_threads"), "cpus": cpus}


def main(argv=None) -> int:
    args = parse_args(argv)
    runs: dict = {label: [] for label in args.variants}
    for round_ in range(args.rounds):
        for label, (path, options) in args.variants.items():
            runs[label].append(run_once(path, options, Path(args.out) / f"{label}-round{round_}", args.cpus))
            speed = runs[label][-1]["env_steps_per_second"]
            print(f"round {round_} {label}: {speed:,.0f} env steps/s", file=sys.stderr, flush=True)
    first = statistics.median(r["env_steps_per_second"] for r in next(iter(runs.values())))
    summary = {}
    for label, rows in runs.items():
        median = statistics.median(r["env_steps_per_second"] for r in rows)
        summary[label] = {"command": " ".join(args.variants[label][1]), "pythonpath": args.variants[label][0],
                          "env_steps_per_second_median": median, "ratio_to_first": median / first,
                          "env_share_median": statistics.median(r["env_share"] for r in rows),
                          "stage_shares_median": {k: statistics.median(r["stage_shares"][k] for r in rows)
                                                  for k in rows[0]["stage_shares"]},
                          "rounds": rows}
    text = json.dumps(summary, indent=1)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "throughput.json").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
