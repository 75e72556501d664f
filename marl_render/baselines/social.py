"""The social outcomes of the published mixed-motive rows: random, the heuristic and MAPPO on the same worlds.

    python -m marl_render.baselines.social             # the table, as docs/results.md shows it
    python -m marl_render.baselines.social --measure   # kept actors whose result.json predates the metrics

A mixed-motive task's evaluation (``marl_render.envs.evaluation.evaluate``) reports the four social
outcomes of Perolat et al. (2017) beside the return (envs/episodes.py). A run trained since then has
them in its result.json, for its greedy policy and for random and the heuristic on the same
publication worlds. commons' and capture_flag's rows were trained before: ``--measure`` plays each of
their kept actors (docs/baselines/<task>/seed0/actor.pt) again on its run's own evaluation worlds and
options, random and the heuristic beside it, and writes the outcomes to the run's social.json. Runs
whose actor was not kept have no social outcomes, and the table says so.

``report`` (python -m marl_render.baselines.report) writes the table between the markers
``<!-- social:start -->`` and ``<!-- social:end -->`` of docs/results.md.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

from marl_render.envs.evaluation import evaluate, heuristic_policy, random_policy
from marl_render.envs.registry import env_class
from marl_render.populations.policies import load_policy
from marl_render.util.threads import limited_threads

from .published import OBSERVATIONS, ROOT, RUNS, SEEDS, evaluation_kwargs, published_env_options, run_folder

OUTCOMES = ("efficiency", "equality", "sustainability", "peace")
REFERENCES = ("random", "heuristic")
SOCIAL = "social.json"  # in a run's folder, written by --measure
START, END = "<!-- social:start -->", "<!-- social:end -->"


def mixed_motive_tasks() -> list[str]:
    """The published tasks whose evaluations report social outcomes."""
    return sorted(env for env in RUNS if env_class(env).mixed_motive)


def _outcomes(scores: dict) -> dict:
    return {key: scores[f"{key}_mean"] for key in OUTCOMES}


def run_outcomes(folder) -> dict | None:
    """{"policy" | "random" | "heuristic": {outcome: mean over the run's evaluation episodes}} of one run,
    from its result.json, else from the social.json that --measure wrote; None when neither has them."""
    folder = Path(folder)
    path = folder / "result.json"
    if not path.is_file():
        return None
    evaluation = json.loads(path.read_text())["evaluation"]
    if all(f"{key}_mean" in evaluation["policy"] for key in OUTCOMES):
        return {name: _outcomes(evaluation[name]) for name in ("policy", *REFERENCES)}
    measured = folder / SOCIAL
    return json.loads(measured.read_text())["outcomes"] if measured.is_file() else None


def measure(folder) -> dict:
    """The run's kept actor, random and the heuristic on the run's own evaluation worlds and options:
    the dict social.json holds. ValueError for a task that is not mixed-motive or a run without its actor."""
    folder = Path(folder)
    result = json.loads((folder / "result.json").read_text())
    if not env_class(result["env"]).mixed_motive:
        raise ValueError(f"{folder}: {result['env']} is not a mixed-motive task; it has no social outcomes")
    if not (folder / "actor.pt").is_file():
        raise ValueError(f"{folder} kept no actor.pt: its policy cannot be played again")
    policy, kwargs = load_policy(str(folder)), evaluation_kwargs(result)
    with limited_threads(result["hyperparameters"].get("torch_threads", 1) or None):  # as the run evaluated
        scores = {name: evaluate(result["env"], player, **kwargs)
                  for name, player in (("policy", policy), ("random", random_policy),
                                       ("heuristic", heuristic_policy))}
    return {"run": str(folder), "env": result["env"], "seed": kwargs["seed"], "episodes": kwargs["episodes"],
            "env_options": published_env_options(result),
            # The replayed greedy policy's returns against the run's own: the same episodes, or not.
            "reproduces_run": scores["policy"]["per_episode"] == result["evaluation"]["policy"]["per_episode"],
            "return": {name: score["mean"] for name, score in scores.items()},
            "outcomes": {name: _outcomes(score) for name, score in scores.items()}}


def measure_missing(root=ROOT) -> list[Path]:
    """--measure: social.json for every kept actor of a mixed-motive row whose result.json lacks the outcomes."""
    written = []
    for env in mixed_motive_tasks():
        for obs in OBSERVATIONS:
            for seed in SEEDS:
                folder = run_folder(root, env, obs, seed)
                if run_outcomes(folder) is None and (folder / "actor.pt").is_file():
                    measured = measure(folder)
                    (folder / SOCIAL).write_text(json.dumps(measured, indent=1) + "\n")
                    print(f"wrote {folder / SOCIAL} (replays the run's returns: {measured['reproduces_run']})",
                          flush=True)
                    written.append(folder / SOCIAL)
    return written


def cell(values: list[float]) -> str:
    """Mean over seeds, 3 significant digits (whole numbers from 1000 up: peace is in agent-steps)."""
    mean = statistics.fmean(values)
    return f"{mean:.3g}" if abs(mean) < 1000 else f"{mean:.0f}"


def task_rows(env: str, root=ROOT) -> list[tuple]:
    """(policy, seeds, efficiency, equality, sustainability, peace) of random, the heuristic and MAPPO from
    each observation; random's and the heuristic's from the task's first run that has outcomes (every run of
    a task is scored on the same worlds with the same options)."""
    found = {obs: [o for seed in SEEDS if (o := run_outcomes(run_folder(root, env, obs, seed))) is not None]
             for obs in OBSERVATIONS}
    trained = [folder for obs in OBSERVATIONS for seed in SEEDS
               if (folder := run_folder(root, env, obs, seed) / "result.json").is_file()]
    first = next((outcomes[0] for outcomes in found.values() if outcomes), None)
    if first is None:
        missing = "no trained runs yet" if not trained else "no kept actor to replay (python -m " \
                                                            "marl_render.baselines.social --measure)"
        return [(name, "–", *(missing,) * len(OUTCOMES)) for name in (*REFERENCES, "MAPPO")]
    rows = [(name, "–", *(cell([first[name][key]]) for key in OUTCOMES)) for name in REFERENCES]
    for obs in OBSERVATIONS:
        outcomes = found[obs]
        if outcomes:
            rows.append((f"MAPPO from {obs}", str(len(outcomes)),
                         *(cell([o["policy"][key] for o in outcomes]) for key in OUTCOMES)))
        else:
            rows.append((f"MAPPO from {obs}", "0", *("not measured: no actor of its runs was kept",) * len(OUTCOMES)))
    return rows


def table(root=ROOT) -> str:
    lines = ["| task | policy | seeds | " + " | ".join(OUTCOMES) + " |", "|---|---|---:|" + "---:|" * len(OUTCOMES)]
    for env in mixed_motive_tasks():
        lines += [f"| {env} | " + " | ".join(row) + " |" for row in task_rows(env, root)]
    return "\n".join(lines)


def update_page(path, root=ROOT) -> bool:
    """Rewrite the table between the page's social markers; False (nothing written) when it has none."""
    path = Path(path)
    text = path.read_text()
    if START not in text or END not in text:
        return False
    head, rest = text.split(START, 1)
    path.write_text(f"{head}{START}\n{table(root)}\n{END}{rest.split(END, 1)[1]}")
    return True


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.social", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", default=ROOT, help="folder of the runs' folders (default: %(default)s)")
    parser.add_argument("--measure", action="store_true", help="replay the kept actors whose result.json lacks the "
                                                               "social outcomes and write their social.json")
    args = parser.parse_args(argv)
    if not Path(args.results).is_dir():
        parser.error(f"--results must be a folder of runs, got {args.results!r} (no such folder)")
    if args.measure:
        measure_missing(args.results)
    print(table(args.results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
