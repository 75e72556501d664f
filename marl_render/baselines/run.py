"""Train MAPPO on one task from pixels for a fixed wall-clock budget, then evaluate it.

    python -m marl_render.baselines --env spread                       # 15 minutes, 2 CPU cores
    python -m marl_render.baselines --env cartpole --budget-minutes 30
    python -m marl_render.baselines --env spread --obs state           # the same learner on the state

The budget is hard and covers the whole run (env setup, the reference evaluations, training,
the final evaluation): training stops when one more update and the final evaluation would
not fit. The learned greedy policy, the task's uniform random policy and its scripted
heuristic are each evaluated on --episodes episodes (one per world, the same seeds) by
``marl_render.envs.evaluation.evaluate``: an episode's return is the sum of the rewards of the
evaluated agents, averaged over them; opponents (tag's prey, push's and capture_flag's second
team) play random actions in training and in every evaluation.

Env keywords: ``--env-option KEY=VALUE`` goes to the training and every evaluation env (a
task's keyword or an accuracy knob: ``multisamples=4``, ``physics_substeps=4``);
``--train-option KEY=VALUE`` to the training env only (a shaped reward such as push's
``shaping=1``: the evaluations keep the task's own reward, so the table compares like with like).
VALUE is a Python literal (``1``, ``0.5``, ``True``, ``'x'``).

Writes OUT/result.json (env, seeds, versions, env steps, wall-clock, hyperparameters, the
training curve, the evaluations), OUT/curve.png and OUT/actor.pt (the actor's state_dict).
Options left out take the task's default (marl_render/baselines/settings.py).
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import os
import platform
import shlex
import sys
import time

import torch

from marl_render.envs import list_envs
from marl_render.envs.evaluation import evaluate, heuristic_policy, random_policy

from .curve import plot_curve
from .policy import GreedyPolicy
from .ppo import MAPPO
from .settings import FIELDS, task_hyperparameters

PROGRESS_SECONDS = 10.0  # at most one progress line per this many seconds


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines", description=__doc__,
                                     formatter_class=HelpFormatter)
    parser.add_argument("--env", required=True, choices=list_envs(), help="the task")
    parser.add_argument("--obs", choices=("pixels", "state"), default="pixels", help="what the actor sees")
    parser.add_argument("--out", default=None, help="folder for result.json and curve.png "
                                                    "(default: out/baselines/ENV, or ENV-state with --obs state)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the training env and the networks")
    parser.add_argument("--eval-seed", type=int, default=1000, help="seed of the evaluation episodes")
    parser.add_argument("--episodes", type=int, default=32, help="evaluation episodes per policy")
    parser.add_argument("--budget-minutes", type=float, default=15.0, help="wall-clock budget of the whole run")
    parser.add_argument("--env-option", action="append", default=[], metavar="KEY=VALUE", type=env_option,
                        help="env keyword for training and evaluation (repeatable)")
    parser.add_argument("--train-option", action="append", default=[], metavar="KEY=VALUE", type=env_option,
                        help="env keyword for the training env only, e.g. a shaped reward (repeatable)")
    hp = parser.add_argument_group("hyperparameters (default: the task's, see settings.py)")
    for name, kind in (("worlds", int), ("resolution", int), ("frames", int), ("action-repeat", int),
                       ("rollout", int), ("epochs", int), ("minibatches", int), ("lr", float), ("gamma", float),
                       ("gae-lambda", float), ("clip", float), ("entropy", float), ("critic-coef", float),
                       ("max-grad-norm", float), ("hidden", int),
                       ("torch-threads", int), ("aux-state", float)):
        hp.add_argument(f"--{name}", type=kind, default=None)
    hp.add_argument("--grayscale", action="store_true", default=None, help="one-channel pixels")
    args = parser.parse_args(argv)
    for name in ("episodes", "worlds", "resolution", "frames", "action_repeat", "rollout", "epochs", "minibatches"):
        value = getattr(args, name)
        if value is not None and value < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    if args.budget_minutes <= 0:
        parser.error(f"--budget-minutes must be > 0, got {args.budget_minutes}")
    reserved = {"num_worlds", "resolution", "grayscale", "state_obs", "seed"}  # set from the hyperparameters
    for key, _ in args.env_option + args.train_option:
        if key in reserved:
            parser.error(f"--env-option / --train-option {key}: set it with the learner's own option instead")
    if args.out is None:
        args.out = os.path.join("out", "baselines", args.env if args.obs == "pixels" else f"{args.env}-state")
    return args


def env_option(text: str) -> tuple:
    """KEY=VALUE -> (KEY, the Python literal VALUE)."""
    key, sep, value = text.partition("=")
    if not sep or not key.isidentifier():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE (e.g. shaping=1.0), got {text!r}")
    try:
        return key, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        raise argparse.ArgumentTypeError(f"VALUE of {key} must be a Python literal (1, 0.5, True, 'x'), "
                                         f"got {value!r}") from None


def versions() -> dict:
    import tensordict
    import torchrl

    import marl_render
    return {"marl_render": getattr(marl_render, "__version__", "unknown"), "torch": torch.__version__,
            "torchrl": torchrl.__version__, "tensordict": tensordict.__version__,
            "python": platform.python_version()}


def main(argv=None) -> int:
    started = time.perf_counter()
    args = parse_args(argv)
    deadline = started + args.budget_minutes * 60
    hp = task_hyperparameters(args.env, **{name: getattr(args, name) for name in FIELDS})
    torch.set_num_threads(hp.torch_threads)
    load_start = os.getloadavg()[0]
    print(f"{args.env}: MAPPO from {args.obs}, budget {args.budget_minutes:g} min, {hp}", flush=True)

    env_options, train_options = dict(args.env_option), dict(args.train_option)
    trainer = MAPPO(args.env, hp, args.obs, args.seed, {**env_options, **train_options})
    eval_kwargs = dict(episodes=args.episodes, seed=args.eval_seed, resolution=hp.resolution,
                       grayscale=hp.grayscale, state_obs=args.obs == "state", **env_options)
    before = time.perf_counter()
    references = {name: evaluate(args.env, policy, **eval_kwargs)
                  for name, policy in (("random", random_policy), ("heuristic", heuristic_policy))}
    # The greedy policy's evaluation also runs the actor: count it as 1.5 reference evaluations.
    eval_estimate = 0.75 * (time.perf_counter() - before) + 1.0
    print(f"random {references['random']['mean']:.4g} ± {references['random']['std']:.2g}, heuristic "
          f"{references['heuristic']['mean']:.4g} ± {references['heuristic']['std']:.2g} "
          f"({args.episodes} episodes)", flush=True)

    train_start = time.perf_counter()
    curve, updates, printed = [], 0, 0.0
    while True:
        update_start = time.perf_counter()
        samples, ended = trainer.collect()
        terms = trainer.update(samples)
        updates += 1
        now = time.perf_counter()
        point = {"env_steps": trainer.env_steps, "seconds": now - train_start,
                 "episode_return": sum(ended) / len(ended) if ended else None, "episodes_ended": len(ended),
                 **terms}
        curve.append(point)
        if now - printed >= PROGRESS_SECONDS:
            printed = now
            shown = [p["episode_return"] for p in curve if p["episode_return"] is not None]
            last = f"{shown[-1]:.4g}" if shown else "- (no episode ended yet)"
            print(f"[{now - started:6.0f} s] update {updates}, {trainer.env_steps:,} env steps "
                  f"({trainer.env_steps / (now - train_start):,.0f}/s), episode return {last}, "
                  f"entropy {terms['entropy']:.3f}", flush=True)
        if now + (now - update_start) + eval_estimate > deadline:
            break
    training_seconds = time.perf_counter() - train_start
    trainer.close()

    eval_start = time.perf_counter()
    policy = evaluate(args.env, GreedyPolicy(trainer.actor_net, trainer.trained, args.obs, hp.frames,
                                             hp.action_repeat), **eval_kwargs)
    evaluation_seconds = time.perf_counter() - eval_start
    print(f"learned greedy policy {policy['mean']:.4g} ± {policy['std']:.2g} (random "
          f"{references['random']['mean']:.4g}, heuristic {references['heuristic']['mean']:.4g})", flush=True)

    result = {
        "env": args.env, "obs": args.obs,
        "algorithm": "MAPPO (TorchRL ClipPPOLoss + GAE): shared actor on each agent's own observation, "
                     "centralised critic on all agents' state observations",
        "command": "python -m marl_render.baselines " + shlex.join(sys.argv[1:] if argv is None else argv),
        "seeds": {"train": args.seed, "evaluation": args.eval_seed},
        "versions": versions(),
        "machine": {"cpu_count": os.cpu_count(), "load_average_1min_start": load_start,
                    "load_average_1min_end": os.getloadavg()[0], "platform": platform.platform()},
        "budget_minutes": args.budget_minutes,
        "wall_clock_seconds": time.perf_counter() - started,
        "training_seconds": training_seconds, "env_seconds_in_training": trainer.seconds_stepping,
        "stage_seconds": trainer.clock.seconds,
        "evaluation_seconds": evaluation_seconds,
        "env_steps": trainer.env_steps, "updates": updates,
        "hyperparameters": dataclasses.asdict(hp),
        "env_options": env_options, "train_options": train_options,
        "trained_agents": [n for n, t in zip(trainer.env.agent_names, trainer.trained.tolist(), strict=True) if t],
        "evaluation": {"policy": policy, **references,
                       "return": "sum of the evaluated agents' rewards over an episode, averaged over them; "
                                 "mean and std over episodes"},
        "curve": curve,
    }
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "result.json"), "w") as f:
        json.dump(result, f, indent=1)
    plot_curve(result, os.path.join(args.out, "curve.png"))
    torch.save(trainer.actor_net.state_dict(), os.path.join(args.out, "actor.pt"))
    print(f"wrote {args.out}/result.json, curve.png and actor.pt in {result['wall_clock_seconds']:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
