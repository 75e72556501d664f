"""docs/baselines.md (and the summary table of docs/results.md) from the runs' result.json files.

    python -m marl_render.baselines.report      # reads docs/baselines/<task>[-state]/seed<k>/result.json

One row per task: the uniform random policy, the scripted heuristic and the greedy policies
learned from pixels and from the state, each the mean over training seeds with its 95%
stratified bootstrap interval (marl_render.baselines.stats, rliable's method) and every seed's
value; the evaluation worlds every number was scored on; the step budget and the wall-clock.
Then the normalised scores across tasks, and per task and observation the commands, each seed's
run, the greedy checkpoints along training and a picture of the curves across seeds. Also
writes RESULTS/<task>[-state]/curves.png, RESULTS/aggregate.png, RESULTS/marl_eval.json (the
runs in marl-eval's layout) and, between the markers ``<!-- baselines:start -->`` and
``<!-- baselines:end -->``, docs/results.md's table (--readme PAGE names another page, '' none), and
between ``<!-- social:start -->`` and ``<!-- social:end -->`` the mixed-motive rows' social outcomes
(marl_render.baselines.social).

Runs from before the step budgets (RESULTS/<task>[-state|-seedK]/result.json) are read where a
task and observation has no run in seed folders yet.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shlex
import sys
from pathlib import Path

import numpy as np

from marl_render.envs import list_envs
from marl_render.envs.evaluation import SEALED_SEEDS
from marl_render.populations import stats

from . import figures, marl_eval, social
from .ablate import ABLATION, CONSTANT_ACTIONS
from .published import (
    BUDGET_FLAG,
    EVALUATION_SET_FLAG,
    OBSERVATIONS,
    PENDING,
    PENDING_CELL,
    ROOT,
    folder,
    learner_argv,
    published_env_options,
)
from .settings import EVALUATION_SETS, Hyperparameters

START, END = "<!-- baselines:start -->", "<!-- baselines:end -->"
DEFAULTS = dataclasses.asdict(Hyperparameters())
REQUIRED = (("env",), ("obs",), ("seeds", "train"), ("env_steps",), ("evaluation", "policy", "mean"),
            ("evaluation", "random", "mean"), ("evaluation", "heuristic", "mean"))
LEGACY = "before step budgets"


# --- reading the runs ---------------------------------------------------------------------------

def read_result(path: Path) -> dict:
    """One result.json, checked for the fields the report reads; ValueError naming the file."""
    try:
        result = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable result.json ({exc})") from None
    for keys in REQUIRED:
        value = result
        for key in keys:
            if not isinstance(value, dict) or key not in value:
                raise ValueError(f"{path}: result.json has no {'.'.join(keys)}")
            value = value[key]
        if keys[-1] == "mean" and (isinstance(value, bool) or not isinstance(value, (int, float))
                                   or not math.isfinite(value)):
            raise ValueError(f"{path}: {'.'.join(keys)} must be a finite number, got {value!r}")
    if result["obs"] not in OBSERVATIONS:
        raise ValueError(f"{path}: obs must be one of {OBSERVATIONS}, got {result['obs']!r}")
    if not isinstance(result["env"], str):
        raise ValueError(f"{path}: env must be a task name, got {result['env']!r}")
    seed = result["seeds"]["train"]
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"{path}: seeds.train must be an int, got {seed!r}")
    for point in result.get("checkpoints") or ():  # null (a NaN when written, strict_json) reads as NaN again
        if isinstance(point, dict):
            point.update({key: math.nan for key in ("mean", "std", "min", "max") if key in point
                          and point[key] is None})
            if isinstance(point.get("per_episode"), list):
                point["per_episode"] = [math.nan if x is None else x for x in point["per_episode"]]
    result["folder"] = path.parent
    ablation = path.parent / ABLATION
    if ablation.is_file():  # python -m marl_render.baselines.ablate RUN
        result["ablation"] = json.loads(ablation.read_text())
    # Runs before the split into development and publication worlds were scored on the worlds
    # every development choice used.
    result.setdefault("evaluation_set", "development")
    return result


def load_constant_actions(folder_: Path) -> dict:
    """{task: best constant action} of FOLDER/constant_actions.json (python -m marl_render.baselines.ablate
    --constant); {} without the file."""
    path = Path(folder_) / CONSTANT_ACTIONS
    return json.loads(path.read_text()) if path.is_file() else {}


def load_results(folder_: Path) -> dict:
    """{env: {obs: [results ordered by training seed]}} of the runs under `folder_`: the seed
    folders' runs, or the older flat folders' where a task and observation has none."""
    layouts = {}
    for name, pattern in (("seeds", "*/seed*/result.json"), (LEGACY, "*/result.json")):
        grouped: dict = {}
        for path in sorted(Path(folder_).glob(pattern)):
            result = read_result(path)
            result["layout"], result["relative"] = name, path.parent.relative_to(folder_)
            runs = grouped.setdefault((result["env"], result["obs"]), {})
            seed = result["seeds"]["train"]
            if seed in runs:
                raise ValueError(f"two runs of {result['env']} from {result['obs']} with training seed {seed}: "
                                 f"{runs[seed]['folder']} and {path.parent}")
            runs[seed] = result
        layouts[name] = grouped
    runs: dict = {}
    for (env, obs), by_seed in {**layouts[LEGACY], **layouts["seeds"]}.items():
        runs.setdefault(env, {})[obs] = [by_seed[seed] for seed in sorted(by_seed)]
    return runs


def tasks(runs: dict) -> list[str]:
    """Every registered task, then any other task that has runs."""
    return list_envs() + sorted(set(runs) - set(list_envs()))


# --- numbers and cells ----------------------------------------------------------------------------

def digits(*values: float) -> int:
    size = max((abs(v) for v in values), default=0.0)
    return 2 if size < 10 else 1 if size < 100 else 0


def number(value: float, places: int) -> str:
    return f"{value:.{places}f}"


def scores(results: list, policy: str = "policy") -> np.ndarray:
    """Each run's mean return of `policy` ("policy", "random" or "heuristic")."""
    return np.array([r["evaluation"][policy]["mean"] for r in results], dtype=np.float64)


