"""Episode returns of a policy: the reference numbers of every task (random and scripted heuristic).

    python -m marl_render.envs.evaluation --env all --episodes 32 --json
    python -m marl_render.envs.evaluation --env all --difficulty all --json   # every preset
    python -m marl_render.envs.evaluation --env rooms --levels published        # on the published test levels
    python -m marl_render.envs.evaluation --import my_tasks --env my_task       # a user's task (or my_tasks:MyTask)

For each task it plays `episodes` episodes at once (one per world, no autoreset, the task's
default length) with the scripted heuristic (``Scenario.heuristic``, which reads the state)
and with uniformly random valid actions (sampled among the actions the action mask allows),
and reports the mean and standard deviation of the episode return. The return of an episode
is the sum of the rewards of the evaluated agents, averaged over those agents. A mixed-motive
task (``Scenario.mixed_motive``) adds its episodes' mean social outcomes over all agents
(``efficiency_mean``, ``equality_mean``, ``sustainability_mean``, ``peace_mean``: envs/episodes.py). In tasks with
opponents (``Scenario.opponents``: tag's prey, push's and capture_flag's second team) only the
other agents are evaluated, and the opponents play random actions in both rows: the rows then
say how well a team does against random opponents.

``evaluate(name, policy)`` takes any policy: a function ``policy(env, obs, generator) -> actions``
of every agent (random_policy, heuristic_policy, the trainer's greedy policy) or an object with
``act`` (``marl_render.policies.load_policy``'s saved run, ``heuristic_policy()``, a bot), both
through ``as_policy`` (envs/policy.py, the one policy protocol), so learners are measured the same
way. (``marl_render.evaluate.evaluate_heldout`` is another evaluation: a focal policy on held-out
scenarios with bots.)
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import torch

from marl_render.util import strict_json

from . import masking
from . import options as check
from .episodes import EpisodeOutcomes
from .levels import levels_option
from .policy import as_policy, heuristic_policy, joint_actions
from .registry import env_class, list_envs, make_env
from .task_imports import add_import_option, load_user_tasks


def random_policy(env, obs, generator: torch.Generator) -> torch.Tensor:
    """Uniformly random valid actions: among the unmasked ones for discrete actions (0 for an agent
    whose mask allows nothing: masking.sample_allowed), on the observations' device."""
    if env.continuous:
        return env.random_actions(generator)
    mask = obs["action_mask"]
    return masking.sample_allowed(mask, generator).to(mask.device)


# Env seeds of sealed evaluation sets (marl_render/baselines/settings.py, final_set.py): committed before
# anything was scored on them, scored only when the caller says so (final=True), by the final runs.
SEALED_SEEDS = {52_813_907: "final"}


def check_evaluation_seed(seed, final: bool) -> None:
    """TypeError unless `seed` is an int in [0, 2**63) (make_env's; the generator takes seed + 1);
    ValueError for a sealed set's seed without `final`, or `final` with any other seed."""
    if check.seed("seed", seed) is None:
        raise TypeError("seed must be an int in [0, 2**63), got None")
    if (seed in SEALED_SEEDS) != bool(final):
        raise ValueError(f"seed {seed} is the sealed {SEALED_SEEDS[seed]!r} evaluation set: it is scored only with "
                         f"final=True (python -m marl_render.baselines --eval-set final --final), got final={final!r}"
                         if seed in SEALED_SEEDS else
                         f"final=True applies to a sealed set's seed {sorted(SEALED_SEEDS)}, got seed {seed}")


def evaluate(name: str, policy, *, episodes: int = 32, seed: int = 0, resolution: int = 16, final: bool = False,
             **kwargs) -> dict:
    """Mean, std, min and max episode return of `policy` over `episodes` episodes (one per world), and
    each episode's return (``per_episode``, in world order). A sealed set's seed (``SEALED_SEEDS``) is
    refused unless `final` is True, and `final` is refused with any other seed."""
    check_evaluation_seed(seed, final)
    generator = torch.Generator().manual_seed(seed + 1)
    player = as_policy(policy, generator)  # before the env is built: a policy of no kind fails at once
    env = make_env(name, num_worlds=episodes, resolution=resolution, seed=seed, **kwargs)
    try:
        opponents = opponent_mask(env)
        evaluated = ~opponents
        if not bool(evaluated.any()):  # the mean over no agents would be NaN
            raise ValueError(f"{type(env.scenario).__name__}.opponents {list(env.scenario.opponents)} names every team "
                             f"{list(env.groups)}, so no agent is evaluated; leave at least one team out of it")
        obs = env.reset()
        player.reset(env, torch.ones(episodes, dtype=torch.bool))
        episode_return = torch.zeros(episodes, env.num_agents, dtype=torch.float64)
        running = torch.ones(episodes, dtype=torch.bool)
        outcomes = EpisodeOutcomes(env)  # mixed-motive tasks: efficiency, equality, sustainability, peace
        steps = 0
        while bool(running.any()) and steps < env.max_steps:
            actions = joint_actions(player, env, obs)
            if bool(opponents.any()):
                actions = torch.where(_expand_like(opponents, actions), random_policy(env, obs, generator), actions)
            obs, reward, terminated, truncated, info = env.step(actions)
            episode_return += reward.to(torch.float64) * running[:, None]
            outcomes.add(info, running)
            running &= ~info["done_worlds"]
            steps += 1
        per_world = (episode_return * evaluated).sum(-1) / evaluated.sum()
        return {"mean": float(per_world.mean()), "std": float(per_world.std(unbiased=False)),
                "min": float(per_world.min()), "max": float(per_world.max()), "episodes": episodes,
                "per_episode": per_world.tolist(),
                "evaluated_agents": [n for n, e in zip(env.agent_names, evaluated.tolist(), strict=True) if e],
                **outcomes.fields()}
    finally:
        env.close()


