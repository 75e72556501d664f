"""The published reference runs, as data: one entry per task and observation.

    python -m marl_render.baselines.published               # every published command, one a line
    python -m marl_render.baselines.published --run         # runs them one at a time (hours), then the report
    make baselines                                          # the same as --run

Every row of docs/baselines.md is ``SEEDS`` training seeds of one entry, each stopped by the
entry's budget in env steps (summed over worlds) and scored on the ``publication`` evaluation
worlds. Those worlds are a second development set, not a sealed one: the budgets, the default init and
which rows keep ``--init torch`` were chosen after scores on them were in (docs/baselines/notes.md). Run k writes
docs/baselines/<task>[-state]/seed<k>/. An entry holds the step budget, the env options (training
and evaluation), the training-only options (a shaped reward; the evaluations keep the task's own
reward) and the hyperparameters that differ from the task's defaults (settings.py).

``--run`` keeps a run whose result.json exists, so an interrupted batch resumes; delete a run's
folder to redo it.

The step budgets are the learner's own (``settings.STEP_BUDGETS``, what ``python -m
marl_render.baselines`` trains for when no budget is given): one table, so a published command
and a plain run of the task train alike. docs/training.md says how they were chosen.
"""
from __future__ import annotations

import argparse
import dataclasses
import shlex
import subprocess
import sys
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import MappingProxyType

from marl_render.envs import list_envs
from marl_render.envs.options import EnvOptions

from .settings import step_budget

SEEDS = (0, 1, 2)
EVALUATION_SET = "publication"  # its env seed and number of episodes are the learner's (run.py)
OBSERVATIONS = ("pixels", "state")
# The learner's options that stop a run and choose its evaluation worlds (run.py owns the names).
BUDGET_FLAG = "--env-steps"
EVALUATION_SET_FLAG = "--eval-set"
ROOT = "docs/baselines"


@dataclasses.dataclass(frozen=True)
class Published:
    """One published row's settings (read-only)."""
    env_steps: int
    env_options: Mapping = dataclasses.field(default_factory=dict)
    train_options: Mapping = dataclasses.field(default_factory=dict)
    hyperparameters: Mapping = dataclasses.field(default_factory=dict)  # the overrides of the task's defaults

    def __post_init__(self):
        if isinstance(self.env_steps, bool) or not isinstance(self.env_steps, int) or self.env_steps < 1:
            raise ValueError(f"env_steps must be an int >= 1, got {self.env_steps!r}")
        for name in ("env_options", "train_options", "hyperparameters"):
            object.__setattr__(self, name, MappingProxyType(dict(getattr(self, name))))


def _entry(env: str, *, state_resolution: int = 8, torch_init: tuple[str, ...] = (), **options) -> dict:
    """A task's pixels and state entries: the same options, the learner's step budgets
    (settings.STEP_BUDGETS); the state run renders tiny views (its actor never sees them).
    `torch_init` names the observations whose row was trained with torch's default initial weights
    (``--init torch``, the learner's default before issue 25's orthogonal one): every seed of a row
    shares its seed 0's init, so that the row's seeds differ in the seed alone."""
    def hyperparameters(obs: str, **overrides) -> dict:
        return {**overrides, **({"init": "torch"} if obs in torch_init else {})}
    return {"pixels": Published(step_budget(env, "pixels"), **options, hyperparameters=hyperparameters("pixels")),
            "state": Published(step_budget(env, "state"), **options,
                               hyperparameters=hyperparameters("state", resolution=state_resolution))}


# Registered tasks whose runs are listed in RUNS (budgets chosen, commands ready: `--run` trains them) but not
# trained and committed yet: the report shows them as "pending" rows. A task leaves this tuple when its runs
# are committed.
PENDING: tuple = ()
PENDING_CELL = "pending: no trained runs yet"