def across_seeds(values: np.ndarray) -> stats.Estimate:
    """The mean over runs with its 95% stratified bootstrap interval (one task: runs resampled)."""
    return stats.stratified_bootstrap(values[:, None], stats.mean)


def interval(e: stats.Estimate, places: int, scale: float = 1, unit: str = "") -> str:
    """"point [low, high]"."""
    point, low, high = (number(v * scale, places) + unit for v in (e.point, e.low, e.high))
    return f"{point} [{low}, {high}]"


def estimate_cell(values: np.ndarray, seeds: list, percent: bool = False) -> str:
    """"mean [low, high]; seeds a/b/c: x / y / z"; the value alone for one run."""
    scale, unit, places = (100, "%", 0) if percent else (1, "", digits(*values))
    if len(values) == 1:
        return number(values[0] * scale, places) + unit
    return (interval(across_seeds(values), places, scale, unit) + f"; seeds {'/'.join(map(str, seeds))}: "
            + " / ".join(number(v * scale, places) + unit for v in values))


def learned_cell(results: list | None, short: bool = False) -> str:
    if not results:
        return "–"
    values, seeds = scores(results), [r["seeds"]["train"] for r in results]
    if len(results) == 1:
        return f"{number(values[0], digits(values[0]))} (seed {seeds[0]} only)"
    return interval(across_seeds(values), digits(*values)) if short else estimate_cell(values, seeds)


def above_random(results: list | None) -> stats.Estimate | None:
    """The learned minus random return, run by run (both scored on the run's evaluation worlds),
    mean over runs with its interval; None for fewer than 2 runs."""
    if not results or len(results) < 2:
        return None
    return across_seeds(scores(results) - scores(results, "random"))


def verdict(results: list | None) -> str:
    if not results:
        return "–"
    difference = above_random(results)
    if difference is None:
        return "not judged (1 seed)"
    return "yes" if difference.low > 0 else "no"


VIEW_Z = 1.96  # a view ablation costs return when its paired drop's 95% normal interval is above 0


