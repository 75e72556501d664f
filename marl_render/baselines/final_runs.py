"""The final runs: each frozen published row trained once more, in the reproducible mode, and scored
once on the sealed final set (issue 38).

    python -m marl_render.baselines.final_runs                    # every final command, one a line
    python -m marl_render.baselines.final_runs --run --jobs 2     # trains the missing ones, then the page
    python -m marl_render.baselines.final_runs --run --tasks speaker_listener
    python -m marl_render.baselines.final_runs --report           # docs/final.md from the runs
    python -m marl_render.baselines.ablate --constant --eval-set final --final --root docs/final --tasks ...
    python -m marl_render.baselines.ablate --final docs/final/tag/seed0 ...   # the pixel runs' view ablations

A final run is its published entry's command (published.RUNS: step budget, env and training options,
hyperparameters) with three changes: ``--reproducible`` (float32, kernels pinned, one torch thread:
reproducible.py; 0.7-1.9x the published runs' training time on an AMD EPYC), ``--eval-set final
--final`` (the sealed set of final_set.py, which ``evaluate`` refuses without --final) and its folder,
docs/final/<task>[-state]/seed<k>.

Only the FROZEN tasks have final runs. Their published entries are frozen (tests/test_final_runs.py pins
each entry's settings, so that a change to one fails until its final runs are deleted and the change is
said): a final run is trained once with them, and the sealed set scores it once. The five tasks of issue
41 were frozen later (stop 49) at their published budgets, which are short (a quarter or less of what
their notes estimate learning needs): their final rows judge the rows the results table publishes. A
longer budget for them would be a new development choice, and its runs would need a new sealed set, since
this one will have scored them. A run whose result.json exists is kept, so a batch cut short resumes.

The page judges each row as the results table does (report.learned_verdict): above random and the best
constant action across seeds and, from pixels, a view ablation that costs every seed return; both
baselines computed on the sealed episodes with ablate.py, after the runs.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import shlex
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from . import published
from .report import across_seeds, constant_cell, learned_verdict, load_constant_actions, read_result
from .settings import task_hyperparameters

ROOT = "docs/final"
PAGE = "docs/final.md"
EVALUATION_SET = "final"
# Tasks whose development choices are frozen (published.RUNS entries, the learner, the evaluation):
# the nine trained at full budgets before issue 41 (stop 40), then issue 41's five at their short budgets.
FROZEN = ("capture_flag", "cartpole", "commons", "forage", "push", "rooms", "speaker_listener", "spread", "tag",
          "clean_up", "cooking", "coop_mining", "matrix", "territory")


def settings_digest(env: str, obs: str) -> str:
    """16 hex digits of everything a final run of `env` from `obs` trains with: its step budget, env and
    training options and the hyperparameters they resolve to (the task's defaults under the entry's
    overrides). A frozen row's digest must not change once its final runs exist."""
    entry = published.RUNS[env][obs]
    resolved = dataclasses.asdict(task_hyperparameters(env, **entry.hyperparameters))
    settings = {"env_steps": entry.env_steps, "env_options": dict(entry.env_options),
                "train_options": dict(entry.train_options), "hyperparameters": resolved}
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]


def argv(env: str, obs: str, seed: int, root=ROOT) -> list[str]:
    """The arguments of ``python -m marl_render.baselines`` for the final run of `env` from `obs`, `seed`."""
    if env not in FROZEN:
        raise ValueError(f"env must be one of the frozen tasks {list(FROZEN)}, got {env!r}")
    entry = published.RUNS[env][obs]
    return published.learner_argv(
        env, obs, seed, budget=[published.BUDGET_FLAG, str(entry.env_steps)],
        evaluation=[published.EVALUATION_SET_FLAG, EVALUATION_SET, "--final", "--reproducible"],
        hyperparameters=entry.hyperparameters, env_options=entry.env_options, train_options=entry.train_options,
        out=published.run_folder(root, env, obs, seed))


