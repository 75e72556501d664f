"""Baselines a learned policy must beat: the best constant action, and the policy with its view taken away.

    python -m marl_render.baselines.ablate docs/baselines/tag/seed0   # view ablations: RUN/ablation.json
    python -m marl_render.baselines.ablate --constant   # every task: docs/baselines/constant_actions.json
    python -m marl_render.baselines.ablate --constant --tasks matrix   # one task's entry, the others kept
    python -m marl_render.baselines.ablate --final docs/final/tag/seed0   # a final run, on its sealed episodes
    python -m marl_render.baselines.ablate --constant --eval-set final --final --root docs/final

- **The best constant action** (``marl_render.envs.evaluation.best_constant_action``): each action
  held by every evaluated agent for whole episodes, the best one. No learning, so it is computed per
  task on the publication worlds (or the sealed final set's, for the final runs), with the published
  rows' env options.
- **The view ablation** of a saved run from pixels: its final greedy actor scored on the run's own
  evaluation episodes three ways: as trained (``none``: it must give the run's own returns, episode
  for episode), with every view replaced by zeros (``zeros``) and with every world's views replaced by
  those of the next world (``shifted``: world w sees world w-1's pictures, agent by agent). A policy
  that uses its eyes loses return under both. A run trained in the reproducible mode is replayed in it
  (the command line restarts itself pinned, as the learner's does), so that ``none`` can match it.

The sealed final set is scored only with ``--final`` (``evaluate``'s ``final=True``): its constant
actions, and the ablations of the final runs, once, after the runs and before anything is chosen
from them.

The report (report.py) reads both: a row counts as learned only if it beats random and the best
constant action across seeds, and the view ablation costs it return.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import torch

from marl_render.envs.evaluation import best_constant_action, check_evaluation_seed, evaluate, opponent_mask
from marl_render.populations.policies import load_policy
from marl_render.util.threads import limited_threads

from . import reproducible
from .policy import GreedyPolicy
from .published import ROOT, RUNS, evaluation_kwargs
from .settings import EVALUATION_SETS

VIEWS = ("none", "zeros", "shifted")
CONSTANT_ACTIONS = "constant_actions.json"  # under the runs' root
ABLATION = "ablation.json"  # in a run's folder
CONSTANT_RESOLUTION = 8  # the constant actions never look: the smallest views (returns do not depend on them)


def ablate_view(pixels: torch.Tensor, view: str) -> torch.Tensor:
    """Pixels [W, A, ...] as the ablated actor sees them: unchanged ("none"), zeros, or each world's
    views replaced by the previous world's ("shifted", world 0 taking the last's)."""
    if view == "none":
        return pixels
    if view == "zeros":
        return torch.zeros_like(pixels)
    if view == "shifted":
        if pixels.shape[0] < 2:
            raise ValueError(f"the shifted view needs at least 2 worlds (another world's pixels), got "
                             f"{pixels.shape[0]}")
        return pixels.roll(1, 0)
    raise ValueError(f"view must be one of {list(VIEWS)}, got {view!r}")


class AblatedPolicy:
    """A saved actor (as ``evaluate`` takes it) that sees ``ablate_view(obs[obs_key], view)``; the task's
    vector observations it reads (`vector_keys`, e.g. matrix's inventory) it gets unchanged: the ablation
    takes the view away, nothing else. `kind` chooses the actions (GreedyPolicy, or a subclass that draws
    them: tools/greedy_vs_sampled.py); it is built at the first call, when the env shows which agents are
    evaluated. A state run goes through with view "none" only."""

    def __init__(self, actor, frames: int, action_repeat: int, view: str, vector_keys: tuple = (), *,
                 obs_key: str = "pixels", kind: type = GreedyPolicy):
        if view not in VIEWS:
            raise ValueError(f"view must be one of {list(VIEWS)}, got {view!r}")
        if obs_key != "pixels" and view != "none":
            raise ValueError(f"view {view!r} takes pixels away; obs_key {obs_key!r} goes with view 'none' only")
        self.actor, self.frames, self.action_repeat, self.view = actor, frames, action_repeat, view
        self.obs_key, self.kind, self.vector_keys = obs_key, kind, tuple(vector_keys)
        self.needs = frozenset({obs_key, "action_mask", *self.vector_keys})  # the keys as_policy hands it
        self.policy = None

    def __call__(self, env, obs: dict, generator: torch.Generator) -> torch.Tensor:
        if self.policy is None:
            self.policy = self.kind(self.actor, ~opponent_mask(env), self.obs_key, self.frames, self.action_repeat,
                                    self.vector_keys)
        if self.view != "none":
            obs = {**obs, self.obs_key: ablate_view(obs[self.obs_key], self.view)}
        return self.policy(env, obs, generator)


def is_reproducible(result: dict) -> bool:
    """Whether a run (its result.json's dict) trained and evaluated in the reproducible mode."""
    return result.get("mode") == "reproducible"


def view_ablation(run_folder, views=VIEWS, *, final: bool = False) -> dict:
    """The run's final actor scored on its own evaluation episodes with each of `views`:
    {"run", "evaluation_set", "seed", "episodes", "views": {view: evaluate's result},
    "reproduces_run": whether "none" gave the run's returns episode for episode (None without "none")}.
    A run of the reproducible mode is replayed inside it (``reproducible.mode``: ValueError if this
    process did not start pinned). ValueError for a run from the state (it has no view to take away);
    `final` as ``evaluate``'s: a final run's sealed episodes need it."""
    folder = Path(run_folder)
    result = json.loads((folder / "result.json").read_text())
    if result["obs"] != "pixels":
        raise ValueError(f"a view ablation needs a run from pixels; {folder} learned from {result['obs']!r}")
    hp = result["hyperparameters"]
    kwargs = evaluation_kwargs(result)
    check_evaluation_seed(kwargs["seed"], final)  # before the actor loads
    loaded = load_policy(str(folder))
    with reproducible.mode() if is_reproducible(result) else contextlib.nullcontext(), \
            limited_threads(hp.get("torch_threads", 1) or None):  # as the run evaluated (0: torch's own count)
        scores = {view: evaluate(result["env"], AblatedPolicy(loaded.actor, hp.get("frames", 1),
                                                              hp.get("action_repeat", 1), view, loaded.vector_keys),
                                 final=final, **kwargs) for view in views}
    reproduces = scores["none"]["per_episode"] == result["evaluation"]["policy"]["per_episode"] \
        if "none" in scores else None
    return {"run": str(folder), "env": result["env"], "evaluation_set": result.get("evaluation_set", "development"),
            "seed": kwargs["seed"], "episodes": kwargs["episodes"], "views": scores, "reproduces_run": reproduces,
            "cpu": reproducible.cpu()["model"]}


def constant_actions(tasks=None, evaluation_set: str = "publication", *, final: bool = False) -> dict:
    """{task: best_constant_action on `evaluation_set`'s worlds, with the published rows' env options};
    `final` as ``evaluate``'s (the sealed final set needs it)."""
    worlds = EVALUATION_SETS[evaluation_set]
    check_evaluation_seed(worlds["seed"], final)
    out = {}
    for env in tasks or RUNS:
        options = dict(RUNS[env]["pixels"].env_options) if env in RUNS else {}
        out[env] = {"evaluation_set": evaluation_set, "seed": worlds["seed"], "env_options": options,
                    **best_constant_action(env, episodes=worlds["episodes"], seed=worlds["seed"],
                                           resolution=CONSTANT_RESOLUTION, final=final, **options)}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.ablate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", help="run folders from pixels (result.json and actor.pt): writes each "
                                                f"one's {ABLATION}")
    parser.add_argument("--constant", action="store_true",
                        help=f"the best constant action of every published task on --eval-set's worlds: "
                             f"writes ROOT/{CONSTANT_ACTIONS}")
    parser.add_argument("--tasks", nargs="+", choices=sorted(RUNS), metavar="TASK",
                        help="with --constant: only these tasks, the file's other entries kept (default: every task)")
    parser.add_argument("--eval-set", choices=("publication", "final"), default="publication",
                        help="with --constant: the worlds (default: %(default)s)")
    parser.add_argument("--final", action="store_true",
                        help="allow scoring on the sealed final set (--constant --eval-set final, final runs)")
    parser.add_argument("--root", default=ROOT, help="folder of the runs (default: %(default)s)")
    args = parser.parse_args(argv)
    if (args.tasks or args.eval_set != "publication") and not args.constant:
        parser.error("--tasks and --eval-set go with --constant")
    if not args.runs and not args.constant:
        parser.error("give run folders, --constant, or both")
    results = {}
    for run in args.runs:
        if not (Path(run) / "result.json").is_file() or not (Path(run) / "actor.pt").is_file():
            parser.error(f"runs: {run!r} must be a run folder holding result.json and actor.pt")
        results[run] = json.loads((Path(run) / "result.json").read_text())
    sealed = [run for run, result in results.items() if result.get("evaluation_set") == "final"]
    if (bool(sealed) or args.eval_set == "final") != args.final:
        parser.error(f"--final scores the sealed final set and is needed for it: runs scored on it {sealed}, "
                     f"--eval-set {args.eval_set}, --final {args.final}")
    modes = {is_reproducible(result) for result in results.values()}
    if len(modes) > 1:
        parser.error("runs mix the reproducible mode and the default one: ablate each mode's runs in its own call")
    if modes == {True} and reproducible.problems():
        if argv is not None:  # called from Python: torch has chosen its kernels in this process already
            parser.error("runs of the reproducible mode need a process started with its environment ("
                         + "; ".join(reproducible.problems()) + "): run `python -m marl_render.baselines.ablate`, "
                         "which restarts itself with it")
        reproducible.restart("marl_render.baselines.ablate")
    if args.constant:
        found = constant_actions(args.tasks, args.eval_set, final=args.final)
        path = Path(args.root) / CONSTANT_ACTIONS
        merged = {**(json.loads(path.read_text()) if args.tasks and path.is_file() else {}), **found}
        path.write_text(json.dumps({env: merged[env] for env in RUNS if env in merged}, indent=1) + "\n")
        for env, best in found.items():
            print(f"{env}: action {best['action']} holds {best['mean']:.4g} (each: "
                  + ", ".join(f"{m:.4g}" for m in best["per_action"]) + ")", flush=True)
    for run in args.runs:
        found = view_ablation(run, final=run in sealed)
        (Path(run) / ABLATION).write_text(json.dumps(found, indent=1) + "\n")
        print(f"{run}: " + ", ".join(f"{view} {score['mean']:.4g}" for view, score in found["views"].items())
              + ("" if found["reproduces_run"] else " (as trained it did NOT give the run's returns)"), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
