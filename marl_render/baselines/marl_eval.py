"""The reference runs in marl-eval's JSON layout, the one BenchMARL writes, so that BenchMARL and
marl-eval users can put them beside their own runs.

    {"marl_render": {TASK: {"mappo_pixels" | "mappo_state": {"seed_K": {
        "step_I": {"step_count": ENV_STEPS, "return": [...]}, ...,
        "absolute_metrics": {"return": [...]}}}}}}

``marl_render`` is the env name of these tasks in BenchMARL (marl_render.wrappers.benchmarl);
runs are named ``seed_K`` and steps ``step_I`` as BenchMARL's JsonWriter names them. The steps
are the greedy evaluations along training (``checkpoints`` of result.json, development worlds)
before the budget's end; ``absolute_metrics`` holds the final policy's episode returns on the row's
evaluation worlds (BenchMARL puts the best return seen there; these rows never pick a best). A
checkpoint at the budget's end is of the final policy, which ``absolute_metrics`` holds: leaving it
out gives every run the same steps (a checkpoint every tenth of the budget falls on its last update
or just past it, depending on how the budget divides into updates). A run without checkpoints
(before the step budgets) has one step: its final evaluation. A return is the evaluated agents'
summed rewards over an episode, averaged over them.

marl-eval's tools need the same algorithms, runs and number of steps on every task of an env;
``problems`` lists what keeps a file from that.
"""
from __future__ import annotations

from pathlib import Path

from marl_render.util import strict_json

ENVIRONMENT = "marl_render"
ALGORITHMS = {"pixels": "mappo_pixels", "state": "mappo_state"}
METRIC = "return"


def _episodes(evaluation: dict) -> list:
    """The episode returns of an evaluation, or its mean alone where they were not recorded."""
    return [float(x) for x in evaluation.get("per_episode") or [evaluation["mean"]]]


def run_entry(result: dict) -> dict:
    """One run: its checkpoints before the budget's end as steps, its final evaluation as the
    absolute metric."""
    final = result["evaluation"]["policy"]
    points = ([p for p in result.get("checkpoints") or () if p["env_steps"] < result["env_steps"]]
              or [{"env_steps": result["env_steps"], **final}])
    steps = {f"step_{i}": {"step_count": int(p["env_steps"]), METRIC: _episodes(p)} for i, p in enumerate(points)}
    return {**steps, "absolute_metrics": {METRIC: _episodes(final)}}


def layout(runs: dict) -> dict:
    """{env: {obs: [result, ...]}} (report.load_results) in marl-eval's layout."""
    tasks = {}
    for env, by_obs in runs.items():
        algorithms = {ALGORITHMS[obs]: {f"seed_{r['seeds']['train']}": run_entry(r) for r in results}
                      for obs, results in by_obs.items() if results}
        if algorithms:
            tasks[env] = algorithms
    return {ENVIRONMENT: tasks}


def problems(data: dict) -> list[str]:
    """What keeps marl-eval's tools from reading `data`: per env, every task must have the same
    algorithms, and every (task, algorithm) the same run names, each with the same number of steps."""
    found = []
    for env, tasks in data.items():
        if len({tuple(sorted(algorithms)) for algorithms in tasks.values()}) > 1:
            found.append(f"{env}: tasks differ in algorithms (" + "; ".join(
                f"{task}: {', '.join(sorted(algorithms))}" for task, algorithms in tasks.items()) + ")")
        shapes: dict = {}  # (run names, step counts) -> the (task, algorithm) pairs that have them
        for task, algorithms in tasks.items():
            for algorithm, runs in algorithms.items():
                shape = (tuple(sorted(runs)), tuple(sorted({len(steps) - 1 for steps in runs.values()})))
                shapes.setdefault(shape, []).append(f"{task}/{algorithm}")
        if len(shapes) > 1 or any(len(steps) > 1 for _, steps in shapes):
            found.append(f"{env}: runs or steps differ (" + "; ".join(
                f"{', '.join(runs)} with {'/'.join(map(str, steps))} steps: {', '.join(pairs)}"
                for (runs, steps), pairs in shapes.items()) + ")")
    return found


def write(runs: dict, path) -> dict:
    data = layout(runs)
    Path(path).write_text(strict_json.dumps(data, indent=1) + "\n")
    return data