# commons' and capture_flag's rows were trained before mixed-motive tasks ended at random (issue 41): their
# commands keep the fixed end they were trained and scored with (episode_end=False), so that a rerun is that run.
# commons', forage's and push's rows were trained before spheres were drawn as impostors by default (issue 42):
# their commands keep the sphere meshes they saw (impostors=False); the actors' greedy actions follow the pixels.
RUNS: dict[str, dict[str, Published]] = {
    "capture_flag": _entry("capture_flag", env_options={"num_agents": 4, "episode_end": False},
                           train_options={"shaping": 0.5},
                           torch_init=("pixels",)),
    "cartpole": _entry("cartpole", state_resolution=16),
    # Issue 41's tasks: their classes' budgets (Scenario.training), at their task defaults (random episode ends,
    # spheres as impostors).
    "clean_up": _entry("clean_up"),
    "commons": _entry("commons", env_options={"episode_end": False, "impostors": False},
                      torch_init=("pixels", "state")),
    "cooking": _entry("cooking"),
    "coop_mining": _entry("coop_mining"),
    "forage": _entry("forage", env_options={"impostors": False}),
    "matrix": _entry("matrix"),
    "push": _entry("push", env_options={"impostors": False}, train_options={"shaping": 1.0}, torch_init=("pixels",)),
    "rooms": _entry("rooms", train_options={"explore_reward": 0.1}),
    "speaker_listener": _entry("speaker_listener"),
    "spread": _entry("spread"),
    "tag": _entry("tag", train_options={"shaping": 0.05}, torch_init=("state",)),
    "territory": _entry("territory"),
}


# Env options whose default changed after published runs were trained: random episode ends for the mixed-motive
# tasks and sphere impostors (issues 41 and 42). A run records the defaults it left these at (run.py's
# result.json "env_defaults"); a run from before has no such record, and its published entry pins what it used.
CHANGED_DEFAULTS = ("episode_end", "impostors")


def left_at_default(env_options: Mapping) -> dict:
    """{option: its default} of the CHANGED_DEFAULTS a run's `env_options` do not set: what result.json records,
    so that a replay passes them and not whatever the defaults are then."""
    defaults = {field.name: field.default for field in dataclasses.fields(EnvOptions)}
    return {name: defaults[name] for name in CHANGED_DEFAULTS if name not in env_options}


def published_env_options(run: dict) -> dict:
    """The env options that a rerun or a replay of `run` (a result.json's dict) must pass: its recorded ones over
    the defaults it recorded, or, for a run from before that record, over its published entry's pins."""
    if "env_defaults" in run:
        return {**run["env_defaults"], **run.get("env_options", {})}
    entry = RUNS.get(run["env"], {}).get(run["obs"])
    return {**(entry.env_options if entry else {}), **run.get("env_options", {})}


def evaluation_kwargs(run: dict) -> dict:
    """The keywords of ``evaluate`` that `run`'s (a result.json's dict) final evaluation was scored with (run.py's
    own, options pinned as published_env_options says): a replay of its actor on them gives the run's returns."""
    hp = run["hyperparameters"]
    levels = run.get("evaluation_levels")
    return {"episodes": run["evaluation"]["policy"]["episodes"], "seed": run["seeds"]["evaluation"],
            "resolution": hp["resolution"], "grayscale": hp.get("grayscale", False), "state_obs": run["obs"] == "state",
            **published_env_options(run), **({} if levels is None else {"levels": levels})}


def folder(env: str, obs: str) -> str:
    """The folder of a task's runs from one observation, under docs/baselines/."""
    return env if obs == "pixels" else f"{env}-state"


def run_folder(root, env: str, obs: str, seed: int) -> Path:
    return Path(root) / folder(env, obs) / f"seed{seed}"


def _value(value) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def learner_argv(env: str, obs: str, seed: int, *, budget: list[str], evaluation: list[str],
                 hyperparameters: Mapping, env_options: Mapping, train_options: Mapping, out) -> list[str]:
    """The arguments of ``python -m marl_render.baselines`` for one run. `budget` and `evaluation`
    are the options that stop the run and choose its evaluation episodes."""
    argv = ["--env", env] + (["--obs", obs] if obs != "pixels" else []) + ["--seed", str(seed), *budget, *evaluation]
    for name, value in hyperparameters.items():
        flag = name.replace("_", "-")
        # A switch is written either way: its default is the task's, so a False left out could read as True.
        argv += [f"--{flag}" if value else f"--no-{flag}"] if isinstance(value, bool) else [f"--{flag}", _value(value)]
    for kind, options in (("env", env_options), ("train", train_options)):
        for key, value in options.items():
            argv += [f"--{kind}-option", f"{key}={value!r}"]
    return argv + ["--out", str(out)]


