"""Train MAPPO on one task for a budget of env steps, then evaluate the final policy.

    python -m marl_render.baselines --env spread                          # the task's step budget
    python -m marl_render.baselines --env spread --env-steps 300000 --eval-set publication
    python -m marl_render.baselines --env spread --obs state              # the same learner on the state
    python -m marl_render.baselines --env forage --seeds 0 1 2 --tensorboard runs/forage   # three seeds, logged

Training stops on its budget: --env-steps (summed over worlds, rounded up to whole updates) or
--updates; without either, the task's budget (settings.STEP_BUDGETS). The wall-clock is recorded,
never used to stop, so the same command gives the same numbers (timings apart) on machines with
the same software and the same CPU model (another instruction set rounds the learner differently).
--max-minutes is an opt-in safety cap on training: a run it stops is marked
"truncated": true in result.json.

The final greedy policy, the task's uniform random policy and its scripted heuristic are each
evaluated on one evaluation set (--eval-set): "development" (env seed 1000, 32 episodes: every
development choice so far was scored on it) or "publication" (env seed 7000000, 64 episodes, kept
for the published rows). ``marl_render.envs.evaluation.evaluate`` plays one episode per world; an
episode's return is the sum of the rewards of the evaluated agents, averaged over them; opponents
(tag's prey, push's and capture_flag's second team) play random actions in training and in every
evaluation. Every --checkpoint-every env steps the greedy policy is also evaluated on
--checkpoint-episodes episodes of the development set: result.json's "checkpoints" show how
stable it is. The row's number is always the final policy's, never the best checkpoint's.

Env keywords: ``--env-option KEY=VALUE`` goes to the training and every evaluation env (a
task's keyword or an accuracy knob: ``multisamples=4``, ``physics_substeps=4``);
``--train-option KEY=VALUE`` to the training env only (a shaped reward such as push's
``shaping=1``: the evaluations keep the task's own reward, so the table compares like with like).
VALUE is a Python literal (``1``, ``0.5``, ``True``, ``'x'``).

Levels and looks (docs/levels.md, docs/generalisation.md): ``--levels N`` (or ``train``) trains on
those levels (the test levels, ``test`` and ``published``, are refused: they are for evaluation);
``--eval-levels`` sets the levels of the evaluations (default: none, the env's default resets;
``published`` for the frozen test levels);
``--appearance train`` (or ``heldout``) draws every world's look from its level (training and
evaluation). ``python -m marl_render.baselines.generalisation`` runs the train/test study.

Writes OUT/actor.pt (the actor's state_dict), then OUT/result.json (env, seeds, evaluation set,
budget, versions, env steps, wall-clock and its stages, hyperparameters, the training curve, the
checkpoints, the evaluations with every episode's return), each atomically, and last OUT/curve.png.
Options left out take the task's default (marl_render/baselines/settings.py).

Self-play (--self-play, for a task of two or more teams; selfplay.py): every team is trained against
a pool of frozen snapshots of the actor, one taken every --snapshot-every env steps; each world faces
the latest snapshot with chance --play-latest, else one of the last --window, drawn anew (with the
team it trains) every --swap-every env steps at its next reset. result.json's "self_play" records
every snapshot (env steps when taken, episodes and env steps it was faced) and OUT/snapshots/NNN/
holds each one as a run folder (actor.pt, result.json) that marl_render.policies.load_policy reads.
A run into a folder that holds an earlier run replaces it, snapshots included (those of the earlier
run are removed when the new run's files are written; until then it is left whole).

``--seeds 0 1 2`` trains one run per seed into OUT/seedS (the same command with ``--seed S --out
OUT/seedS`` reproduces each), then prints the across-seed summary (the final policy's return per
seed, their mean with a 95% bootstrap interval over seeds, and the normalised score: random 0,
heuristic 1) and writes it to OUT/seeds.json. ``--tensorboard DIR`` logs every update's curve point
(episode return, entropy, losses), the checkpoints and the final evaluations for TensorBoard, at
the env steps learned from (DIR/seedS with --seeds; needs ``pip install 'marl-render[tensorboard]'``).

A task registered by the user: --import MODULE (a module that calls register_env), or --env
module:Class (a Scenario subclass, registered under that name).
"""
from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import math
import os
import platform
import shlex
import sys
import tempfile
import time

