"""Scores of focal policies: a policy on held-out scenarios (its focal slots, test bots on the
others) and cross-play matrices of a roster on a competitive task (``python -m marl_render.evaluate``
is their command line, marl_render/populations/evaluate.py; pages.py writes the published pages).
Every function here plays episodes, none writes a page."""
from __future__ import annotations

import csv
import glob
import hashlib
import json
import math
import os

import numpy as np
import torch

from marl_render.envs import Population, env_class, make_env
from marl_render.envs.episodes import EpisodeOutcomes
from marl_render.util import strict_json

from .bots import POPULATIONS, bot_names, make_bot
from .elo import elo_ratings
from .heldout import HELDOUT, heldout_scenario, list_heldout
from .policies import Policy, RandomPolicy, as_policy, heuristic_policy, load_policy, required_env_kwargs


def make_policy(spec, task: str, seed: int = 0) -> Policy:
    """A fresh focal policy from `spec`: a policy object or function (``as_policy``), "random",
    "heuristic", a bot name of `task`, or a run folder."""
    if not isinstance(spec, (str, os.PathLike)):
        return as_policy(spec, torch.Generator().manual_seed(seed + 1))
    if spec == "random":
        return RandomPolicy(seed + 1)
    if spec == "heuristic" and task not in POPULATIONS:  # a user's task: its own scripted heuristic
        return heuristic_policy()
    if task in POPULATIONS and spec in bot_names(task):
        return make_bot(task, spec, seed + 2)
    if isinstance(spec, str) and os.path.isdir(spec):
        policy = load_policy(spec)
        policy.check_task(task)  # a run of another task is refused here, naming both
        return policy
    variants = bot_names(task) if task in POPULATIONS else []
    raise ValueError(f"policy must be 'random', 'heuristic', one of {task}'s heuristic variants {variants} "
                     f"or a run folder of python -m marl_render.baselines, got {spec!r}")


def check_seed(seed) -> None:
    """TypeError / ValueError unless `seed` is an int the envs take, [0, 2**63)."""
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"seed must be an int in [0, 2**63), got {seed!r}")
    if not 0 <= seed < 2 ** 63:
        raise ValueError(f"seed must be an int in [0, 2**63), got {seed}")


def play(env, policy: Policy) -> dict:
    """One episode per world of the focal-only env `env` with `policy` on its focal slots: per-world
    focal and background per-capita returns (float64 [W]) and the bots each world sampled."""
    W, F = env.num_worlds, env.num_agents
    worlds = torch.arange(W).repeat_interleave(F)
    slots = env.focal_slots.repeat(W)
    obs = env.reset(seed=env.seed)
    policy.reset(env.core, torch.ones(W, dtype=torch.bool))
    focal = torch.zeros(W, dtype=torch.float64)
    background = torch.zeros(W, dtype=torch.float64)
    running = torch.ones(W, dtype=torch.bool)
    outcomes = EpisodeOutcomes(env)  # mixed-motive tasks: efficiency, equality, sustainability, peace
    for _ in range(env.max_steps):
        seen = {key: value.flatten(0, 1) for key, value in obs.items() if key in policy.needs}
        actions = policy.act(env.core, seen, worlds, slots).reshape(W, F, *env.spec.action.shape)
        obs, reward, terminated, truncated, info = env.step(actions)
        focal += reward.sum(1).to(torch.float64) / F * running
        background += info["background_reward"].to(torch.float64) * running
        outcomes.add(info, running)
        running &= ~info["done_worlds"]
        if not bool(running.any()):
            break
    return {"focal": focal, "background": background, "bots": env.sampled_bots(), "social": outcomes.fields()}


def _env(task: str, episodes: int, seed: int, resolution: int, policy: Policy, max_steps=None, **kwargs):
    # A trained actor's resolution and colours, never the levels and looks it trained on: those are the caller's.
    return make_env(task, num_worlds=episodes, seed=seed, max_steps=max_steps,
                    **{"resolution": resolution, **required_env_kwargs(policy), **kwargs})


