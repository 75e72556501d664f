"""One evaluation of a focal policy on held-out scenarios, one score.

    python -m marl_render.evaluate --list
    python -m marl_render.evaluate --policy heuristic --scenario tag --out out/heuristic_tag
    python -m marl_render.evaluate --policy docs/baselines/tag/seed0 --scenario all --out out/mappo_tag
    python -m marl_render.evaluate --docs            # regenerates docs/heldout.md and docs/crossplay.md
    python -m marl_render.evaluate --docs --crossplay-only --task tag   # only tag's cross-play section
    python -m marl_render.evaluate --crossplay tag --roster random heuristic docs/selfplay/tag/seed0 --out out/x
    python -m marl_render.evaluate --import my_tasks --crossplay my_task --roster random out/my_task --out out/x

A policy is ``random``, ``heuristic``, a heuristic variant of the task (a bot name of
marl_render/bots.py, e.g. ``interceptor``) or a run folder of ``python -m marl_render.baselines``
(``load_policy``). A scenario is a held-out scenario's name, a task's name (its scenarios) or ``all``.

Each scenario plays `episodes` episodes at once (one per world of its focal-only env, no autoreset,
the task's default length). A row holds the focal per-capita return (the focal agents' summed
reward over the episode, averaged over them; mean and std over episodes), the background's per-capita
return, the bots that were sampled (slots played, summed over episodes), and the normalised score
(score - random) / (heuristic - random) with the returns of random and heuristic focal players on the
same scenario and seed. With the same policy, scenario and seed the numbers are the same.

``--out PREFIX`` writes PREFIX.json and PREFIX.csv (one row per scenario); without it the JSON is
printed.

``--crossplay TASK`` plays every policy of ``--roster`` as the task's first team against every one
as its second (any registered task of two or more teams, a user's too: ``--import MODULE`` or
``module:Class``; its bots by name once ``register_bot`` made them known), and writes the matrices
and Elo ratings to PREFIX.json, the tables (Elo, returns, win rates) to PREFIX.md, which it also
prints, and the win-rate heatmap to PREFIX.png (matplotlib: the plots extra); without ``--out``
it prints the JSON. Self-play
snapshots are run folders (``python -m marl_render.baselines --self-play`` writes them under
OUT/snapshots/).
"""
from __future__ import annotations

import argparse
import os
import sys

import torch

from marl_render.envs import list_envs, make_env
from marl_render.envs.levels import levels_option
from marl_render.envs.task_imports import add_import_option, load_user_tasks
from marl_render.util import strict_json
from marl_render.util.extras import command_needs_extra
from marl_render.util.threads import MAX_THREADS

from .pages import (
    CROSSPLAY_EPISODES,
    DOCS_EPISODES,
    DOCS_RESOLUTION,
    DOCS_SEED,
    crossplay_page,
    crossplay_section,
    heatmap,
    heldout_file_name,
    heldout_page,
    mean_gap_lines,
    normalised_gaps,
    publish,
    publish_heldout,
    rewrite_heldout_page,
    self_play_verdict,
)
from .scores import (
    baseline_runs,
    check_seed,
    crossplay,
    crossplay_roster,
    evaluate,
    evaluate_heldout,
    listing,
    make_policy,
    matrix_env_kwargs,
    normalised,
    play,
    run_label,
    scenario_names,
    scenario_returns,
    selfplay_runs,
    spec_key,
    training_condition,
    trains_focal_side,
    write,
)

# This module was the whole evaluation before it was split by concept (scores.py plays, pages.py writes
# the pages, this is the command line): their names stay importable from here.
__all__ = ["CROSSPLAY_EPISODES", "DOCS_EPISODES", "DOCS_RESOLUTION", "DOCS_SEED", "HelpFormatter", "baseline_runs",
           "check_seed", "crossplay", "crossplay_page", "crossplay_roster", "crossplay_section", "evaluate",
           "evaluate_heldout", "heatmap", "heldout_file_name", "heldout_page", "listing", "main", "make_policy",
           "matrix_env_kwargs", "mean_gap_lines", "normalised", "normalised_gaps", "out_problem", "play", "publish",
           "publish_heldout", "rewrite_heldout_page", "run_label", "scenario_names", "scenario_returns",
           "self_play_verdict", "selfplay_runs", "spec_key", "training_condition", "trains_focal_side", "write"]