import torch

from marl_render.envs import list_envs, make_env
from marl_render.envs.evaluation import SEALED_SEEDS, evaluate, heuristic_policy, random_policy
from marl_render.envs.levels import levels_option
from marl_render.envs.task_imports import add_import_option, load_user_tasks
from marl_render.populations.networks import ENCODERS, INITS, PRECISIONS
from marl_render.util import strict_json
from marl_render.util.extras import command_needs_extra
from marl_render.util.threads import MAX_THREADS

from . import reproducible
from .curve import plot_curve
from .published import left_at_default
from .records import (
    arithmetic,
    clear_snapshots,
    print_seeds_summary,
    save_snapshots,
    seed_command,
    seeds_summary,
    versions,
    write_atomically,
)
from .selfplay import PLAY_LATEST, SNAPSHOT_EVERY, SWAP_EVERY, WINDOW, SelfPlay, setting_problem, team_index
from .settings import EVALUATION_SETS, FIELDS, step_budget, task_hyperparameters
from .training import train

PROGRESS_SECONDS = 10.0  # at most one progress line per this many seconds
CHECKPOINTS = 10  # default checkpoint evaluations over a run: one every budget / CHECKPOINTS env steps
# Env options the learner sets itself, or that its bootstrapping and action sampling do not support.
RESERVED_OPTIONS = {"num_worlds": "--worlds", "resolution": "--resolution", "grayscale": "--grayscale",
                    "state_obs": "--obs", "seed": "--seed", "levels": "--levels / --eval-levels",
                    "appearance": "--appearance"}
REFUSED_OPTIONS = {"autoreset": "the learner resets ended worlds itself (it needs autoreset=False to bootstrap "
                                "truncated episodes from their last state)",
                   "continuous": "the learner samples discrete actions"}