def view_drop(result: dict, view: str) -> stats.Estimate:
    """The policy's return minus the ablated one's, episode by episode (the same episodes), its mean
    with a 95% normal interval."""
    drop = (np.array(result["ablation"]["views"]["none"]["per_episode"])
            - np.array(result["ablation"]["views"][view]["per_episode"]))
    half = VIEW_Z * drop.std(ddof=1) / math.sqrt(len(drop)) if len(drop) > 1 else math.inf
    return stats.Estimate(float(drop.mean()), float(drop.mean() - half), float(drop.mean() + half))


def above_constant(results: list, constant: dict | None) -> stats.Estimate | None:
    """Learned minus the best constant action's return, run by run, mean over runs with its interval;
    None for fewer than 2 runs, or a constant action scored on other worlds than the runs."""
    if constant is None or len(results) < 2 or any(r["evaluation_set"] != constant["evaluation_set"]
                                                   or r["seeds"]["evaluation"] != constant["seed"] for r in results):
        return None
    return across_seeds(scores(results) - constant["mean"])


def learned_verdict(results: list | None, constant: dict | None) -> str:
    """Whether a row counts as learned: it beats random and the best constant action across seeds
    (the lower ends of both intervals above 0) and, from pixels, every ablated seed loses return when
    its view is zeros and when it is another world's (view_drop): "yes", "no (why)", or "not judged
    (what is missing)"."""
    if not results:
        return "–"
    if len(results) < 2:
        return "not judged (1 seed)"
    failed, missing = [], []
    if above_random(results).low <= 0:
        failed.append("not above random")
    versus_constant = above_constant(results, constant)
    if versus_constant is None:
        missing.append("no best constant action on its worlds")
    elif versus_constant.low <= 0:
        failed.append("not above the best constant action")
    partly = ""  # the seeds a "yes" rests on, when the view ablation covers only some
    if results[0]["obs"] == "pixels":
        ablated = [r for r in results if "ablation" in r]
        if 0 < len(ablated) < len(results):
            partly = f" (view ablation of seed {', '.join(str(r['seeds']['train']) for r in ablated)} only)"
        if not ablated:
            missing.append("no view ablation")
        elif any(view_drop(r, view).low <= 0 for r in ablated for view in ("zeros", "shifted")):
            failed.append("view ablation costs no return")
    if failed:
        return f"no ({', '.join(failed)})"
    return f"not judged ({', '.join(missing)})" if missing else "yes" + partly


def constant_cell(constant: dict | None) -> str:
    """The best constant action's return and its index."""
    if constant is None:
        return "–"
    return f"{number(constant['mean'], digits(constant['mean']))} (action {constant['action']})"


def reference_cell(by_obs: dict, policy: str) -> str:
    """Random's or the heuristic's return, from the pixel runs where there are some."""
    results = by_obs.get("pixels") or by_obs.get("state")
    if not results:
        return "–"
    values = scores(results, policy)
    if np.all(values == values[0]):  # the same worlds and the same policy give the same return on every run
        return number(values[0], digits(values[0]))
    return estimate_cell(values, [r["seeds"]["train"] for r in results])


def normalised(results: list) -> np.ndarray | None:
    """Each run's (learned - random) / (heuristic - random): 0 is random, 1 the heuristic; None
    where the heuristic does not beat random."""
    random, heuristic = scores(results, "random"), scores(results, "heuristic")
    if np.any(heuristic <= random):
        return None
    return (scores(results) - random) / (heuristic - random)


def normalised_cell(results: list | None) -> str:
    values = normalised(results) if results else None
    if values is None:
        return "–"
    return estimate_cell(values, [r["seeds"]["train"] for r in results], percent=True)


def evaluation_worlds(result: dict) -> str:
    """The run's evaluation set and its env seed ("seed N" alone for a seed outside the named sets)."""
    name, seed = result["evaluation_set"], result["seeds"]["evaluation"]
    return name if name == f"seed {seed}" else f"{name} (seed {seed})"


