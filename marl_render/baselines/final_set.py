"""The sealed final evaluation set: how many episodes it needs.

    python -m marl_render.baselines.final_set      # per task: the episodes a 5% standard error needs

The final set (settings.EVALUATION_SETS["final"]) was committed, seed and episode count, before
anything was scored on it; ``marl_render.envs.evaluation.evaluate`` refuses its seed unless called
with ``final=True`` (``python -m marl_render.baselines --eval-set final --final``), so that it is
scored once, by the final runs.

Its episode count: a row's standard error, sd / sqrt(n), must be under ``TARGET`` (5%) of the task's
random-to-heuristic range. The per-episode sd is estimated per task from the committed runs on the
publication worlds (docs/baselines/<task>[-state]/seed<k>/result.json): the largest sample sd among
the random policy's, the heuristic's and every learned policy's returns. A task needs
n > (sd / (TARGET * range))^2 episodes; the set takes the largest over tasks times ``MARGIN`` (a
later policy may vary more), rounded up to a multiple of ``ROUND_TO``.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

from .published import ROOT

TARGET = 0.05  # standard error as a fraction of the random-to-heuristic range
MARGIN = 1.5
ROUND_TO = 64


def needed_episodes(sd: float, value_range: float, target: float = TARGET) -> int:
    """The fewest episodes n with sd / sqrt(n) < target * |value_range| (at least 1)."""
    if value_range == 0:
        raise ValueError("value_range must not be 0 (random and heuristic score alike: no range to resolve)")
    return max(1, math.floor((sd / (target * abs(value_range))) ** 2) + 1)


def per_task(root=ROOT) -> dict:
    """{task: {"range", "sd", "episodes"}} from every committed run under `root` (seed folders)."""
    found: dict = {}
    for path in sorted(Path(root).glob("*/seed*/result.json")):
        result = json.loads(path.read_text())
        evaluation = result["evaluation"]
        value_range = evaluation["heuristic"]["mean"] - evaluation["random"]["mean"]
        sd = max(statistics.stdev(evaluation[k]["per_episode"]) for k in ("random", "heuristic", "policy"))
        task = found.setdefault(result["env"], {"range": value_range, "sd": 0.0})
        task["sd"] = max(task["sd"], sd)
    for task in found.values():
        task["episodes"] = needed_episodes(task["sd"], task["range"])
    return found


def final_episodes(tasks: dict) -> int:
    """The set's episode count: the most any task needs, times MARGIN, rounded up to ROUND_TO."""
    most = max(task["episodes"] for task in tasks.values())
    return ROUND_TO * math.ceil(most * MARGIN / ROUND_TO)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.final_set", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default=ROOT, help="folder of the committed runs (default: %(default)s)")
    args = parser.parse_args(argv)
    tasks = per_task(args.root)
    print("| task | random-to-heuristic range | largest per-episode sd | episodes for a 5% standard error |")
    print("|---|---:|---:|---:|")
    for env, task in tasks.items():
        print(f"| {env} | {task['range']:.4g} | {task['sd']:.4g} | {task['episodes']} |")
    print(f"\nthe final set: {final_episodes(tasks)} episodes (the most, x {MARGIN:g}, rounded up to {ROUND_TO})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