# (option, kind, lowest, highest, lowest allowed itself): the hyperparameters' ranges. --torch-threads' highest is
# the envs' torch_threads bound (marl_render/threads.py): fixed, not this machine's cores, so that a published
# command line runs on every machine; beyond it torch would start idle OpenMP threads by the thousand.
RANGES = (("worlds", int, 1, None, True), ("resolution", int, 1, None, True), ("frames", int, 1, None, True),
          ("action-repeat", int, 1, None, True), ("rollout", int, 1, None, True), ("epochs", int, 1, None, True),
          ("minibatches", int, 1, None, True), ("lr", float, 0.0, None, False), ("gamma", float, 0.0, 1.0, False),
          ("gae-lambda", float, 0.0, 1.0, True), ("clip", float, 0.0, None, False),
          ("entropy", float, 0.0, None, True), ("critic-coef", float, 0.0, None, False),
          ("max-grad-norm", float, 0.0, None, False), ("hidden", int, 1, None, True),
          ("torch-threads", int, 0, MAX_THREADS, True), ("aux-state", float, 0.0, None, True))


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def parse_args(argv=None) -> argparse.Namespace:
    """The command line, every value checked before any work starts."""
    prog = "python -m marl_render.baselines"
    load_user_tasks(argv, prog)  # before the parser lists the tasks
    parser = argparse.ArgumentParser(prog=prog, description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--env", required=True, choices=list_envs(),
                        help="the task (a user's: with --import MODULE, or as module:Class)")
    add_import_option(parser)
    parser.add_argument("--obs", choices=("pixels", "state"), default="pixels", help="what the actor sees")
    parser.add_argument("--out", default=None, help="folder for result.json, actor.pt and curve.png "
                                                    "(default: out/baselines/ENV, or ENV-state with --obs state)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the training env and the networks (default 0)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, metavar="SEED",
                        help="one run per seed, into OUT/seedS, then the across-seed summary (instead of --seed)")
    parser.add_argument("--tensorboard", default=None, metavar="DIR",
                        help="log the training curve, checkpoints and evaluations to DIR for TensorBoard")
    budget = parser.add_mutually_exclusive_group()
    budget.add_argument("--env-steps", type=int, default=None,
                        help="budget in env steps summed over worlds (default: the task's, settings.STEP_BUDGETS)")
    budget.add_argument("--updates", type=int, default=None, help="budget in updates (instead of --env-steps)")
    parser.add_argument("--max-minutes", "--budget-minutes", dest="max_minutes", type=float, default=None,
                        help="opt-in safety cap on the training wall-clock; a run it stops is marked truncated")
    parser.add_argument("--eval-set", choices=list(EVALUATION_SETS), default="development",
                        help="evaluation episodes of the final policy and the references: " + "; ".join(
                            f"{k}: env seed {v['seed']}, {v['episodes']} episodes" for k, v in EVALUATION_SETS.items()))
    parser.add_argument("--final", action="store_true",
                        help="allow scoring the sealed final set (--eval-set final): once, by the final runs")
    parser.add_argument("--eval-seed", type=int, default=None, help="env seed of the evaluation (default: the set's)")
    parser.add_argument("--episodes", type=int, default=None, help="evaluation episodes (default: the set's)")
    parser.add_argument("--checkpoint-every", type=int, default=None,
                        help=f"env steps between checkpoint evaluations (default: the budget / {CHECKPOINTS}; 0: none)")
    parser.add_argument("--checkpoint-episodes", type=int, default=8, help="development episodes per checkpoint")
    parser.add_argument("--env-option", action="append", default=[], metavar="KEY=VALUE", type=env_option,
                        help="env keyword for training and evaluation (repeatable)")
    parser.add_argument("--train-option", action="append", default=[], metavar="KEY=VALUE", type=env_option,
                        help="env keyword for the training env only, e.g. a shaped reward (repeatable)")
    parser.add_argument("--levels", type=levels_option, default=None,
                        help="levels of the training env: a count n (levels 0..n-1) or train (test and published "
                             "are for --eval-levels only)")
    parser.add_argument("--eval-levels", type=levels_option, default=None,
                        help="levels of the evaluations (default: none, the default resets)")
    parser.add_argument("--appearance", choices=("train", "heldout"), default=None,
                        help="per-level looks in training and evaluation (default: off)")
    hp = parser.add_argument_group("hyperparameters (default: the task's, see settings.py)")
    for name, kind, *_ in RANGES:
        hp.add_argument(f"--{name}", type=kind, default=None)
    hp.add_argument("--grayscale", action=argparse.BooleanOptionalAction, default=None, help="one-channel pixels")
    hp.add_argument("--overlap", action=argparse.BooleanOptionalAction, default=None,
                    help="collect the next rollout while the update runs (one update behind)")
    hp.add_argument("--encoder", choices=list(ENCODERS), default=None, help="the actor's pixel encoder")
    hp.add_argument("--init", choices=list(INITS), default=None,
                    help="the actor's initial weights (torch: torch's default, as before issue 25's fix)")
    hp.add_argument("--precision", choices=list(PRECISIONS), default=None,
                    help="the actor's compute (bfloat16: CPU autocast, float32 weights)")
    parser.add_argument("--reproducible", action=argparse.BooleanOptionalAction, default=False,
                        help="train and evaluate in the reproducible mode (reproducible.py): float32, one torch "
                             "thread, kernels pinned; the same bits on machines of one CPU model, not across "
                             "models (docs/training.md); the command restarts itself with the mode's environment")
    sp = parser.add_argument_group("self-play (a task of two or more teams; see selfplay.py for the defaults' why)")
    sp.add_argument("--self-play", action="store_true",
                    help="train every team against a pool of frozen snapshots of the actor")
    for name, kind, default, what in SELF_PLAY_OPTIONS:
        sp.add_argument(f"--{name}", type=kind, default=None, help=f"{what} (default {default})")
    args = parser.parse_args(argv)
    check_args(parser, args)
    return args