def scored_on(by_obs: dict) -> str:
    sets = {obs: sorted({evaluation_worlds(r) for r in results})
            for obs, results in by_obs.items() if results}
    unique = {", ".join(s) for s in sets.values()}
    if len(unique) <= 1:
        return unique.pop() if unique else "–"
    return "; ".join(f"{obs}: {', '.join(s)}" for obs, s in sets.items())


def cost_cell(results: list | None) -> str:
    """The step budget (or the old wall-clock budget) and the wall-clock, mean (min-max) over runs."""
    if not results:
        return "–"
    minutes = np.array([r.get("wall_clock_seconds", r.get("training_seconds", 0.0)) for r in results]) / 60
    clock = f"{minutes.mean():.1f} min" + (f" ({minutes.min():.1f}-{minutes.max():.1f})" if len(results) > 1 else "")
    truncated = sum(bool(r.get("truncated")) for r in results)
    if truncated:  # stopped by the opt-in wall-clock cap before the step budget
        clock += f"; {truncated} of {len(results)} truncated by --max-minutes"
    if "budget" in results[0]:
        budgets = sorted({f"{b['env_steps']:,} steps" if b.get("env_steps") else f"{b['updates']:,} updates"
                          for b in (r["budget"] for r in results)})
        return f"{' / '.join(budgets)}; {clock}"
    steps = sorted({r["env_steps"] for r in results})
    reached = f"{steps[0]:,}" + (f"-{steps[-1]:,}" if len(steps) > 1 else "")
    return f"{results[0]['budget_minutes']:g} min wall-clock budget: {reached} steps; {clock}"


# --- the tables -----------------------------------------------------------------------------------

def table(runs: dict, short: bool = False, constants: dict | None = None) -> str:
    """The results table; `constants` ({task: best constant action}) fills the last two columns."""
    head = "| task | random | heuristic | learned from pixels | learned from state |"
    rule = "|---|---:|---:|---:|---:|"
    if short:
        head += " above random (pixels; state) |"
        rule += "---|"
    else:
        head += (" above random (pixels; state) | pixels normalised (random 0%, heuristic 100%) | scored on "
                 "| pixels: budget, wall-clock | state: budget, wall-clock |")
        rule += "---|---:|---|---:|---:|"
    head += " best constant action | counts as learned (pixels; state) |"
    rule += "---:|---|"
    rows = [head, rule]
    for env in tasks(runs):
        by_obs = runs.get(env, {})
        if not by_obs and env in PENDING:  # registered, no runs yet: said so, not left out
            width = rule.count("|") - 1
            cells = ["–", "–", PENDING_CELL, PENDING_CELL, "pending; pending"] + ["–"] * (width - 7) + [
                "pending; pending"]
            rows.append(f"| {env} | " + " | ".join(cells) + " |")
            continue
        pixels, state = by_obs.get("pixels"), by_obs.get("state")
        constant = (constants or {}).get(env)
        row = (f"| {env} | {reference_cell(by_obs, 'random')} | {reference_cell(by_obs, 'heuristic')} "
               f"| {learned_cell(pixels, short)} | {learned_cell(state, short)} "
               f"| {verdict(pixels)}; {verdict(state)} |")
        if not short:
            row += f" {normalised_cell(pixels)} | {scored_on(by_obs)} | {cost_cell(pixels)} | {cost_cell(state)} |"
        row += (f" {constant_cell(constant)} | {learned_verdict(pixels, constant)}; "
                f"{learned_verdict(state, constant)} |")
        rows.append(row)
    return "\n".join(rows)


def aggregate_scores(runs: dict, obs: str) -> tuple[np.ndarray | None, list[str], str]:
    """The (runs, tasks) normalised scores of every task learned from `obs` whose heuristic beats
    random, the tasks, and why there is no matrix (or what was left out)."""
    columns, names, left_out = [], [], []
    pending = [env for env in tasks(runs) if env in PENDING and not runs.get(env)]
    for env in tasks(runs):
        if env in pending:
            continue
        results = runs.get(env, {}).get(obs)
        values = normalised(results) if results else None
        if values is None:
            left_out.append(env)
        else:
            columns.append(values)
            names.append(env)
    notes = ([f"left out (no run, or a heuristic that does not beat random): {', '.join(left_out)}"] * bool(left_out)
             + [f"left out ({PENDING_CELL}): {', '.join(pending)}"] * bool(pending))
    note = "; ".join(notes)
    counts = {len(c) for c in columns}
    if not columns:
        return None, names, "no task has runs"
    if len(counts) > 1 or counts == {1}:
        have = ", ".join(f"{n} {len(c)}" for n, c in zip(names, columns, strict=True))
        return None, names, f"needs at least 2 seeds, the same number on every task (have: {have})"
    return np.stack(columns, axis=1), names, note


