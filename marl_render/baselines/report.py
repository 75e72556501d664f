"""docs/baselines.md (and README's summary table) from the committed runs' result.json files.

    python -m marl_render.baselines.report                # reads docs/baselines/*/result.json

One table over every task: the uniform random policy, the scripted heuristic, the greedy
policy learned from pixels and the one learned from the state (where a run exists), the
wall-clock and the env steps of each run; then per task the hyperparameters, the command
that reproduces the run and its curve; then RESULTS/notes.md (hand-written findings), if there
is one. A task with no run has a row of dashes. README.md's
table between the markers ``<!-- baselines:start -->`` and ``<!-- baselines:end -->`` is
rewritten too (--readme '' leaves README alone).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import sys
from pathlib import Path

from marl_render.envs import list_envs

from .settings import Hyperparameters

START, END = "<!-- baselines:start -->", "<!-- baselines:end -->"
DEFAULTS = dataclasses.asdict(Hyperparameters())


def load_results(folder: Path) -> dict:
    """{env: {"pixels": [results], "state": [results]}} of the result.json files under `folder`,
    each list ordered by training seed (the first is the row's run; the others are its seeds)."""
    runs: dict = {}
    for path in sorted(folder.glob("*/result.json")):
        result = json.loads(path.read_text())
        result["folder"] = path.parent
        runs.setdefault(result["env"], {}).setdefault(result["obs"], []).append(result)
    for pair in runs.values():
        for results in pair.values():
            results.sort(key=lambda r: r["seeds"]["train"])
    return runs


def mean_std(r: dict | None) -> str:
    """"mean ± std" of an evaluation, digits by its size; a dash for none."""
    if r is None:
        return "–"
    size = max(abs(r["mean"]), r["std"])
    digits = 2 if size < 10 else 1 if size < 100 else 0
    return f"{r['mean']:.{digits}f} ± {r['std']:.{digits}f}"


def _learned(results: list | None) -> str:
    """The greedy policy's return, marked where it does not beat random by a standard error; with
    several seeds, every seed's mean after it."""
    if not results:
        return "–"
    e = results[0]["evaluation"]
    policy, random = e["policy"], e["random"]
    margin = (policy["std"] ** 2 / policy["episodes"] + random["std"] ** 2 / random["episodes"]) ** 0.5
    flag = "" if policy["mean"] > random["mean"] + margin else " (not above random)"
    text = mean_std(policy) + flag
    if len(results) > 1:
        means = [r["evaluation"]["policy"]["mean"] for r in results]
        digits = 0 if max(abs(m) for m in means) >= 100 else 1
        text += (f"; seeds {'/'.join(str(r['seeds']['train']) for r in results)}: "
                 + " / ".join(f"{m:.{digits}f}" for m in means))
    return text


def _cost(results: list | None) -> str:
    if not results:
        return "–"
    run = results[0]
    return f"{run['wall_clock_seconds'] / 60:.1f} min, {run['env_steps'] / 1e6:.2f} M"


def _gap_closed(results: list | None) -> str:
    """How far the learned policy got from random towards the heuristic: (learned - random) /
    (heuristic - random), in percent (100%: as good as the heuristic)."""
    if not results:
        return "–"
    e = results[0]["evaluation"]
    span = e["heuristic"]["mean"] - e["random"]["mean"]
    if span <= 0:
        return "–"
    return f"{100 * (e['policy']['mean'] - e['random']['mean']) / span:.0f}%"


def table(runs: dict, short: bool = False) -> str:
    head = "| task | random | heuristic | learned from pixels | learned from state |"
    rule = "|---|---:|---:|---:|---:|"
    if not short:
        head += (" pixels: random-to-heuristic gap closed | pixels run: wall-clock, env steps "
                 "| state run: wall-clock, env steps |")
        rule += "---:|---:|---:|"
    rows = [head, rule]
    for env in list_envs():
        pair = runs.get(env, {})
        pixels, state = pair.get("pixels"), pair.get("state")
        any_run = pixels or state
        e = any_run[0]["evaluation"] if any_run else None
        row = (f"| {env} | {mean_std(e and e['random'])} | {mean_std(e and e['heuristic'])} | {_learned(pixels)} | "
               f"{_learned(state)} |")
        if not short:
            row += f" {_gap_closed(pixels)} | {_cost(pixels)} | {_cost(state)} |"
        rows.append(row)
    return "\n".join(rows)


def reproducing_command(run: dict) -> str:
    """The run's command with every hyperparameter spelled out, so that it still reproduces the
    run after a task's defaults change."""
    parts = ["python -m marl_render.baselines", f"--env {run['env']}"]
    if run["obs"] != "pixels":
        parts.append(f"--obs {run['obs']}")
    parts += [f"--seed {run['seeds']['train']}", f"--eval-seed {run['seeds']['evaluation']}",
              f"--episodes {run['evaluation']['policy']['episodes']}", f"--budget-minutes {run['budget_minutes']:g}"]
    for name, value in run["hyperparameters"].items():
        flag = "--" + name.replace("_", "-")
        if isinstance(value, bool):
            parts += [flag] if value else []
        else:
            parts.append(f"{flag} {value:g}" if isinstance(value, float) else f"{flag} {value}")
    for flag in ("env", "train"):
        options = run.get(f"{flag}_options", {})
        parts += [f"--{flag}-option {shlex.quote(f'{key}={value!r}')}" for key, value in options.items()]
    parts.append(f"--out docs/baselines/{run['folder'].name}")
    return " ".join(parts)


def details(env: str, run: dict, docs: Path) -> str:
    hp = run["hyperparameters"]
    changed = ", ".join(f"{k}={v}" for k, v in hp.items() if DEFAULTS.get(k) != v) or "none"
    curve = os.path.relpath(run["folder"] / "curve.png", docs)
    e = run["evaluation"]
    options = ", ".join([f"{k}={v!r} (training and evaluation)" for k, v in run.get("env_options", {}).items()]
                        + [f"{k}={v!r} (training only)" for k, v in run.get("train_options", {}).items()])
    return "\n".join([
        f"### {env} from {run['obs']}, seed {run['seeds']['train']}",
        "",
        f"`{reproducing_command(run)}`",
        "",
        f"- greedy policy {mean_std(e['policy'])} over {e['policy']['episodes']} episodes "
        f"(random {mean_std(e['random'])}, heuristic {mean_std(e['heuristic'])}), "
        f"evaluation seed {run['seeds']['evaluation']}",
        f"- {run['wall_clock_seconds'] / 60:.1f} min wall-clock (budget {run['budget_minutes']:g}; training "
        f"{run['training_seconds'] / 60:.1f} min, of which env steps {run['env_seconds_in_training'] / 60:.1f}), "
        f"{run['env_steps']:,} env steps, {run['updates']} updates, seed {run['seeds']['train']}",
        f"- hyperparameters that differ from the defaults: {changed}",
        f"- env options: {options or 'none (the task as registered)'}",
        "- versions: " + ", ".join(f"{k} {v}" for k, v in run["versions"].items()),
        "",
        f"![{env} {run['obs']}]({curve})",
        "",
    ])


def document(runs: dict, docs: Path, notes: str = "") -> str:
    defaults = ", ".join(f"{k}={v}" for k, v in DEFAULTS.items())
    parts = [
        "# Reference results: every task learned from pixels",
        "",
        "Generated by `python -m marl_render.baselines.report` from `docs/baselines/*/result.json`; each run by",
        "the command shown under its task (`python -m marl_render.baselines --env NAME`), on 2 CPU cores.",
        "",
        "Returns are those of `marl_render.envs.evaluation.evaluate`: the sum of the evaluated agents' rewards",
        "over an episode, averaged over them, mean ± std over 32 episodes (seed 1000); opponents (tag's prey,",
        "push's and capture_flag's second team) play random actions in training and in every row. *Learned*",
        "is the greedy policy of MAPPO (TorchRL ClipPPOLoss + GAE: one actor shared by the trained agents,",
        "on each agent's own egocentric pixels or its state observation; a centralised critic on the state",
        "observations of all agents). \"(not above random)\" marks a learned return that does not exceed",
        "random's by one standard error of the difference. *Gap closed*: (learned - random) / (heuristic -",
        "random) of the pixel run, how close pixels get to the scripted heuristic (which reads the state).",
        "Env steps are summed over worlds.",
        "",
        table(runs),
        "",
        f"Default hyperparameters: {defaults}.",
        "",
        "## Runs",
        "",
    ]
    for env in list_envs():
        for obs in ("pixels", "state"):
            for run in runs.get(env, {}).get(obs, []):
                parts.append(details(env, run, docs))
    if notes:
        parts += ["## Findings", "", notes.strip(), ""]
    return "\n".join(parts)


def update_readme(path: Path, runs: dict) -> None:
    text = path.read_text()
    if START not in text or END not in text:
        raise ValueError(f"{path} has no {START} ... {END} markers to put the table between")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    path.write_text(f"{head}{START}\n{table(runs, short=True)}\n{END}{tail}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.report", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", default="docs/baselines", help="folder of the runs' folders")
    parser.add_argument("--out", default="docs/baselines.md", help="the document to write")
    parser.add_argument("--readme", default="README.md", help="README whose table to rewrite ('' for none)")
    args = parser.parse_args(argv)
    runs = load_results(Path(args.results))
    notes = Path(args.results) / "notes.md"
    out = Path(args.out)
    out.write_text(document(runs, out.parent, notes.read_text() if notes.is_file() else ""))
    if args.readme:
        update_readme(Path(args.readme), runs)
    count = sum(len(results) for pair in runs.values() for results in pair.values())
    print(f"wrote {out} ({count} runs)" + (f" and {args.readme}" if args.readme else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