# (option, type, default, help) of the self-play pool; each is a field of SelfPlay.
SELF_PLAY_OPTIONS = (("snapshot-every", int, SNAPSHOT_EVERY, "env steps between snapshots of the learner"),
                     ("window", int, WINDOW, "the last N snapshots are in play"),
                     ("play-latest", float, PLAY_LATEST, "chance that a world faces the latest snapshot"),
                     ("swap-every", int, SWAP_EVERY, "env steps between draws of each world's opponent"))


def self_play_settings(args: argparse.Namespace) -> SelfPlay | None:
    """The SelfPlay of --self-play and its options (None without --self-play)."""
    if not args.self_play:
        return None
    given = {name.replace("-", "_"): getattr(args, name.replace("-", "_")) for name, *_ in SELF_PLAY_OPTIONS}
    return SelfPlay(**{k: v for k, v in given.items() if v is not None})


def check_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """parser.error (exit 2, one line naming the option, the expected and the given) for any value
    out of range, and an output folder that could not take the run's files."""
    for name, _, low, high, closed in RANGES:
        value = getattr(args, name.replace("-", "_"))
        if value is None:
            continue
        expected = (f">= {low}" if closed else f"> {low}") + (f" and <= {high}" if high is not None else "")
        inside = value > low or (value == low and closed)
        if not (math.isfinite(value) and inside and (high is None or value <= high)):
            parser.error(f"--{name} must be {expected}, got {value}")
    for name in ("env_steps", "updates", "episodes", "checkpoint_episodes"):
        value = getattr(args, name)
        if value is not None and value < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    if args.reproducible:
        if args.precision not in (None, reproducible.PRECISION):
            parser.error(f"--precision must be {reproducible.PRECISION} with --reproducible (bfloat16 kernels "
                         f"depend on the CPU), got {args.precision}")
        if args.torch_threads not in (None, reproducible.THREADS):
            parser.error(f"--torch-threads must be {reproducible.THREADS} with --reproducible (reductions split "
                         f"over threads sum in another order), got {args.torch_threads}")
        args.precision = reproducible.PRECISION
    hp = task_hyperparameters(args.env, **{name: getattr(args, name) for name in FIELDS})
    problem = reproducible.settings_problem(hp.precision, hp.torch_threads) if args.reproducible else None
    if problem:  # a task's own defaults
        parser.error(f"--reproducible: the task's {problem}")
    if args.obs == "pixels" and hp.resolution < ENCODERS[hp.encoder]:
        parser.error(f"--resolution must be >= {ENCODERS[hp.encoder]} for the {hp.encoder!r} encoder, got "
                     f"{hp.resolution} (--encoder conv takes {ENCODERS['conv']})")
    eval_seed = EVALUATION_SETS[args.eval_set]["seed"] if args.eval_seed is None else args.eval_seed
    if eval_seed in SEALED_SEEDS and not args.final:
        parser.error(f"--eval-set {SEALED_SEEDS[eval_seed]} is sealed: it is scored once, by the final runs, with "
                     f"--final; got no --final")
    if args.final and eval_seed not in SEALED_SEEDS:
        parser.error(f"--final applies to the sealed set (--eval-set final), got evaluation seed {eval_seed}")
    if args.checkpoint_every is not None and args.checkpoint_every < 0:
        parser.error(f"--checkpoint-every must be >= 0 (0: no checkpoints), got {args.checkpoint_every}")
    if args.max_minutes is not None and not (math.isfinite(args.max_minutes) and args.max_minutes > 0):
        parser.error(f"--max-minutes must be a finite number > 0, got {args.max_minutes}")
    for key, _ in args.env_option + args.train_option:
        if key in RESERVED_OPTIONS:
            parser.error(f"--env-option / --train-option {key}: set it with the learner's own option "
                         f"{RESERVED_OPTIONS[key]} instead")
        if key in REFUSED_OPTIONS:
            parser.error(f"--env-option / --train-option {key}: not supported, {REFUSED_OPTIONS[key]}")
    if args.levels in ("test", "published"):  # a generalisation study is void once it trains on its test levels
        parser.error(f"--levels {args.levels}: the test levels are for evaluation only (--eval-levels {args.levels}); "
                     f"train on a count n (levels 0..n-1) or train")
    check_self_play(parser, args, env_options={**dict(args.env_option), **dict(args.train_option)})
    if args.seeds is not None:
        if args.seed is not None:
            parser.error(f"--seed and --seeds exclude each other: give one, got --seed {args.seed} and --seeds "
                         f"{' '.join(map(str, args.seeds))}")
        repeated = sorted({seed for seed in args.seeds if args.seeds.count(seed) > 1})
        if repeated:
            parser.error(f"--seeds must name each seed once, got {repeated} more than once")
    for seed in [args.seed] if args.seeds is None else args.seeds:  # before the first seed's training, not after it
        if seed is not None and not 0 <= seed < 2 ** 63:
            parser.error(f"--seed{'s' if args.seeds is not None else ''} must be an int in [0, 2**63), got {seed}")
    args.seed = 0 if args.seed is None else args.seed
    if args.tensorboard is not None:  # "" would send SummaryWriter to its own runs/DATE_HOST folder
        problem = writable_folder(args.tensorboard) if args.tensorboard else "it is empty"
        if problem:
            parser.error(f"--tensorboard must be a folder this process can write to, got {args.tensorboard!r}: "
                         f"{problem}")
    if args.out is None:
        args.out = os.path.join("out", "baselines", args.env if args.obs == "pixels" else f"{args.env}-state")
    problem = writable_folder(args.out)
    if problem:
        parser.error(f"--out must be a folder this process can write to, got {args.out!r}: {problem}")