def aggregate_section(runs: dict, results_root: Path, docs: Path) -> list[str]:
    parts = ["## Across tasks", "",
             "Normalised score of a run: (learned - random) / (heuristic - random), from that run's own evaluations "
             "(0 is random, 1 the heuristic). Aggregates over every run of every task, with 95% stratified bootstrap "
             "intervals (runs resampled within each task; rliable's IQM, mean, median and optimality gap at 1). "
             "The profile: the fraction of all runs whose score exceeds each threshold.", ""]
    matrices, estimates, profiles = {}, {}, {}
    for obs in OBSERVATIONS:
        matrix, names, note = aggregate_scores(runs, obs)
        if matrix is None:
            parts += [f"- from {obs}: no aggregate, {note}.", ""]
            continue
        matrices[obs] = matrix
        estimates[obs] = {name: stats.stratified_bootstrap(matrix, f) for name, f in stats.AGGREGATES.items()}
        cells = ", ".join(f"{name} {interval(e, 2)}" for name, e in estimates[obs].items())
        parts += [f"- from {obs}, {matrix.shape[0]} seeds x {matrix.shape[1]} tasks ({', '.join(names)}): {cells}"
                  + (f"; {note}" if note else "") + ".", ""]
    if matrices:  # one set of thresholds for every profile, from the lowest score to past the heuristic
        every = np.concatenate([m.ravel() for m in matrices.values()])
        thresholds = np.linspace(min(0.0, every.min()), max(1.5, every.max()), 101)
        profiles = {obs: (thresholds, *stats.performance_profile(m, thresholds)) for obs, m in matrices.items()}
    if estimates:
        figures.plot_aggregate(estimates, profiles, results_root / "aggregate.png")
        parts += [f"![normalised scores across tasks]({os.path.relpath(results_root / 'aggregate.png', docs)})", ""]
    return parts


# --- per task -------------------------------------------------------------------------------------

def mean_std(r: dict) -> str:
    """"mean ± std" of an evaluation over its episodes, digits by its size."""
    places = digits(r["mean"], r["std"]) if "std" in r else digits(r["mean"])
    return f"{number(r['mean'], places)}" + (f" ± {number(r['std'], places)}" if "std" in r else "")


def reproducing_command(run: dict) -> str:
    """The run's command with every hyperparameter spelled out, so that it still reproduces the
    run after a task's defaults change."""
    if "budget" in run:
        budget = run["budget"]
        flags = [BUDGET_FLAG, str(budget["env_steps"])] if budget.get("env_steps") else [
            "--updates", str(budget["updates"])]
        if budget.get("max_minutes"):
            flags += ["--max-minutes", f"{budget['max_minutes']:g}"]
        named = run["evaluation_set"] in EVALUATION_SETS
        evaluation = [EVALUATION_SET_FLAG, run["evaluation_set"]] if named else [
            "--eval-seed", str(run["seeds"]["evaluation"])]
        evaluation += ["--final"] if run["seeds"]["evaluation"] in SEALED_SEEDS else []
    else:  # the wall-clock budget and the evaluation seed of the runs before step budgets
        flags = ["--budget-minutes", f"{run['budget_minutes']:g}"]
        evaluation = ["--eval-seed", str(run["seeds"]["evaluation"])]
    evaluation += ["--episodes", str(run["evaluation"]["policy"]["episodes"])]
    # Runs from before the trainer recorded `init` drew the actor with torch's default.
    argv = learner_argv(run["env"], run["obs"], run["seeds"]["train"], budget=flags, evaluation=evaluation,
                        hyperparameters={**run["hyperparameters"], "init": run["hyperparameters"].get("init", "torch")},
                        env_options=published_env_options(run), train_options=run.get("train_options", {}),
                        out=Path(ROOT) / run["relative"])
    return "python -m marl_render.baselines " + shlex.join(argv)