def out_problem(prefix: str) -> str | None:
    """What keeps `prefix` from taking PREFIX.json (and .csv), or None: checked before any work."""
    if not prefix or prefix.endswith(("/", os.sep)) or os.path.basename(prefix) in (".", ".."):
        return ("it names a folder, and --out is the prefix of the files written (OUT.json, OUT.csv): add a file "
                "name, e.g. out/results")
    existing = os.path.dirname(os.path.abspath(prefix))
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        return f"{existing} is a file, not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"the folder {existing} takes no files"
    return None


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def main(argv=None) -> int:
    prog = "python -m marl_render.evaluate"
    load_user_tasks(argv, prog, ("--crossplay",))  # a user's task, before its name is checked
    parser = argparse.ArgumentParser(prog=prog, description=__doc__, formatter_class=HelpFormatter)
    add_import_option(parser)
    parser.add_argument("--list", action="store_true", help="print every held-out scenario, its tags and bots")
    parser.add_argument("--policy", help="random, heuristic, a heuristic variant or a run folder")
    parser.add_argument("--scenario", default="all", help="a held-out scenario, a task (its scenarios) or all")
    parser.add_argument("--episodes", type=int, default=32, help="episodes per scenario (one per world)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the envs, the bots and random players")
    parser.add_argument("--resolution", type=int, default=16, help="pixels per side (a run folder's own wins)")
    parser.add_argument("--max-steps", type=int, default=None, help="shorter episodes (default: the task's length)")
    parser.add_argument("--gap", action="store_true", help="also play the training condition (generalisation gap)")
    parser.add_argument("--levels", type=levels_option, default=None,
                        help="levels of the scenarios' envs: a count n, train, test or published (default: none)")
    parser.add_argument("--appearance", choices=("train", "heldout"), default=None,
                        help="per-level looks of the scenarios' envs (default: off)")
    parser.add_argument("--out", help="write OUT.json and OUT.csv instead of printing JSON")
    parser.add_argument("--docs", action="store_true", help="regenerate docs/heldout.md and docs/crossplay.md")
    parser.add_argument("--crossplay-episodes", type=int, default=CROSSPLAY_EPISODES,
                        help="--docs: episodes per cross-play pair")
    parser.add_argument("--task", nargs="+", default=None, help="--docs: only these tasks")
    parser.add_argument("--crossplay-only", action="store_true",
                        help="--docs: only the cross-play matrices of --task (the others' sections are kept)")
    parser.add_argument("--heldout-only", action="store_true",
                        help="--docs: only the held-out tables (the cross-play page is kept)")
    parser.add_argument("--baselines", default=None, help="--docs: the MAPPO runs' folder (default docs/baselines)")
    parser.add_argument("--selfplay", default=None, help="--docs: the self-play runs' folder (default docs/selfplay)")
    parser.add_argument("--crossplay", metavar="TASK", choices=list_envs(), default=None,
                        help="cross-play of --roster on TASK (two or more teams; a user's: --import, module:Class)")
    parser.add_argument("--roster", nargs="+", default=["random", "heuristic"],
                        help="--crossplay: the policies (random, heuristic, a heuristic variant, run folders)")
    parser.add_argument("--torch-threads", type=int, default=1,
                        help="torch threads of the trained actors (1: on a busy machine more threads spin idle)")
    args = parser.parse_args(argv)
    # The envs' torch_threads bound (marl_render/threads.py): fixed, not this machine's cores, so that a published
    # command line runs on every machine; beyond it torch would start idle OpenMP threads by the thousand.
    if not 1 <= args.torch_threads <= MAX_THREADS:
        parser.error(f"--torch-threads must be in [1, {MAX_THREADS}], got {args.torch_threads}")
    if not 0 <= args.seed < 2 ** 63:
        parser.error(f"--seed must be an int in [0, 2**63), got {args.seed}")
    if args.out is not None and out_problem(args.out):
        parser.error(f"--out {args.out!r}: {out_problem(args.out)}")
    threads = torch.get_num_threads()
    torch.set_num_threads(args.torch_threads)
    try:
        return run_command(parser, args)
    except BrokenPipeError:  # `--list | head`: the reader has gone; stop quietly, as a shell tool does
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes
        return 1
    finally:
        torch.set_num_threads(threads)