def constant_policy(action: int):
    """A policy that holds `action` for every agent at every step; an agent whose action mask forbids it
    takes its lowest allowed action instead (so in speaker_listener, whose speaker and listener allow
    different actions, each index is one constant listener action). Discrete actions only."""
    def policy(env, obs, generator: torch.Generator) -> torch.Tensor:
        mask = obs["action_mask"]
        lowest = mask.to(torch.int8).argmax(-1)  # the first allowed action of each agent
        return torch.where(mask[..., action], action, lowest)
    return policy


def best_constant_action(name: str, *, episodes: int = 32, seed: int = 0, resolution: int = 16, final: bool = False,
                         **kwargs) -> dict:
    """Every action held for whole episodes (``constant_policy``), each scored by ``evaluate`` on the same
    episodes: the best one's evaluation, with ``"action"`` (its index) and ``"per_action"`` (each action's
    mean return, by index). A baseline a learned policy must beat: one that never looks can reach it.
    `final` as ``evaluate``'s (a sealed set's seed needs it). ValueError for an env built with continuous
    actions (it has no finite set of actions to hold)."""
    check_evaluation_seed(seed, final)  # before the probe env: a sealed seed without final=True builds nothing
    with make_env(name, num_worlds=1, resolution=8, **kwargs) as probe:
        if probe.continuous:
            raise ValueError(f"the best constant action needs discrete actions; {name} was built with "
                             f"continuous=True (a constant continuous action is not one of finitely many)")
        actions = probe.num_actions
    scores = [evaluate(name, constant_policy(a), episodes=episodes, seed=seed, resolution=resolution, final=final,
                       **kwargs) for a in range(actions)]
    best = max(range(actions), key=lambda a: scores[a]["mean"])  # the lowest index among equals
    return {**scores[best], "action": best, "per_action": [score["mean"] for score in scores]}


def opponent_mask(env) -> torch.Tensor:
    """bool [A]: the agents of the task's opponent teams (they play random actions in evaluations)."""
    opponents = set(getattr(env.scenario, "opponents", ()))
    return torch.tensor([team in opponents for team, names in env.groups.items() for _ in names])


def _expand_like(agent_mask: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    mask = agent_mask.expand(actions.shape[0], -1)
    return mask[..., None].expand_as(actions) if actions.ndim == 3 else mask


def reference_returns(name: str, episodes: int = 32, seed: int = 0, **kwargs) -> dict:
    """{"heuristic": ..., "random": ...} of task `name` at its defaults, or with make_env `kwargs`
    (difficulty=, levels=, ...)."""
    out = {}
    for label, policy in (("heuristic", heuristic_policy), ("random", random_policy)):
        start = time.perf_counter()
        out[label] = evaluate(name, policy, episodes=episodes, seed=seed, **kwargs)
        out[label]["seconds"] = round(time.perf_counter() - start, 2)
    return out


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def main(argv=None) -> int:
    prog = "python -m marl_render.envs.evaluation"
    load_user_tasks(argv, prog)  # a user's task (--import MODULE, or --env module:Class) before the names are checked
    parser = argparse.ArgumentParser(prog=prog, description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--env", nargs="+", default=["all"],
                        help="task names (a user's: with --import MODULE, or as module:Class), or all")
    add_import_option(parser)
    parser.add_argument("--episodes", type=int, default=32, help="episodes per policy (one per world)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the envs and the random policy")
    parser.add_argument("--difficulty", choices=("easy", "medium", "hard", "all"), default=None,
                        help="a difficulty preset (all: {task: {preset: returns}}); none: the defaults")
    parser.add_argument("--levels", type=levels_option, default=None,
                        help="levels= of the envs (train, test, published or a count n)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if not 0 <= args.seed < 2 ** 63:
        parser.error(f"--seed must be an int in [0, 2**63), got {args.seed}")
    names = list_envs() if args.env == ["all"] else args.env
    for name in names:
        try:
            env_class(name)  # an unknown name fails now, listing the known ones
        except ValueError as error:
            parser.error(f"--env: {error}")
    extra = {} if args.levels is None else {"levels": args.levels}
    results = {}
    try:  # options a task refuses (a count of worlds beyond memory, levels it lacks): one line, no traceback
        for name in names:
            print(f"evaluating {name} ...", file=sys.stderr, flush=True)
            if args.difficulty == "all":
                results[name] = {preset: reference_returns(name, args.episodes, args.seed, difficulty=preset, **extra)
                                 for preset in ("easy", "medium", "hard")}
                continue
            results[name] = reference_returns(name, args.episodes, args.seed, difficulty=args.difficulty, **extra)
    except (ValueError, TypeError) as error:
        parser.error(str(error))
    if args.json:
        print(strict_json.dumps(results))
    elif args.difficulty == "all":
        for preset in ("easy", "medium", "hard"):
            print(f"{preset}:\n{markdown_table({name: r[preset] for name, r in results.items()})}")
    else:
        print(markdown_table(results))
    return 0


def markdown_table(results: dict) -> str:
    rows = ["| task | heuristic | random | evaluated agents |", "|---|---:|---:|---|"]
    for name, r in results.items():
        h, u = r["heuristic"], r["random"]
        rows.append(f"| {name} | {_pm(h)} | {_pm(u)} | {', '.join(h['evaluated_agents'])} |")
    return "\n".join(rows)


def _pm(r: dict) -> str:
    digits = 2 if max(abs(r["mean"]), r["std"]) < 100 else 1
    return f"{r['mean']:.{digits}f} ± {r['std']:.{digits}f}" if math.isfinite(r["mean"]) else "n/a"


if __name__ == "__main__":
    sys.exit(main())