def commands(root=ROOT, tasks=FROZEN) -> list[str]:
    """Every final command of `tasks`, seed by seed, so that a batch cut short leaves whole seeds."""
    return ["python -m marl_render.baselines " + shlex.join(argv(env, obs, seed, root))
            for seed in published.SEEDS for obs in published.OBSERVATIONS for env in tasks]


def missing(root=ROOT, tasks=FROZEN) -> list[list[str]]:
    """The learner argv of every final run of `tasks` without a result.json, in commands()' order."""
    return [argv(env, obs, seed, root) for seed in published.SEEDS for obs in published.OBSERVATIONS
            for env in tasks if not (published.run_folder(root, env, obs, seed) / "result.json").is_file()]


def load(root=ROOT) -> dict:
    """{(task, obs): [result.json dicts by seed]} of the final runs found under `root`, read and checked
    as the results table's (report.read_result: with its view ablation where one was run)."""
    found = {}
    for env in FROZEN:
        for obs in published.OBSERVATIONS:
            for seed in published.SEEDS:
                path = published.run_folder(root, env, obs, seed) / "result.json"
                if path.is_file():
                    found.setdefault((env, obs), []).append(read_result(path))
    return found


def row_interval(returns: list) -> str:
    """mean [95% percentile bootstrap interval over seeds] (stats.py); one seed has no interval."""
    if not returns:
        return "-"
    if len(returns) < 2:
        return f"{returns[0]:.3g} (1 seed)"
    estimate = across_seeds(np.asarray(returns, dtype=np.float64))  # as the results table's rows
    return f"{estimate.point:.3g} [{estimate.low:.3g}, {estimate.high:.3g}]"


def ablation_cell(results: list) -> str:
    """The mean return with the views zeroed / another world's, over the ablated seeds; "–" from the state."""
    if results[0]["obs"] != "pixels":
        return "–"
    ablated = [r["ablation"]["views"] for r in results if "ablation" in r]
    if not ablated:
        return "not run"
    zeros, shifted = (float(np.mean([views[view]["mean"] for views in ablated])) for view in ("zeros", "shifted"))
    return f"{zeros:.3g} / {shifted:.3g}" + (f" ({len(ablated)} seeds)" if len(ablated) < len(results) else "")


def published_returns(env: str, obs: str, root=published.ROOT) -> list:
    """The published row's returns per seed (the publication set, the default mode), for comparison."""
    paths = [published.run_folder(root, env, obs, seed) / "result.json" for seed in published.SEEDS]
    return [json.loads(path.read_text())["evaluation"]["policy"]["mean"] for path in paths if path.is_file()]