def scenario_returns(spec, scenario, *, episodes: int = 32, seed: int = 0, resolution: int = 16,
                     max_steps: int | None = None, **looks) -> dict:
    """play() of policy `spec` on held-out `scenario`; `looks`: levels= and appearance= of its env."""
    scenario = heldout_scenario(scenario)
    policy = make_policy(spec, scenario.task, seed)
    with _env(scenario.task, episodes, seed, resolution, policy, max_steps, heldout=scenario, **looks) as env:
        return play(env, policy)


def training_condition(spec, scenario, *, episodes: int = 32, seed: int = 0, resolution: int = 16,
                       max_steps: int | None = None, **looks) -> dict:
    """play() of policy `spec` on the focal slots of `scenario` in the condition the reference trainer
    trains in: its partners (the background slots of the focal agents' teams, or every slot of a
    cooperative task) are copies of itself, opponents play random actions."""
    scenario = heldout_scenario(scenario)
    policy = make_policy(spec, scenario.task, seed)
    focal_teams = {team for team, names in _teams(scenario.task, scenario.num_agents).items()
                   if set(names) & set(scenario.focal)}
    competitive = bool(getattr(env_class(scenario.task), "opponents", ()))
    roles = {team: [RandomPolicy(seed + 3) if competitive and team not in focal_teams else policy]
             for team in scenario.bots_by_role}
    with _env(scenario.task, episodes, seed, resolution, policy, max_steps, num_agents=scenario.num_agents,
              **scenario.params, **looks,
              background=Population(roles, focal=scenario.focal)) as env:
        return play(env, policy)


def _teams(task: str, num_agents: int) -> dict:
    with make_env(task, num_worlds=1, resolution=8, num_agents=num_agents) as env:
        return dict(env.groups)


def _summary(values: torch.Tensor) -> tuple:
    return float(values.mean()), float(values.std(unbiased=False))


def _bot_counts(bots: list) -> dict:
    counts: dict = {}
    for row in bots:
        for name in row:
            counts[name] = counts.get(name, 0) + 1
    return dict(sorted(counts.items()))


def normalised(value: float, random: float, heuristic: float) -> float:
    """0 at random focal players, 1 at heuristic ones; NaN where the two are equal."""
    return (value - random) / (heuristic - random) if heuristic != random else math.nan