def run_argv(env: str, obs: str, seed: int, root=ROOT) -> list[str]:
    """The arguments of the published run of `env` from `obs` with training seed `seed`."""
    entry = RUNS[env][obs]
    return learner_argv(env, obs, seed, budget=[BUDGET_FLAG, str(entry.env_steps)],
                        evaluation=[EVALUATION_SET_FLAG, EVALUATION_SET],
                        hyperparameters=entry.hyperparameters, env_options=entry.env_options,
                        train_options=entry.train_options, out=run_folder(root, env, obs, seed))


def commands(root=ROOT) -> list[str]:
    """Every published command, task by task, pixels then state, seed by seed."""
    return ["python -m marl_render.baselines " + shlex.join(run_argv(env, obs, seed, root))
            for env in RUNS for obs in OBSERVATIONS for seed in SEEDS]


def published_tasks() -> list[str]:
    """The registered tasks that have published runs: every one but the PENDING ones."""
    return [env for env in list_envs() if env not in PENDING]


def check_complete() -> None:
    """Every registered task has a pixels and a state entry, nothing else is listed, and every PENDING
    task is registered."""
    missing = [f"{env}/{obs}" for env in list_envs() for obs in OBSERVATIONS if obs not in RUNS.get(env, {})]
    unknown = sorted(set(RUNS) - set(list_envs()))
    if missing or unknown:
        raise ValueError(f"published.RUNS must list every task from pixels and state: missing {missing}, "
                         f"unknown tasks {unknown}")
    stale = sorted(set(PENDING) - set(list_envs()))
    if stale:
        raise ValueError(f"published.PENDING must name registered tasks, got {stale}")


def run_quietly(command: list[str]) -> int:
    """Run one training, its output in its folder's train.log (runs at a time would interleave theirs)."""
    out = Path(command[command.index("--out") + 1])
    out.mkdir(parents=True, exist_ok=True)
    say(f"started {out}")
    with open(out / "train.log", "w") as log:
        code = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT).returncode
    say(f"{'finished' if code == 0 else f'FAILED ({code})'} {out}")
    return code


def say(line: str) -> None:
    """One line in one write: print() writes the text and its newline apart, so two runs' threads
    interleaved their lines ("started Astarted B")."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.published", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="store_true", help="run every command whose result.json is missing, "
                                                           "then write the report")
    parser.add_argument("--root", default=ROOT, help="folder of the runs (default: %(default)s)")
    parser.add_argument("--jobs", type=int, default=1, help="runs at a time with --run (default: 1; each run "
                                                            "uses one torch thread, so up to the cores)")
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")
    check_complete()
    if not args.run:
        print("\n".join(commands(args.root)))
        return 0
    pending = []
    for seed in SEEDS:  # seed by seed, so that a batch cut short leaves whole seeds of every task
        for obs in OBSERVATIONS:
            for env in RUNS:
                if (run_folder(args.root, env, obs, seed) / "result.json").is_file():
                    print(f"kept {run_folder(args.root, env, obs, seed)}", flush=True)
                else:
                    pending.append([sys.executable, "-m", "marl_render.baselines",
                                    *run_argv(env, obs, seed, args.root)])
    with ThreadPoolExecutor(args.jobs) as pool:  # threads only wait on the runs' processes
        failed = [" ".join(c[2:]) for c, code in zip(pending, pool.map(run_quietly, pending), strict=True) if code != 0]
    if failed:
        print("failed (rerun --run to retry them):\n  " + "\n  ".join(failed), file=sys.stderr)
        return 1
    return subprocess.run([sys.executable, "-m", "marl_render.baselines.report", "--results", args.root],
                          check=False).returncode


if __name__ == "__main__":
    sys.exit(main())