def check_self_play(parser: argparse.ArgumentParser, args: argparse.Namespace, env_options: dict) -> None:
    """The pool's options in range, given only with --self-play, and a task of two or more teams."""
    for name, *_ in SELF_PLAY_OPTIONS:
        value = getattr(args, name.replace("-", "_"))
        if value is None:
            continue
        if not args.self_play:
            parser.error(f"--{name} applies to self-play only: add --self-play, got --{name} {value}")
        problem = setting_problem(name.replace("-", "_"), value)
        if problem:
            parser.error(f"--{name} {problem}")
    if args.self_play:
        try:  # the task's teams, from a one-world env of its training options
            with make_env(args.env, num_worlds=1, resolution=8, state_obs=True, **env_options) as probe:
                team_index(probe.groups)
        except ValueError as error:
            parser.error(f"--self-play: {error}")


def writable_folder(path: str) -> str | None:
    """None if `path` is a folder that takes files, or could be made one; else what is wrong.
    Nothing is left behind: a folder that does not exist yet is tried through its nearest ancestor."""
    existing = os.path.abspath(path)
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        return "it is a file" if existing == os.path.abspath(path) else f"{existing} is a file"
    try:
        with tempfile.NamedTemporaryFile(dir=existing, prefix=".write-check-"):
            pass
    except OSError as exc:
        return f"{existing} takes no files ({exc.strerror or exc})"
    return None


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


def require_matplotlib() -> None:
    """Exit at once (one line naming the extra, status 1) when curve.png could not be drawn at the end."""
    with command_needs_extra("plots", "python -m marl_render.baselines (its curve.png)"):
        import matplotlib  # noqa: F401 (only its presence is checked here)


def require_tensorboard() -> None:
    """Exit at once (one line naming the extra, status 1) when --tensorboard could not log."""
    with command_needs_extra("tensorboard", "python -m marl_render.baselines --tensorboard"):
        import tensorboard  # noqa: F401 (torch.utils.tensorboard needs it; imported only when asked for)


def tensorboard_writer(folder: str):
    """A SummaryWriter into `folder` (torch's, imported only when --tensorboard asks for it)."""
    require_tensorboard()
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(folder)


def log_update(writer, run, point: dict) -> None:
    """One update's curve point (and a checkpoint it made) as TensorBoard scalars at the env steps learned from."""
    step = run.learned_env_steps
    for key, value in point.items():
        if key not in ("env_steps", "seconds") and isinstance(value, (int, float)):
            writer.add_scalar(f"train/{key}", value, step)
    if run.checkpoints and run.checkpoints[-1]["updates"] == run.updates:
        writer.add_scalar("checkpoint/return_mean", run.checkpoints[-1]["mean"], step)