def seeds_table(results: list) -> list[str]:
    rows = ["| seed | final greedy policy (episodes) | random | heuristic | scored on | env steps | updates "
            "| wall-clock | training (env) |", "|---:|---:|---:|---:|---|---:|---:|---:|---:|"]
    for r in results:
        e = r["evaluation"]
        rows.append(f"| {r['seeds']['train']} | {mean_std(e['policy'])} ({e['policy']['episodes']}) "
                    f"| {mean_std(e['random'])} | {mean_std(e['heuristic'])} "
                    f"| {evaluation_worlds(r)} | {r['env_steps']:,}{' (truncated)' if r.get('truncated') else ''} "
                    f"| {r.get('updates', '–')} | {r.get('wall_clock_seconds', 0) / 60:.1f} min "
                    f"| {r.get('training_seconds', 0) / 60:.1f} ({r.get('env_seconds_in_training', 0) / 60:.1f}) min |")
    return rows


def checkpoints_table(results: list) -> list[str]:
    """Greedy returns along training, a row per checkpoint and a column per seed."""
    by_seed = {r["seeds"]["train"]: {c["env_steps"]: c["mean"] for c in r.get("checkpoints", [])} for r in results}
    steps = sorted({s for points in by_seed.values() for s in points})
    if not steps:
        return [f"No greedy evaluations along training recorded (runs {LEGACY})."]
    places = digits(*[v for points in by_seed.values() for v in points.values()])
    rows = ["Greedy returns along training, on the development worlds (the rows are the final policies; no "
            "checkpoint is ever picked for a row):", "",
            "| env steps | " + " | ".join(f"seed {s}" for s in by_seed) + " |", "|---:|" + "---:|" * len(by_seed)]
    for step in steps:
        rows.append(f"| {step:,} | " + " | ".join(number(points[step], places) if step in points else "–"
                                                 for points in by_seed.values()) + " |")
    return rows


def details(env: str, obs: str, results: list, results_root: Path, docs: Path) -> list[str]:
    first = results[0]
    changed = ", ".join(f"{k}={v}" for k, v in first["hyperparameters"].items() if DEFAULTS.get(k) != v) or "none"
    options = ", ".join([f"{k}={v!r} (training and evaluation)" for k, v in first.get("env_options", {}).items()]
                        + [f"{k}={v!r} (training only)" for k, v in first.get("train_options", {}).items()])
    versions = sorted({", ".join(f"{k} {v}" for k, v in r["versions"].items()) for r in results if "versions" in r})
    difference = above_random(results)
    parts = [f"### {env} from {obs}", "", "```", *(reproducing_command(r) for r in results), "```", "",
             *seeds_table(results), ""]
    if difference is not None:
        places = digits(difference.point, difference.low, difference.high)
        parts += [f"Learned minus random, mean over seeds: {interval(difference, places)} "
                  f"({'above' if difference.low > 0 else 'not above'} random).", ""]
    parts += [f"- hyperparameters that differ from the defaults: {changed}",
              f"- env options: {options or 'none (the task as registered)'}",
              *(f"- versions: {v}" for v in versions), ""]
    picture = results_root / folder(env, obs) / "curves.png"
    picture.parent.mkdir(parents=True, exist_ok=True)
    figures.plot_task(env, obs, results, picture)
    parts += [f"![{env} from {obs} across seeds]({os.path.relpath(picture, docs)})", ""]
    return parts + [*checkpoints_table(results), ""]


