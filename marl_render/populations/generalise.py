"""How saved runs generalise: their return on their training levels, on test levels and on test
levels under held-out looks, each beside random and the heuristic, in one call.

    python -m marl_render.generalise out/forage/seed0                         # one run
    python -m marl_render.generalise out/forage/seed0 out/forage/seed1 out/forage/seed2 --out out/forage/gen
    python -m marl_render.generalise out/forage/seed0 --heldout               # and its held-out scenarios
    python -m marl_render.generalise --import my_tasks out/my_task/seed0      # a run of a user's task

A run is a folder that ``python -m marl_render.baselines`` wrote (result.json and actor.pt; train
with ``--levels 200 --appearance train`` for a finite train set with per-level looks). Its greedy
policy (``marl_render.policies.load_policy``) plays `episodes` episodes (one per world, env seed
`seed`, no autoreset, the task's length or `max_steps`) of each evaluation set:

* training levels: the levels and looks it trained with (none: the env's default resets);
* test levels: ``levels="published"`` (the frozen test set, ids from 2**40 on, never trained on)
  with its training looks;
* test levels, held-out looks: the same levels under ``appearance="heldout"`` (hues and patterns
  that never appear in training).

Random and the heuristic play the same levels with the same seed (they read the state and the
action mask, never pixels, so looks change neither: they play each level set once). A return is
``marl_render.envs.evaluation.evaluate``'s: the evaluated agents' summed reward over an episode,
averaged over them; opponents play random actions. Each cell gives the mean over episodes and its
95% percentile bootstrap interval over episodes; ``normalised`` is (return - random) / (heuristic -
random) on the same set; the gap is the training levels' return minus the set's, raw and
normalised by the test set's heuristic - random. Several runs of one task (seeds) add a summary
across runs: each cell's mean over runs with its 95% bootstrap interval over runs.

``--heldout`` also plays the task's held-out scenarios (marl_render/heldout.py, a user's too:
``register_heldout``) with ``marl_render.evaluate.evaluate(gap=True)``: per scenario the focal
return, its normalised score and the gap to the training condition, normalised per scenario by
heuristic - random, so that tasks of different return scales average fairly.

Prints one table per task (``--json``: the JSON instead); ``--out PREFIX`` also writes PREFIX.json
and PREFIX.md.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np
import torch

from marl_render.envs import env_class
from marl_render.envs.evaluation import evaluate, heuristic_policy, random_policy
from marl_render.envs.task_imports import add_import_option, load_user_tasks, register_task_option

from . import stats
from .bots import POPULATIONS
from .evaluate import check_seed, evaluate_heldout, out_problem
from .heldout import heldout_scenario, list_heldout
from .policies import load_policy, required_env_kwargs

SETS = {  # evaluation set -> its make_env keywords (None: the run's own)
    "training levels": {"levels": None, "appearance": None},
    "test levels": {"levels": "published", "appearance": None},
    "test levels, held-out looks": {"levels": "published", "appearance": "heldout"},
}
TRAINING = "training levels"
EPISODES, SEED = 32, 1000  # the trainer's development evaluation set
REPS = 2000  # bootstrap resamples of an interval


def run_settings(run: str) -> dict:
    """The task, the env keywords and the training levels and looks of run folder `run`."""
    policy = load_policy(run)  # checks the folder, its result.json and actor.pt
    with open(os.path.join(run, "result.json")) as f:
        result = json.load(f)
    task = result.get("env")
    if not isinstance(task, str):
        raise ValueError(f"{run}/result.json names no task (its 'env'), got {task!r}")
    if not env_class(task).has_levels():
        raise ValueError(f"run {run}: task {task!r} draws its resets with spawn(generator), so it has no levels to "
                         f"hold out (spawn_level(draws) gives it levels: docs/authoring.md); score it on held-out "
                         f"scenarios with python -m marl_render.evaluate instead")
    options = {k: v for k, v in (result.get("env_options") or {}).items() if k != "appearance"}
    return {"task": task, "env_kwargs": {**options, **required_env_kwargs(policy)},
            "levels": policy.env_kwargs.get("levels"), "appearance": policy.env_kwargs.get("appearance"),
            "seed": (result.get("seeds") or {}).get("train"), "num_agents": policy.num_agents}


def interval(values, reps: int = REPS) -> dict:
    """Mean of `values` with its 95% percentile bootstrap interval (stats.py, rliable's method)."""
    values = np.asarray(values, dtype=np.float64)
    if not np.isfinite(values).all():
        return {"mean": float(values.mean()), "low": math.nan, "high": math.nan, "n": len(values)}
    estimate = stats.stratified_bootstrap(values[:, None], stats.mean, reps=reps)
    return {"mean": estimate.point, "low": estimate.low, "high": estimate.high, "n": len(values)}


def normalised(value: float, random: float, heuristic: float) -> float:
    """0 at random, 1 at the heuristic; NaN where the two are equal."""
    return (value - random) / (heuristic - random) if heuristic != random else math.nan


def generalise(runs, *, episodes: int = EPISODES, seed: int = SEED, max_steps: int | None = None,
               heldout: bool = False) -> dict:
    """The train / test / held-out-looks table of run folders `runs` (see the module docstring):
    ``{"runs": [one entry per run], "summary": {task: across-run cells}, ...}``."""
    runs = [runs] if isinstance(runs, (str, os.PathLike)) else list(runs)
    if not runs:
        raise ValueError("runs must name at least one run folder of python -m marl_render.baselines, got none")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 2:
        raise ValueError(f"episodes must be an int >= 2 (an interval over episodes), got {episodes!r}")
    check_seed(seed)
    folders = [os.path.realpath(run) for run in runs]  # "run" and "run/" are one run, not two seeds
    repeated = sorted({str(run) for run, folder in zip(runs, folders, strict=True) if folders.count(folder) > 1})
    if repeated:
        raise ValueError(f"runs must name each run folder once (each is one seed of the summary), got {repeated} "
                         f"naming the same folder")
    settings = {str(run): run_settings(str(run)) for run in runs}
    length = {} if max_steps is None else {"max_steps": max_steps}
    references: dict = {}  # (task, env keywords, levels) -> random's and the heuristic's returns
    entries = []
    for run, own in settings.items():
        print(f"generalise: {run} ({own['task']}) ...", file=sys.stderr, flush=True)
        cells = {}
        for name, keywords in SETS.items():
            levels = own["levels"] if keywords["levels"] is None else keywords["levels"]
            appearance = own["appearance"] if keywords["appearance"] is None else keywords["appearance"]
            looks = {k: v for k, v in (("levels", levels), ("appearance", appearance)) if v is not None}
            common = dict(episodes=episodes, seed=seed, **own["env_kwargs"], **length)
            played = evaluate(own["task"], load_policy(run), **common, **looks)
            key = repr((own["task"], sorted(common.items()), levels))
            if key not in references:
                plain = {k: v for k, v in looks.items() if k != "appearance"}
                references[key] = {label: evaluate(own["task"], policy, **common, **plain)["mean"]
                                   for label, policy in (("random", random_policy), ("heuristic", heuristic_policy))}
            ref = references[key]
            cells[name] = {"levels": levels, "appearance": appearance, "return": interval(played["per_episode"]),
                           "per_episode": played["per_episode"], **ref,
                           "normalised": normalised(played["mean"], ref["random"], ref["heuristic"])}
        train = cells[TRAINING]["return"]["mean"]
        test = cells["test levels"]
        for cell in cells.values():
            cell["gap"] = train - cell["return"]["mean"]
            cell["normalised_gap"] = normalised(train, test["random"], test["heuristic"]) - normalised(
                cell["return"]["mean"], test["random"], test["heuristic"])
        entry = {"run": run, "task": own["task"], "seed": own["seed"], "levels": own["levels"],
                 "appearance": own["appearance"], "sets": cells}
        if heldout:
            entry["heldout"] = heldout_rows(run, own, episodes, seed, max_steps)
        entries.append(entry)
    return {"episodes": episodes, "seed": seed, "max_steps": max_steps, "runs": entries, "summary": summary(entries)}


def heldout_rows(run: str, own: dict, episodes: int, seed: int, max_steps: int | None) -> dict:
    """The run on its task's held-out scenarios defined for its team sizes, each gap normalised by
    the scenario's heuristic - random, and their mean."""
    task = own["task"]
    if task not in POPULATIONS:
        return {"rows": [], "note": f"{task} has no held-out scenarios (register_heldout adds them)"}
    fitting = [name for name in list_heldout(task) if heldout_scenario(name).num_agents == own["num_agents"]]
    rows = evaluate_heldout(run, fitting, episodes=episodes, seed=seed, max_steps=max_steps, gap=True) \
        if fitting else []
    for row in rows:
        row["normalised_gap"] = normalised(row["training_condition_return"], row["random_return"],
                                           row["heuristic_return"]) - row["normalised_score"]
    gaps = [row["normalised_gap"] for row in rows if math.isfinite(row["normalised_gap"])]
    return {"rows": rows, "mean_normalised_gap": float(np.mean(gaps)) if gaps else math.nan,
            "scenarios_in_mean": len(gaps)}


def summary(entries: list) -> dict:
    """Per task: each set's return, normalised score and gaps as mean over runs with a 95% bootstrap
    interval over runs (one run: its own numbers, no interval)."""
    out = {}
    for task in dict.fromkeys(entry["task"] for entry in entries):
        mine = [entry for entry in entries if entry["task"] == task]
        out[task] = {"runs": len(mine), "sets": {
            name: {field: interval([pick(entry["sets"][name]) for entry in mine])
                   for field, pick in (("return", lambda c: c["return"]["mean"]),
                                       ("normalised", lambda c: c["normalised"]), ("gap", lambda c: c["gap"]),
                                       ("normalised_gap", lambda c: c["normalised_gap"]))}
            for name in SETS}}
        heldout = [entry["heldout"]["mean_normalised_gap"] for entry in mine if "heldout" in entry]
        if heldout:
            out[task]["heldout_mean_normalised_gap"] = interval(heldout)
    return out


def _cell(c: dict) -> str:
    if not math.isfinite(c["mean"]):
        return "n/a"
    if c["n"] < 2 or not math.isfinite(c["low"]):
        return f"{c['mean']:.2f}"
    return f"{c['mean']:.2f} [{c['low']:.2f}, {c['high']:.2f}]"


def _num(value: float) -> str:
    return f"{value:.2f}" if math.isfinite(value) else "n/a"


def table(result: dict) -> str:
    """The result as markdown: per task, one row per run and set, then the summary across runs."""
    lines = [f"Episodes per cell: {result['episodes']} (env seed {result['seed']}); return: mean [95% bootstrap "
             f"interval over episodes]; normalised: 0 random, 1 heuristic; gap: training levels minus the set "
             f"(normalised gap: on the test set's random-heuristic scale)."]
    for task, summed in result["summary"].items():
        lines += ["", f"## {task}", "", "| run | set | levels | looks | return | random | heuristic | normalised | "
                  "gap | normalised gap |", "|---|---|---|---|---:|---:|---:|---:|---:|---:|"]
        for entry in result["runs"]:
            if entry["task"] != task:
                continue
            for name, c in entry["sets"].items():
                lines.append(f"| {entry['run']} | {name} | {c['levels']} | {c['appearance']} | {_cell(c['return'])} | "
                             f"{_num(c['random'])} | {_num(c['heuristic'])} | {_num(c['normalised'])} | "
                             f"{_num(c['gap'])} | {_num(c['normalised_gap'])} |")
        lines += ["", f"Across {summed['runs']} run(s) (mean [95% bootstrap interval over runs]):", "",
                  "| set | return | normalised | gap | normalised gap |", "|---|---:|---:|---:|---:|"]
        for name, cells in summed["sets"].items():
            lines.append(f"| {name} | " + " | ".join(_cell(cells[f]) for f in ("return", "normalised", "gap",
                                                                               "normalised_gap")) + " |")
        for entry in result["runs"]:
            if entry["task"] == task and "heldout" in entry:
                lines += ["", f"Held-out scenarios of {entry['run']}:", "",
                          "| scenario | focal return | normalised score | training condition | normalised gap |",
                          "|---|---:|---:|---:|---:|"]
                for row in entry["heldout"]["rows"]:
                    lines.append(f"| {row['scenario']} | {_num(row['focal_return_mean'])} | "
                                 f"{_num(row['normalised_score'])} | {_num(row['training_condition_return'])} | "
                                 f"{_num(row['normalised_gap'])} |")
                lines.append(f"\nMean normalised gap over {entry['heldout'].get('scenarios_in_mean', 0)} "
                             f"scenario(s): {_num(entry['heldout'].get('mean_normalised_gap', math.nan))}."
                             + (f" {entry['heldout']['note']}." if "note" in entry["heldout"] else ""))
        if "heldout_mean_normalised_gap" in summed:
            lines.append(f"\nHeld-out scenarios, mean normalised gap across runs: "
                         f"{_cell(summed['heldout_mean_normalised_gap'])}.")
    return "\n".join(lines)


def strict_json(value):
    """`value` with every non-finite float as None, so that strict JSON parsers read the file."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    return value


def main(argv=None) -> int:
    prog = "python -m marl_render.generalise"
    load_user_tasks(argv, prog, ())
    parser = argparse.ArgumentParser(prog=prog, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", metavar="RUN", help="run folders of python -m marl_render.baselines")
    add_import_option(parser)
    parser.add_argument("--episodes", type=int, default=EPISODES, help="episodes per cell (one per world)")
    parser.add_argument("--seed", type=int, default=SEED, help="env seed of every evaluation")
    parser.add_argument("--max-steps", type=int, default=None, help="shorter episodes (default: the task's length)")
    parser.add_argument("--heldout", action="store_true", help="also the task's held-out scenarios")
    parser.add_argument("--json", action="store_true", help="print the JSON instead of the tables")
    parser.add_argument("--out", default=None, help="also write OUT.json and OUT.md")
    parser.add_argument("--torch-threads", type=int, default=1, help="torch threads (1: on a busy machine)")
    args = parser.parse_args(argv)
    if args.episodes < 2:
        parser.error(f"--episodes must be >= 2 (an interval over episodes), got {args.episodes}")
    if args.max_steps is not None and args.max_steps < 1:
        parser.error(f"--max-steps must be >= 1, got {args.max_steps}")
    if not 1 <= args.torch_threads <= (os.cpu_count() or 1):
        parser.error(f"--torch-threads must be in [1, {os.cpu_count() or 1}] (this machine's cores), "
                     f"got {args.torch_threads}")
    if args.out is not None and (not os.path.basename(args.out) or os.path.isdir(args.out)):
        parser.error(f"--out must be a file prefix (OUT.json and OUT.md are written), got {args.out!r}")
    if args.out is not None and out_problem(args.out):  # before the work, not after it
        parser.error(f"--out {args.out!r}: {out_problem(args.out)}")
    for run in args.runs:
        if not os.path.isfile(os.path.join(run, "result.json")) or not os.path.isfile(os.path.join(run, "actor.pt")):
            parser.error(f"RUN must be a run folder of python -m marl_render.baselines (result.json and actor.pt), "
                         f"got {run!r}")
        try:  # a run of a task given as module:Class (--env my_tasks:MyTask) registers it again, by that name
            with open(os.path.join(run, "result.json")) as f:
                task = json.load(f).get("env")
        except (OSError, ValueError, AttributeError) as error:
            parser.error(f"RUN {run!r}: its result.json does not read as a run's ({error})")
        if isinstance(task, str):
            register_task_option(parser, f"RUN {run}'s env", task)
    threads = torch.get_num_threads()
    torch.set_num_threads(args.torch_threads)
    try:
        result = generalise(args.runs, episodes=args.episodes, seed=args.seed, max_steps=args.max_steps,
                            heldout=args.heldout)
    except (ValueError, TypeError) as error:
        parser.error(str(error))
    finally:
        torch.set_num_threads(threads)
    text = table(result)
    if args.out is not None:
        if os.path.dirname(args.out):
            os.makedirs(os.path.dirname(args.out), exist_ok=True)
        with open(args.out + ".json", "w") as f:
            json.dump(strict_json(result), f, indent=1, allow_nan=False)
        with open(args.out + ".md", "w") as f:
            f.write(text + "\n")
    print(json.dumps(strict_json(result), allow_nan=False) if args.json else text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