def main(argv=None) -> int:
    """The command; Ctrl-C ends it with one line saying what was written (exit status 130), no traceback."""
    stage = {"writing": False}
    try:
        return train_and_write(argv, stage)
    except KeyboardInterrupt:
        print("python -m marl_render.baselines: interrupted (Ctrl-C) " + (
            "while writing the run's files: each file in --out is whole, this run's or the earlier one's"
            if stage["writing"] else "before writing anything: --out holds what it held before"),
            file=sys.stderr, flush=True)
        return 130


def train_and_write(argv, stage: dict) -> int:
    """Train, evaluate and write the run folder; stage["writing"] is True once its files are being written."""
    started = time.perf_counter()
    args = parse_args(argv)
    require_matplotlib()
    if args.tensorboard is not None:
        require_tensorboard()  # a missing extra ends here, before any training
    if args.reproducible and reproducible.problems():
        if argv is not None:  # called from Python: torch has chosen its kernels in this process already
            print("error: --reproducible needs a process started with its environment ("
                  + "; ".join(reproducible.problems()) + "): run `python -m marl_render.baselines --reproducible "
                  "...`, which restarts itself with it", file=sys.stderr)
            return 2
        reproducible.restart()  # the command line again, in a process that loads torch pinned
    argv = sys.argv[1:] if argv is None else list(argv)
    with reproducible.mode() if args.reproducible else contextlib.nullcontext():
        return train_seeds(args, argv, started, stage)


def train_seeds(args: argparse.Namespace, argv: list, started: float, stage: dict) -> int:
    """One run, or one per seed of --seeds followed by the across-seed summary."""
    if args.seeds is None:
        return train_one(args, argv, started, stage)[0]
    results = []
    for seed in args.seeds:
        one = argparse.Namespace(**{**vars(args), "seed": seed, "out": os.path.join(args.out, f"seed{seed}"),
                                    "tensorboard": None if args.tensorboard is None else
                                    os.path.join(args.tensorboard, f"seed{seed}")})
        print(f"== seed {seed} of {len(args.seeds)} seeds: {one.out}", flush=True)
        status, result = train_one(one, seed_command(argv, seed, one.out, one.tensorboard), time.perf_counter(),
                                   stage)
        if status:
            return status
        results.append({**result, "out": one.out})
    summary = seeds_summary(results)
    print_seeds_summary(summary)
    write_atomically(os.path.join(args.out, "seeds.json"),
                     lambda f: f.write(strict_json.dumps(summary, indent=1).encode()))
    return 0