def run_command(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """What main does once the command line is read."""
    if args.list:
        print(listing(), flush=True)
        return 0
    if args.docs:
        if args.crossplay_only and args.heldout_only:
            parser.error("--crossplay-only and --heldout-only exclude each other: leave both out for both pages")
        publish(episodes=args.episodes, crossplay_episodes=args.crossplay_episodes, seed=args.seed,
                resolution=args.resolution, tasks=args.task, baselines=args.baselines, selfplay=args.selfplay,
                crossplay_only=args.crossplay_only, heldout_only=args.heldout_only)
        return 0
    if args.crossplay is not None:
        return crossplay_command(parser, args)
    if args.policy is None:
        parser.error("--policy is required (or --list, or --docs)")
    try:
        scenarios = scenario_names(args.scenario)
        rows = evaluate_heldout(args.policy, scenarios, episodes=args.episodes, seed=args.seed,
                                resolution=args.resolution, max_steps=args.max_steps, gap=args.gap, levels=args.levels,
                                appearance=args.appearance)
    except (ValueError, FileNotFoundError) as error:
        parser.error(str(error))
    if args.out:
        write(rows, args.out)
        print(f"wrote {args.out}.json and {args.out}.csv ({len(rows)} scenarios)", flush=True)
    else:
        print(strict_json.dumps(rows), flush=True)
    return 0


def crossplay_command(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """--crossplay TASK --roster ...: the matrices and Elo, written to OUT.json or printed."""
    if args.crossplay_episodes < 1:
        parser.error(f"--crossplay-episodes must be >= 1, got {args.crossplay_episodes}")
    try:
        with make_env(args.crossplay, num_worlds=1, resolution=8) as probe:
            teams = list(probe.groups)
    except (ValueError, TypeError) as error:
        parser.error(f"--crossplay {args.crossplay}: {error}")
    if len(teams) < 2:  # the task first: no roster plays a task of one team
        parser.error(f"cross-play needs a task of two or more teams; {args.crossplay} has {teams}")
    if args.out:  # its heatmap: a missing matplotlib ends here, before the matrix is played
        with command_needs_extra("plots", "python -m marl_render.evaluate --crossplay --out (its heatmap)"):
            import matplotlib  # noqa: F401
    roster = roster_of(parser, args.roster, args.crossplay, args.seed)
    try:
        result = crossplay(args.crossplay, roster, episodes=args.crossplay_episodes, seed=args.seed,
                           resolution=args.resolution)
    except (ValueError, FileNotFoundError) as error:
        parser.error(str(error))
    if args.out:
        folder = os.path.dirname(args.out)
        if folder:
            os.makedirs(folder, exist_ok=True)
        with open(args.out + ".json", "w") as f:
            strict_json.dump(result, f, indent=1)
        table = "\n".join(crossplay_section(result, os.path.basename(args.out) + ".png", win_rates=True))
        with open(args.out + ".md", "w") as f:
            f.write(table)
        heatmap(result, args.out + ".png")
        print(table)
        print(f"wrote {args.out}.json, {args.out}.md and {args.out}.png (win-rate heatmap; {len(roster)} policies)")
    else:
        print(strict_json.dumps(result), flush=True)
    return 0


def roster_of(parser: argparse.ArgumentParser, specs: list, task: str, seed: int) -> dict:
    """{label: spec} of --roster, every entry checked before any pair is played: parser.error naming
    --roster for a roster of one, an entry given twice, an unknown policy or a run folder that is
    broken or of another task."""
    if len(specs) < 2:
        parser.error(f"--roster must name at least 2 policies (each plays every other), got {specs}")
    seen: dict = {}
    for spec in specs:
        key = os.path.realpath(spec) if os.path.isdir(spec) else spec
        if key in seen:
            parser.error(f"--roster names {spec!r} twice ({seen[key]!r} is the same policy): name each policy once")
        seen[key] = spec
    roster = {}
    for spec in specs:
        try:
            label = run_label(spec) if os.path.isdir(spec) and os.path.isfile(os.path.join(spec, "result.json")) \
                else spec
            make_policy(spec, task, seed)
        except (ValueError, FileNotFoundError, TypeError) as error:
            parser.error(f"--roster {spec!r}: {error}")
        roster[label if label not in roster else spec] = spec
    return roster


if __name__ == "__main__":
    sys.exit(main())