def document(runs: dict, results_root: Path, docs: Path, notes: str = "", marl_eval_problems=(),
             constants: dict | None = None) -> str:
    defaults = ", ".join(f"{k}={v}" for k, v in DEFAULTS.items())
    parts = [
        "# Reference results: every task trained from pixels",
        "",
        "Generated by `python -m marl_render.baselines.report` from `docs/baselines/<task>[-state]/seed<k>/"
        "result.json`; the runs by `make baselines` (the commands of `python -m marl_render.baselines.published`, "
        "listed under each task).",
        "",
        "Returns are those of `marl_render.envs.evaluation.evaluate`: the sum of the evaluated agents' rewards over "
        "an episode, averaged over them and over the evaluation episodes; opponents (tag's prey, push's and "
        "capture_flag's second team) play random actions in training and in every row. *Learned* is the greedy "
        "policy of MAPPO (PPO's clipped loss and GAE in plain torch, held equal to TorchRL's ClipPPOLoss and GAE "
        "by tests: one actor shared by the trained agents, on each agent's own "
        "egocentric pixels or its state observation; a centralised critic on the state observations of all agents).",
        "",
        "- **Rows are the final policy only**: each run's greedy policy when its budget ends. The greedy "
        "evaluations along training (under each task) show how stable it is; none is ever picked for a row.",
        "- **Across seeds**: each learned cell is the mean over training seeds, its 95% stratified bootstrap "
        "interval in brackets (50,000 resamples of the seeds, percentile method, fixed random seed: rliable's "
        "method, `marl_render.baselines.stats`), then every seed's value. With 3 seeds that interval of the mean "
        "is exactly the lowest to the highest seed (a resample of three copies of one seed has probability "
        "1/27 > 2.5%).",
        "- **Above random** is judged across seeds on the run-by-run difference learned - random (both scored on "
        "the same worlds): *yes* when the lower end of its 95% interval is above 0, which with 3 seeds means every "
        "seed beats random. One seed is not judged.",
        "- **Scored on**: the evaluation worlds of each number. *development* worlds served every development "
        "choice (shaping, hyperparameters, tries); *publication* worlds scored the published runs, and three "
        "choices were made after scores on them were in (the budgets kept after half-budget runs, orthogonal "
        "init as the default, the rows that kept `--init torch`: docs/baselines/notes.md), so they are a second "
        "development set, not a sealed test set.",
        "- **Budgets** are env steps summed over worlds; the wall-clock (mean, min-max over seeds) is what they took "
        "on the machine of the run. Runs from before the step budgets were stopped by a wall-clock budget instead, "
        "so their env steps depend on the machine's speed and load.",
        "",
        "- **Best constant action**: each action held by every evaluated agent for whole episodes, on the "
        "publication worlds, the best one (`python -m marl_render.baselines.ablate --constant`, "
        f"`{CONSTANT_ACTIONS}`; where an agent's mask forbids the action it takes its lowest allowed one). A "
        "policy that never looks can reach it.",
        "- **Counts as learned**: *yes* only when the row beats random and the best constant action across seeds "
        "(both differences, run by run, with the lower end of their 95% interval above 0) and, from pixels, the "
        "view ablation costs return: every ablated run (`python -m marl_render.baselines.ablate RUN`, its "
        f"`{ABLATION}`; only runs whose actor is kept can be ablated) scores lower, episode by episode on its own "
        "evaluation worlds, with its views replaced by zeros and by another world's views (the paired drop's 95% "
        "normal interval above 0). *not judged* says what is missing.",
        "",
        table(runs, constants=constants),
        "",
        f"Default hyperparameters: {defaults}.",
        "",
        *aggregate_section(runs, results_root, docs),
        "## marl-eval and BenchMARL",
        "",
        f"[marl_eval.json]({os.path.relpath(results_root / 'marl_eval.json', docs)}) holds the runs in marl-eval's "
        "JSON layout (the one BenchMARL writes): environment `marl_render`, algorithms `mappo_pixels` and "
        "`mappo_state`, runs `seed_K`, the greedy checkpoints as steps and the final policy's episode returns as "
        "`absolute_metrics` (`marl_render/baselines/marl_eval.py`).",
        "",
        *([f"marl-eval's tools need the same runs and steps on every task; not yet: {p}." for p in marl_eval_problems]
          or ["Every task has the same algorithms, runs and steps, as marl-eval's tools need."]),
        "",
        "## Runs",
        "",
    ]
    for env in tasks(runs):
        for obs in OBSERVATIONS:
            results = runs.get(env, {}).get(obs)
            if results:
                parts += details(env, obs, results, results_root, docs)
                parts += baselines_lines(results, (constants or {}).get(env))
    if notes:
        parts += ["## Findings", "", notes.strip(), ""]
    return "\n".join(parts)