def evaluate_heldout(spec, scenarios, *, episodes: int = 32, seed: int = 0, resolution: int = 16,
                     max_steps: int | None = None, references: dict | None = None, gap: bool = False, levels=None,
                     appearance=None) -> list:
    """One row per held-out scenario that policy `spec` plays on its focal slots (see the module
    docstring; ``evaluate`` is its old name, ``marl_render.envs.evaluation.evaluate`` another
    evaluation: a task's episode returns without bots); `references` caches the random and heuristic
    returns per scenario between calls; `gap` adds the training condition's return; `max_steps`
    shortens the episodes (None: the task's length, the published protocol); `levels` and
    `appearance` are make_env's (None: the scenario's default resets and looks)."""
    if isinstance(scenarios, str):  # one name is not a list of its characters
        raise TypeError(f"scenarios must be a list of held-out scenario names, got the str {scenarios!r}: pass "
                        f"[{scenarios!r}], or scenario_names({scenarios!r}) for a task's scenarios or 'all'")
    if episodes < 2:
        raise ValueError(f"episodes must be >= 2 (a mean and a std over episodes), got {episodes}")
    check_seed(seed)
    references = {} if references is None else references
    rows = []
    for name in scenarios:
        scenario = heldout_scenario(name)
        same = dict(episodes=episodes, seed=seed, resolution=resolution, max_steps=max_steps,
                    **{k: v for k, v in (("levels", levels), ("appearance", appearance)) if v is not None})
        result = scenario_returns(spec, scenario, **same)
        for label in ("random", "heuristic"):
            key = (scenario.name, label, repr(sorted(same.items())))
            if key not in references:
                references[key] = result if label == spec else scenario_returns(label, scenario, **same)
        mean, std = _summary(result["focal"])
        random, heuristic = (float(references[(scenario.name, label, repr(sorted(same.items())))]["focal"].mean())
                             for label in ("random", "heuristic"))
        row = {"scenario": scenario.name, "task": scenario.task, "tags": " ".join(scenario.tags),
               "policy": spec if isinstance(spec, str) else make_policy(spec, scenario.task, seed).name,
               "episodes": episodes, "seed": seed,
               "focal_return_mean": mean, "focal_return_std": std,
               "background_return_mean": _summary(result["background"])[0],
               "background_return_std": _summary(result["background"])[1],
               "random_return": random, "heuristic_return": heuristic,
               "normalised_score": normalised(mean, random, heuristic),
               "bots_sampled": _bot_counts(result["bots"]), **result["social"]}
        if gap and not trains_focal_side(spec, scenario):
            # The reference trainer trains one team against random opponents: a side it never trained
            # has no training condition to compare with, so no gap either.
            row["training_condition_return"] = row["generalisation_gap"] = None
            row["focal_side_trained"] = False
        elif gap:
            trained = training_condition(spec, scenario, **same)
            row["training_condition_return"] = float(trained["focal"].mean())
            row["generalisation_gap"] = row["training_condition_return"] - mean
        rows.append(row)
    return rows


evaluate = evaluate_heldout  # the old name (docs, scripts); marl_render.envs.evaluation.evaluate is another


def trains_focal_side(spec, scenario) -> bool:
    """Whether policy `spec` was trained in the focal slots of `scenario`: True for random, the
    heuristic and any policy that is not a saved run; for a run folder, whether its result.json's
    trained_agents hold every focal slot (self-play trains every team)."""
    path = os.path.join(spec, "result.json") if isinstance(spec, str) else None
    if path is None or not os.path.isfile(path):
        return True
    with open(path) as f:
        trained = json.load(f).get("trained_agents")
    return trained is None or set(scenario.focal) <= set(trained)


def scenario_names(which: str) -> list:
    """A scenario's name, a task's name (its scenarios) or "all"."""
    if which == "all":
        return list_heldout()
    if which in POPULATIONS:
        return list_heldout(which)
    return [heldout_scenario(which).name]