def train_one(args: argparse.Namespace, argv: list, started: float, stage: dict) -> tuple:
    """One run of `args` (its --seed, into its --out): (exit status, result.json's content);
    stage["writing"] is set once its files are being written."""
    hp = task_hyperparameters(args.env, **{name: getattr(args, name) for name in FIELDS})
    if hp.torch_threads == 0:  # the cores this process may use
        hp = dataclasses.replace(hp, torch_threads=len(os.sched_getaffinity(0)))
    torch.set_num_threads(hp.torch_threads)  # the evaluations' too
    evaluation_set = EVALUATION_SETS[args.eval_set]
    eval_seed = evaluation_set["seed"] if args.eval_seed is None else args.eval_seed
    episodes = evaluation_set["episodes"] if args.episodes is None else args.episodes
    set_name = args.eval_set if eval_seed == evaluation_set["seed"] else f"seed {eval_seed}"
    # The development and publication sets are env seeds of the default resets: other levels are another set.
    shown_set = f"{set_name} set" if args.eval_levels is None else \
        f"levels {args.eval_levels!r}, env seed {eval_seed}"
    env_steps = args.env_steps if args.env_steps is not None or args.updates is not None else \
        step_budget(args.env, args.obs)
    load_start = os.getloadavg()[0]
    print(f"{args.env}: MAPPO from {args.obs}, budget "
          f"{f'{args.updates} updates' if args.updates else f'{env_steps:,} env steps'}, {hp}", flush=True)

    env_options, train_options = dict(args.env_option), dict(args.train_option)
    if args.appearance is not None:
        env_options["appearance"] = args.appearance
    if args.levels is not None:
        train_options["levels"] = args.levels
    eval_kwargs = dict(episodes=episodes, seed=eval_seed, final=args.final, resolution=hp.resolution,
                       grayscale=hp.grayscale, state_obs=args.obs == "state", **env_options,
                       **({} if args.eval_levels is None else {"levels": args.eval_levels}))
    try:  # the first env this run builds: an option the env refuses ends here, in one line, before training
        references = {name: evaluate(args.env, policy, **eval_kwargs)
                      for name, policy in (("random", random_policy), ("heuristic", heuristic_policy))}
    except (ValueError, TypeError) as error:
        print(f"error: the {args.env} env refused its options (--resolution, --grayscale, --obs, --env-option, "
              f"--appearance, --eval-levels): {error}", file=sys.stderr)
        return 2, None
    print(f"random {references['random']['mean']:.4g} ± {references['random']['std']:.2g}, heuristic "
          f"{references['heuristic']['mean']:.4g} ± {references['heuristic']['std']:.2g} "
          f"({episodes} episodes, {shown_set})", flush=True)

    printed = [0.0]
    writer = None if args.tensorboard is None else tensorboard_writer(args.tensorboard)

    def progress(run, point):
        if writer is not None:
            log_update(writer, run, point)
        now = time.perf_counter()
        if now - printed[0] < PROGRESS_SECONDS:
            return
        printed[0] = now
        shown = [p["episode_return"] for p in run.curve if p["episode_return"] is not None]
        last = f"{shown[-1]:.4g}" if shown else "- (no episode ended yet)"
        # The env steps learned from: with --overlap the next rollout, collected meanwhile, is not counted yet.
        print(f"[{now - started:6.0f} s] update {run.updates}/{run.budget_updates}, {run.learned_env_steps:,} env "
              f"steps ({run.env_steps / point['seconds']:,.0f}/s), episode return {last}, "
              f"entropy {point['entropy']:.3f}", flush=True)

    checkpoint_every = args.checkpoint_every
    if checkpoint_every is None:
        checkpoint_every = math.ceil((env_steps or args.updates * hp.worlds * hp.rollout * hp.action_repeat)
                                     / CHECKPOINTS)
    try:
        run = train(args.env, obs=args.obs, env_steps=env_steps, updates=args.updates, seed=args.seed,
                    hyperparameters=hp, env_options=env_options, train_options=train_options,
                    checkpoint_every=checkpoint_every, checkpoint_episodes=args.checkpoint_episodes,
                    max_seconds=None if args.max_minutes is None else args.max_minutes * 60, progress=progress,
                    self_play=self_play_settings(args), reproducible=args.reproducible)
        trainer = run.trainer

        eval_start = time.perf_counter()
        policy = evaluate(args.env, run.policy(), **eval_kwargs)
        print(f"learned greedy policy {policy['mean']:.4g} ± {policy['std']:.2g} (random "
              f"{references['random']['mean']:.4g}, heuristic {references['heuristic']['mean']:.4g}; "
              f"{shown_set})", flush=True)
        on_training_levels = None
        if args.eval_levels is not None:  # scored on other levels: on its own training levels too, for the gap
            own = {key: value for key, value in eval_kwargs.items() if key != "levels"}
            if args.levels is not None:
                own["levels"] = args.levels
            on_training_levels = {"levels": args.levels, "policy": evaluate(args.env, run.policy(), **own),
                                  **{name: evaluate(args.env, reference, **own) for name, reference in
                                     (("random", random_policy), ("heuristic", heuristic_policy))}}
            print(f"on its training levels ({'the default resets' if args.levels is None else repr(args.levels)}, "
                  f"env seed {eval_seed}): learned {on_training_levels['policy']['mean']:.4g}, random "
                  f"{on_training_levels['random']['mean']:.4g}, heuristic "
                  f"{on_training_levels['heuristic']['mean']:.4g}", flush=True)
        evaluation_seconds = time.perf_counter() - eval_start
        if writer is not None:
            for name, value in (("policy", policy), *references.items()):
                writer.add_scalar(f"evaluation/{name}", value["mean"], run.learned_env_steps)
    finally:
        if writer is not None:
            writer.close()

    result = {
        "env": args.env, "obs": args.obs,
        "algorithm": "MAPPO (clipped PPO objective, GAE as TorchRL's): shared actor on each agent's own observation, "
                     "centralised critic on all agents' state observations",
        "command": "python -m marl_render.baselines " + shlex.join(argv),
        "seeds": {"train": args.seed, "evaluation": eval_seed},
        "evaluation_set": set_name,
        "budget": {"env_steps": run.budget_env_steps, "updates": run.budget_updates,
                   "max_minutes": args.max_minutes},
        "budget_minutes": args.max_minutes,  # the opt-in cap (None: none); the budget is in env steps
        "truncated": run.truncated,
        "versions": versions(),
        "mode": "reproducible" if args.reproducible else "default",
        "arithmetic": arithmetic(),
        "machine": {"cpu": reproducible.cpu(), "cpu_count": os.cpu_count(),
                    "cores_available": len(os.sched_getaffinity(0)),
                    "load_average_1min_start": load_start, "load_average_1min_end": os.getloadavg()[0],
                    "platform": platform.platform(), "processor": platform.processor()},
        "wall_clock_seconds": time.perf_counter() - started,
        "training_seconds": run.training_seconds, "env_seconds_in_training": trainer.seconds_stepping,
        "training_cpu_seconds": run.training_cpu_seconds, "stage_seconds": trainer.clock.seconds,
        "checkpoint_seconds": run.checkpoint_seconds, "evaluation_seconds": evaluation_seconds,
        "env_steps": trainer.env_steps, "updates": run.updates,
        "hyperparameters": dataclasses.asdict(run.hyperparameters),
        "env_options": env_options, "train_options": train_options, "evaluation_levels": args.eval_levels,
        "env_defaults": left_at_default(env_options),
        "trained_agents": [n for n, t in zip(trainer.env.agent_names, trainer.trained.tolist(), strict=True) if t],
        "evaluation": {"policy": policy, **references,
                       "return": "sum of the evaluated agents' rewards over an episode, averaged over them; "
                                 "mean and std over episodes"},
        "checkpoints": run.checkpoints,
        "curve": run.curve,
    }
    if trainer.vector_keys:  # the task's vector observations the actor reads, in its order (load_policy)
        result["vector_obs"] = list(trainer.vector_keys)
        result["algorithm"] += f"; both networks also read the task's vector observations {list(trainer.vector_keys)}"
    if on_training_levels is not None:
        result["evaluation_training_levels"] = on_training_levels
    stage["writing"] = True
    os.makedirs(args.out, exist_ok=True)
    stale = clear_snapshots(args.out)  # an earlier run's in this folder: the new result.json does not describe them
    if stale:
        print(f"{args.out} held an earlier run: its {stale} snapshot(s) are replaced by this run's files", flush=True)
    if trainer.pool is not None:
        result["algorithm"] += "; self-play: every team trained against a pool of frozen snapshots of the actor"
        result["self_play"] = save_snapshots(trainer.pool, result, args.out)
    write_atomically(os.path.join(args.out, "actor.pt"), lambda f: torch.save(trainer.actor_net.state_dict(), f))
    write_atomically(os.path.join(args.out, "result.json"),
                     lambda f: f.write(strict_json.dumps(result, indent=1).encode()))
    plot_curve(result, os.path.join(args.out, "curve.png"))
    print(f"wrote {args.out}/actor.pt, result.json and curve.png in {result['wall_clock_seconds']:.0f} s", flush=True)
    return 0, result


if __name__ == "__main__":
    sys.exit(main())