def baselines_lines(results: list, constant: dict | None) -> list[str]:
    """What the row must beat: the best constant action, and each ablated run's returns under the
    view ablation."""
    parts = []
    if constant is not None:
        places = digits(*constant["per_action"])
        parts.append(f"Best constant action on the {constant['evaluation_set']} worlds: action {constant['action']}, "
                     f"{number(constant['mean'], places)} (each action, by index: "
                     + ", ".join(number(m, places) for m in constant["per_action"]) + ").")
    for r in results:
        if "ablation" not in r:
            continue
        views = r["ablation"]["views"]
        places = digits(*(v["mean"] for v in views.values()))
        drops = "; ".join(f"{view} {number(views[view]['mean'], places)} (drop "
                          f"{interval(view_drop(r, view), places)})" for view in ("zeros", "shifted"))
        parts.append(f"View ablation of seed {r['seeds']['train']} ({r['ablation']['episodes']} episodes of its "
                     f"evaluation worlds): as trained {number(views['none']['mean'], places)}"
                     + ("" if r["ablation"]["reproduces_run"] else " (NOT the run's own returns)") + f"; {drops}.")
    return [*(f"- {line}" for line in parts), ""] if parts else []


def update_readme(path: Path, runs: dict, constants: dict | None = None) -> None:
    text = path.read_text()
    if START not in text or END not in text:
        raise ValueError(f"{path} has no {START} ... {END} markers to put the table between")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    path.write_text(f"{head}{START}\n{table(runs, short=True, constants=constants)}\n{END}{tail}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.report", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", default="docs/baselines", help="folder of the runs' folders")
    parser.add_argument("--out", default="docs/baselines.md", help="the document to write")
    parser.add_argument("--readme", default="docs/results.md", help="page whose summary table to rewrite ('' for none)")
    args = parser.parse_args(argv)
    try:
        return write_report(args)
    except (ValueError, OSError) as error:  # a missing folder, a broken run: one line, no traceback
        parser.error(str(error))
    except (TypeError, KeyError, AttributeError) as error:  # a field of the wrong type in some run's result.json
        parser.error(f"a result.json under --results {args.results!r} holds a field of the wrong type "
                     f"({type(error).__name__}: {error}); marl_eval.json and {args.out} were left as they were")


def write_report(args: argparse.Namespace) -> int:
    """What main does once the command line is read; ValueError naming the file or option at fault,
    before anything is written."""
    results_root, out = Path(args.results), Path(args.out)
    if not results_root.is_dir():
        raise ValueError(f"--results must be a folder of runs, got {str(results_root)!r} (no such folder)")
    runs = load_results(results_root)
    if args.readme:  # refused before anything is written when README has no markers
        readme_text = Path(args.readme).read_text()
        if START not in readme_text or END not in readme_text:
            raise ValueError(f"{args.readme} has no {START} ... {END} markers to put the table between")
    constants = load_constant_actions(results_root)
    layout = marl_eval.layout(runs)  # both texts first: a run that breaks them leaves the two files as they were
    notes = results_root / "notes.md"
    text = document(runs, results_root, out.parent, notes.read_text() if notes.is_file() else "",
                    marl_eval.problems(layout), constants)
    marl_eval.write(runs, results_root / "marl_eval.json")
    out.write_text(text)
    if args.readme:
        update_readme(Path(args.readme), runs, constants)
        social.update_page(Path(args.readme), results_root)  # the social outcomes' table, where the page has one
    count = sum(len(results) for by_obs in runs.values() for results in by_obs.values())
    print(f"wrote {out}, {results_root / 'marl_eval.json'} and the pictures ({count} runs)"
          + (f" and {args.readme}" if args.readme else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