def write(rows: list, prefix: str) -> None:
    folder = os.path.dirname(prefix)
    if folder:
        os.makedirs(folder, exist_ok=True)
    with open(prefix + ".json", "w") as f:
        strict_json.dump(rows, f, indent=1)
    with open(prefix + ".csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(key for row in rows for key in row)))
        writer.writeheader()
        for row in rows:
            writer.writerow({**row, "bots_sampled": json.dumps(row["bots_sampled"])})


def listing() -> str:
    lines = []
    for name in list_heldout():
        s = HELDOUT[name]
        bots = "; ".join(f"{team}: {', '.join(names)}" for team, names in s.bots_by_role.items())
        lines.append(f"{name}  [{', '.join(s.tags)}]  focal {', '.join(s.focal)}  background {bots}\n"
                     f"    {s.description}")
    return "\n".join(lines)


# ------------------------------------------------------------------ cross-play
def crossplay(task: str, roster: dict, *, episodes: int = 16, seed: int = 0, resolution: int = 16,
              previous: dict | None = None) -> dict:
    """Every policy of `roster` ({label: spec}) as team A against every one as team B (the task's
    ``sides``, or the first two teams of a task that declares none): returns [i, j] of both teams (per capita),
    win/draw counts (the team with the higher per-capita return wins the episode) and Elo ratings
    anchored at the first policy (random). Every pair plays on one env setting: the resolution and
    the env keywords the roster's trained actors need (all must agree), else `resolution`.

    A pair's outcome depends on its two policies, the env setting, `episodes` and `seed` alone: the
    pairs of `previous` (an earlier result) played on the same ones are taken from it, not played again."""
    labels = list(roster)
    n = len(labels)
    if n < 2:
        raise ValueError(f"roster must hold at least 2 policies (each plays every other), got {labels}")
    check_seed(seed)
    env_kwargs = matrix_env_kwargs(task, roster, resolution, seed)
    with make_env(task, num_worlds=1, **{**env_kwargs, "resolution": 8}) as probe:
        if len(probe.groups) < 2:
            raise ValueError(f"cross-play needs a task of two or more teams; {task} has {list(probe.groups)}")
        side_a, side_b = env_class(task).sides or tuple(probe.groups)[:2]
        focal = probe.groups[side_a]
    specs = {label: spec_key(spec) for label, spec in roster.items()}
    same = previous is not None and all(previous.get(k) == v for k, v in (
        ("task", task), ("episodes", episodes), ("seed", seed), ("env_kwargs", env_kwargs)))
    known = {(p["row"], p["column"]): p for p in (previous or {}).get("pairs", [])} if same else {}
    returns_a, returns_b = np.zeros((n, n)), np.zeros((n, n))
    wins, draws = np.zeros((n, n)), np.zeros((n, n))
    pairs = []
    for i, row in enumerate(labels):
        for j, column in enumerate(labels):
            pair = known.get((specs[row], specs[column])) if isinstance(roster[row], str) and isinstance(
                roster[column], str) else None
            if pair is None:
                a = make_policy(roster[row], task, seed)
                b = make_policy(roster[column], task, seed + 7)
                with make_env(task, num_worlds=episodes, seed=seed, **env_kwargs,
                              background=Population({side_b: [b]}, focal=focal)) as env:
                    result = play(env, a)
                difference = result["focal"] - result["background"]
                pair = {"row": specs[row], "column": specs[column], "returns_a": float(result["focal"].mean()),
                        "returns_b": float(result["background"].mean()), "a_wins": int((difference > 1e-9).sum()),
                        "b_wins": int((difference < -1e-9).sum()), "draws": int((difference.abs() <= 1e-9).sum())}
            pairs.append(pair)
            returns_a[i, j], returns_b[i, j] = pair["returns_a"], pair["returns_b"]
            wins[i, j] += pair["a_wins"]
            wins[j, i] += pair["b_wins"]
            draws[i, j] += pair["draws"]
    win_rate = (wins + 0.5 * (draws + draws.T)) / np.maximum(wins + wins.T + draws + draws.T, 1)
    return {"task": task, "sides": [side_a, side_b], "policies": labels, "episodes": episodes, "seed": seed,
            "env_kwargs": env_kwargs, "returns_a": returns_a.tolist(), "returns_b": returns_b.tolist(),
            "wins": wins.tolist(), "draws": draws.tolist(), "win_rate": win_rate.tolist(),
            "elo": elo_ratings(wins, draws).tolist(), "pairs": pairs}


def spec_key(spec) -> str:
    """What identifies a roster entry's play: its name, or a run folder's path and its actor's digest
    (a run trained again in the same folder is another policy)."""
    if not isinstance(spec, str):
        return spec.name
    actor = os.path.join(spec, "actor.pt")
    if not os.path.isfile(actor):
        return spec
    with open(actor, "rb") as f:
        return f"{spec}#{hashlib.sha256(f.read()).hexdigest()[:16]}"


def matrix_env_kwargs(task: str, roster: dict, resolution: int, seed: int) -> dict:
    """The env keywords of a cross-play matrix: `resolution`, overridden by what the roster's
    policies require (``Policy.env_kwargs``); ValueError naming two policies that disagree."""
    required: dict = {}
    owner: dict = {}
    for label, spec in roster.items():
        needs = required_env_kwargs(make_policy(spec, task, seed))
        if isinstance(spec, str) and os.path.isdir(spec):  # the team sizes a trained actor was trained with
            with open(os.path.join(spec, "result.json")) as f:
                options = json.load(f).get("env_options") or {}
            needs.update({key: options[key] for key in ("num_agents",) if key in options})
        for key, value in needs.items():
            if key in required and required[key] != value:
                raise ValueError(f"the roster's policies need different envs: {owner[key]!r} {key}={required[key]!r}, "
                                 f"{label!r} {key}={value!r}")
            required[key], owner[key] = value, label
    return {"resolution": resolution, "grayscale": False, **required}  # the env's default colour, said


def crossplay_roster(task: str, runs: list, snapshots: list = ()) -> dict:
    """{label: policy spec}: random first (the Elo anchor), the heuristic and its variants, the MAPPO
    run folders of `task` among `runs`, then self-play run folders and snapshots (`snapshots`)."""
    roster = {"random": "random", **{name: name for name in (bot_names(task) if task in POPULATIONS
                                                                else ["heuristic"])}}
    for folder in [*runs, *snapshots]:
        roster[run_label(folder)] = folder
    return roster


def run_label(folder: str) -> str:
    """A roster label for a run folder: "MAPPO-vs-random", "self-play" (a self-play run's final actor)
    or "snapshot N@STEPSk" (a self-play snapshot), then the seed. ValueError naming the file for a
    result.json that is not a run's."""
    path = os.path.join(folder, "result.json")
    try:
        with open(path) as f:
            result = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path} is not a readable result.json: {error}") from None
    if not isinstance(result, dict):
        raise ValueError(f"{path} must hold a run's record (a JSON object), got a {type(result).__name__}")
    seeds = result.get("seeds")
    seed = seeds.get("train", "?") if isinstance(seeds, dict) else "?"
    if "snapshot" in result:
        snapshot = result["snapshot"]
        if not (isinstance(snapshot, dict) and all(isinstance(snapshot.get(key), int) and not isinstance(
                snapshot.get(key), bool) for key in ("id", "env_steps"))):
            raise ValueError(f"{path}: snapshot must record its id and env_steps (ints), got {snapshot!r}")
        return f"snapshot {snapshot['id']}@{snapshot['env_steps'] // 1000}k seed{seed}"
    return f"{'self-play' if 'self_play' in result else 'MAPPO-vs-random'} seed{seed}"