def report(root=ROOT, page=PAGE, published_root=published.ROOT) -> str:
    """docs/final.md: every frozen row's final runs so far, beside random, the heuristic and the best
    constant action on the same sealed episodes, their view ablations, whether the row counts as learned,
    the published row, and the rows still to train (if any)."""
    runs = load(root)
    constants = load_constant_actions(Path(root))
    lines = ["# The final runs: reproducible mode, scored once on the sealed set", "",
             f"<!-- Generated by python -m marl_render.baselines.final_runs --report from {root}/; "
             "do not edit by hand. -->", "",
             "Each frozen published row ([results](results.md)) trained once more with its published command "
             "in the reproducible mode (float32, kernels pinned, one torch thread: the same bits on the same "
             "CPU, not across CPUs, [training](training.md); the last column names each row's CPU) and "
             "scored once on the sealed final set (its seed and "
             "episode count committed before anything was scored on it: `marl_render/baselines/final_set.py`). "
             "Return per episode: each seed's mean over the set's episodes; the row's mean with a 95% bootstrap "
             "interval over seeds. Random, the heuristic and the best constant action (each action held by "
             "every evaluated agent for whole episodes, the best one: `python -m marl_render.baselines.ablate "
             "--constant --eval-set final --final`) play the same sealed episodes. The view ablation (pixel "
             "rows: `python -m marl_render.baselines.ablate --final RUN`, replayed in the reproducible mode) "
             "scores each run's actor on its own sealed episodes with every view replaced by zeros / by "
             "another world's, the mean over seeds. A row counts as learned only if it beats random and the "
             "best constant action across seeds and, from pixels, both ablations cost every seed return "
             "(as in [results](results.md)). The last column but one is the published row "
             "([results](results.md)): the same settings in the default mode, scored on the publication "
             "worlds. These ablations and constant actions were computed once, after the runs, and no "
             "choice followed them. The five tasks of issue 41 (clean_up, cooking, coop_mining, matrix, "
             "territory) were frozen later, at their published budgets, a quarter or less of what learning them "
             "is estimated to need: their rows judge the published rows, not what longer training reaches.", "",
             "| task | observation | seeds | return per seed | mean [95% interval] | random | heuristic "
             "| best constant action | view ablation: zeros / shifted | counts as learned | published row | CPU |",
             "|---|---|---:|---|---:|---:|---:|---:|---:|---|---:|---|"]
    for (env, obs), results in sorted(runs.items()):
        returns = [r["evaluation"]["policy"]["mean"] for r in results]
        cpus = sorted({r["machine"]["cpu"]["model"] for r in results})
        references = results[0]["evaluation"]
        lines.append(f"| {env} | {obs} | {len(results)} | " + " / ".join(f"{v:.3g}" for v in returns)
                     + f" | {row_interval(returns)} | {references['random']['mean']:.3g}"
                     f" | {references['heuristic']['mean']:.3g}"
                     f" | {constant_cell(constants.get(env))} | {ablation_cell(results)}"
                     f" | {learned_verdict(results, constants.get(env))}"
                     f" | {row_interval(published_returns(env, obs, published_root))}"
                     f" | {', '.join(cpus)} |")
    todo = missing(root)
    done = f"Final runs done: {sum(len(r) for r in runs.values())} of " \
           f"{len(FROZEN) * len(published.OBSERVATIONS) * len(published.SEEDS)}"
    if todo:
        lines += ["", f"{done}; still to train ({len(todo)}), "
                  "`python -m marl_render.baselines.final_runs --run --jobs 2` trains them:", "", "```"]
        lines += ["python -m marl_render.baselines " + shlex.join(a) for a in todo] + ["```", ""]
    else:
        lines += ["", f"{done}; none left to train.", ""]
    text = "\n".join(lines)
    Path(page).write_text(text)
    return text


def main(argv_=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.final_runs", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="store_true", help="train every final run without a result.json, then "
                                                           "write the page")
    parser.add_argument("--report", action="store_true", help="write the page from the runs found")
    parser.add_argument("--tasks", nargs="+", choices=FROZEN, default=list(FROZEN), metavar="TASK",
                        help="with --run or the listing: only these frozen tasks")
    parser.add_argument("--root", default=ROOT, help="folder of the final runs (default: %(default)s)")
    parser.add_argument("--page", default=PAGE, help="the page --report and --run write (default: %(default)s)")
    parser.add_argument("--jobs", type=int, default=1, help="runs at a time with --run (default: 1)")
    args = parser.parse_args(argv_)
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")
    if not (args.run or args.report):
        print("\n".join(commands(args.root, args.tasks)))
        return 0
    if args.run:
        pending = [[sys.executable, "-m", "marl_render.baselines", *a] for a in missing(args.root, args.tasks)]
        with ThreadPoolExecutor(args.jobs) as pool:  # threads only wait on the runs' processes
            codes = list(pool.map(published.run_quietly, pending))
        failed = [" ".join(c[2:]) for c, code in zip(pending, codes, strict=True) if code != 0]
        if failed:
            print("failed (rerun --run to retry them):\n  " + "\n  ".join(failed), file=sys.stderr)
            return 1
    report(args.root, args.page)
    return 0


if __name__ == "__main__":
    sys.exit(main())