def baseline_runs(root: str = "docs/baselines", obs: str = "pixels") -> dict:
    """{task: [run folders]} of the reference runs under `root` that hold an actor.pt (from `obs`)."""
    runs: dict = {}
    for actor in sorted(glob.glob(os.path.join(root, "**", "actor.pt"), recursive=True)):
        folder = os.path.dirname(actor)
        try:
            with open(os.path.join(folder, "result.json")) as f:
                result = json.load(f)
        except (OSError, json.JSONDecodeError):
            continue
        if result.get("obs") == obs and result.get("env") in POPULATIONS and "snapshot" not in result:
            runs.setdefault(result["env"], []).append(folder)
    return runs


def selfplay_runs(root: str = "docs/selfplay", per_run: int = 4) -> dict:
    """{task: [folders]} of the self-play runs under `root` (baseline_runs' layout): of each run,
    `per_run` snapshots evenly spread over training (the first and the last included), then the
    run's final actor."""
    found: dict = {}
    for task, folders in baseline_runs(root).items():
        for folder in folders:
            snapshots = sorted(glob.glob(os.path.join(folder, "snapshots", "*", "actor.pt")))
            if len(snapshots) > per_run:
                step = (len(snapshots) - 1) / (per_run - 1)
                snapshots = [snapshots[round(k * step)] for k in range(per_run)]
            found.setdefault(task, []).extend([*map(os.path.dirname, snapshots), folder])
    return found
