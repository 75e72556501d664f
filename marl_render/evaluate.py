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
import csv
import glob
import hashlib
import json
import math
import os
import sys

import numpy as np
import torch

from marl_render import strict_json
from marl_render.bots import POPULATIONS, bot_names, make_bot
from marl_render.elo import elo_ratings
from marl_render.envs import Population, env_class, list_envs, make_env
from marl_render.envs.levels import levels_option
from marl_render.extras import command_needs_extra
from marl_render.heldout import HELDOUT, heldout_scenario, list_heldout
from marl_render.policies import Policy, RandomPolicy, as_policy, heuristic_policy, load_policy, required_env_kwargs
from marl_render.task_imports import add_import_option, load_user_tasks
from marl_render.threads import MAX_THREADS

DOCS_EPISODES, CROSSPLAY_EPISODES, DOCS_SEED, DOCS_RESOLUTION = 32, 16, 0, 16


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
    for _ in range(env.max_steps):
        seen = {key: value.flatten(0, 1) for key, value in obs.items() if key in policy.needs}
        actions = policy.act(env.core, seen, worlds, slots).reshape(W, F, *env.spec.action.shape)
        obs, reward, terminated, truncated, info = env.step(actions)
        focal += reward.sum(1).to(torch.float64) / F * running
        background += info["background_reward"].to(torch.float64) * running
        running &= ~info["done_worlds"]
        if not bool(running.any()):
            break
    return {"focal": focal, "background": background, "bots": env.sampled_bots()}


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


def evaluate(spec, scenarios, *, episodes: int = 32, seed: int = 0, resolution: int = 16, max_steps: int | None = None,
             references: dict | None = None, gap: bool = False, levels=None, appearance=None) -> list:
    """One row per scenario (see the module docstring); `references` caches the random and heuristic
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
               "bots_sampled": _bot_counts(result["bots"])}
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


# ------------------------------------------------------------------ the published pages
def heatmap(result: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rate = np.array(result["win_rate"])
    labels = result["policies"]
    figure, axis = plt.subplots(figsize=(1.0 + 0.6 * len(labels), 0.8 + 0.5 * len(labels)))
    image = axis.imshow(rate, vmin=0, vmax=1, cmap="RdBu")
    axis.set_xticks(range(len(labels)), labels, rotation=60, ha="right", fontsize=7)
    axis.set_yticks(range(len(labels)), labels, fontsize=7)
    for i in range(len(labels)):
        for j in range(len(labels)):
            axis.text(j, i, f"{rate[i, j]:.2f}", ha="center", va="center", fontsize=6)
    side_a, side_b = result["sides"]
    axis.set_xlabel(f"column policy as {side_b}")
    axis.set_ylabel(f"row policy as {side_a}")
    axis.set_title(f"{result['task']}: win rate of the row policy", fontsize=9)
    figure.colorbar(image, ax=axis, fraction=0.04)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _fmt(value: float | None, places: int = 2) -> str:
    """`value` to `places` decimals; "n/a" for None (null in JSON) or a non-finite value, and no minus
    sign on a value that rounds to zero (-0.001 is "0.00", not "-0.00")."""
    if value is None or not math.isfinite(value):
        return "n/a"
    text = f"{value:.{places}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text


def _page_head(title: str, command: str, note: str) -> list:
    return [f"# {title}", "", "Generated by `marl_render/evaluate.py` (do not edit by hand). Reproduce with:", "",
            f"    {command}", "", note, ""]


def heldout_page(rows_by_policy: dict, command: str, note: str) -> str:
    lines = [*_page_head("Held-out scenarios: focal policies with bots they never met", command, note),
             "Each row: the focal agents' per-capita episode return (mean ± std over episodes, one per world), "
             "the normalised score (0 = random focal players, 1 = heuristic focal players on the same scenario "
             "and seed), the return in the training condition (the same focal slots, partners played by the "
             "policy itself, opponents random: how the reference trainer trains) and the generalisation gap "
             "(training condition minus held-out). A trained actor whose focal side the trainer never trained (it "
             "trains one team against random opponents) has neither: \"side not trained\". Scenarios and bots: "
             "`python -m marl_render.evaluate --list`.", ""]
    for policy, rows in rows_by_policy.items():
        lines += [f"## {policy}", "", "| scenario | tags | focal return | background return | score | "
                  "training condition | gap | bots sampled |", "|---|---|---:|---:|---:|---:|---:|---|"]
        for r in rows:
            bots = ", ".join(f"{k} {v}" for k, v in r["bots_sampled"].items())
            lines.append(f"| {r['scenario']} | {r['tags']} | {_fmt(r['focal_return_mean'])} ± "
                         f"{_fmt(r['focal_return_std'])} | {_fmt(r['background_return_mean'])} | "
                         f"{_fmt(r['normalised_score'])} | " + (
                             "side not trained | side not trained" if r.get("focal_side_trained") is False else
                             f"{_fmt(r.get('training_condition_return', math.nan))} | "
                             f"{_fmt(r.get('generalisation_gap', math.nan))}") + f" | {bots} |")
        lines += mean_gap_lines(rows)
        lines.append("")
    return "\n".join(lines)


def rewrite_heldout_page(docs: str) -> str:
    """docs/heldout.md again from its own JSON files (docs/heldout/*.json) and its head (command and
    note), without replaying: for a change of the page's layout, or rows repaired in the JSON."""
    page = os.path.join(docs, "heldout.md")
    with open(page) as f:
        lines = f.read().split("\n")
    command, note = lines[4].strip(), lines[6]
    rows_by_policy = {}
    for line in lines:
        if line.startswith("## "):
            label = line[3:]
            with open(os.path.join(docs, "heldout", heldout_file_name(label) + ".json")) as f:
                rows_by_policy[label] = json.load(f)
    text = heldout_page(rows_by_policy, command, note)
    with open(page, "w") as f:
        f.write(text)
    return text


def heldout_file_name(label: str) -> str:
    """The name (without .json / .csv) of a policy's files in docs/heldout/."""
    return label.replace("MAPPO-vs-random ", "mappo_").replace("self-play ", "selfplay_").replace("/", "_")


def normalised_gaps(rows: list) -> list:
    """Each row's generalisation gap on its scenario's scale, (training condition - held-out) /
    (heuristic - random): comparable across tasks whose returns differ by orders of magnitude. Rows
    without a gap, or whose heuristic and random tie (no scale), are left out."""
    def number(row, key):  # null in JSON (an undefined value) counts as missing, like NaN
        value = row.get(key)
        return math.nan if value is None else value
    scales = [number(r, "heuristic_return") - number(r, "random_return") for r in rows]
    return [r["generalisation_gap"] / scale for r, scale in zip(rows, scales, strict=True)
            if math.isfinite(number(r, "generalisation_gap")) and math.isfinite(scale) and scale != 0]


def mean_gap_lines(rows: list) -> list:
    """The page's summary of a policy's gaps: their mean on each scenario's random-heuristic scale."""
    gaps = normalised_gaps(rows)
    if not gaps:
        return []
    untrained = sum(r.get("focal_side_trained") is False for r in rows)
    left_out = sum("generalisation_gap" in r for r in rows) - len(gaps) - untrained
    notes = ([f"{left_out} scenario(s) without a scale, where heuristic and random tie or a return is undefined, "
              "left out"] if left_out else []) + ([f"{untrained} on a side never trained, without a gap"]
                                                  if untrained else [])
    return ["", f"Mean generalisation gap over {len(gaps)} scenarios, each normalised by its heuristic - random: "
            f"{np.mean(gaps):.2f}" + (f" ({'; '.join(notes)})." if notes else ".")]


def crossplay_page(results: list, command: str, note: str) -> str:
    lines = [*_page_head("Cross-play: every policy against every other, competitive tasks", command, note),
             "Rows play the first team, columns the second. An episode is won by the team with the higher "
             "per-capita return (equal returns: a draw, half a win each). Elo: maximum likelihood over all "
             "episodes of both orders (Hunter's MM iteration, OpenSpiel's method, 0.1 smoothing wins), "
             "anchored at random = 0. `MAPPO-vs-random` is the reference trainer's policy (trained against random "
             "opponents); `self-play` the final actor of `python -m marl_render.baselines --self-play` and "
             "`snapshot K@Nk` its K-th snapshot, taken after N thousand env steps (docs/training.md). A trained "
             "actor plays either side (its agent one-hot names its slot).", ""]
    for result in results:
        lines += crossplay_section(result, f"crossplay/{result['task']}.png")
    return "\n".join(lines)


def crossplay_section(result: dict, picture: str | None = None, win_rates: bool = False) -> list:
    """One cross-play result as markdown lines: the Elo ranking, the self-play verdict, the row
    team's per-capita returns (and, with `win_rates`, the row policy's win rate) per pair."""
    task, labels = result["task"], result["policies"]
    side_a, side_b = result["sides"]
    lines = [f"## {task} ({side_a} vs {side_b}, {result['episodes']} episodes per pair)", ""]
    if picture:
        lines += [f"![{task} cross-play]({picture})", ""]
    lines += ["| Elo | policy |", "|---:|---|"]
    for rating, label in sorted(zip(result["elo"], labels, strict=True), reverse=True):
        lines.append(f"| {_fmt(rating, 0)} | {label} |")
    tables = [(f"Per-capita return of the row team ({side_a}):", result["returns_a"])]
    if win_rates:
        tables.append(("Win rate of the row policy over both sides (a draw counts half):", result["win_rate"]))
    lines += ["", *self_play_verdict(result)]
    for title, matrix in tables:
        lines += [title, "", "| row \\ column | " + " | ".join(labels) + " |", "|---|" + "---:|" * len(labels)]
        for label, values in zip(labels, matrix, strict=True):
            lines.append(f"| {label} | " + " | ".join(_fmt(v) for v in values) + " |")
        lines.append("")
    return lines


def self_play_verdict(result: dict) -> list:
    """Lines saying whether the self-play policy beats the MAPPO-vs-random one in this matrix: their
    Elo, and the win rate of each against the other on both sides."""
    labels = result["policies"]
    selfplay = [label for label in labels if label.startswith("self-play")]
    mappo = [label for label in labels if label.startswith("MAPPO-vs-random")]
    if not selfplay:
        return []
    if not mappo:
        return [f"No MAPPO-vs-random policy with an actor.pt was found for {result['task']}: no comparison with "
                "self-play in this matrix.", ""]
    i, j = labels.index(selfplay[0]), labels.index(mappo[0])
    elo, rate, ra, rb = result["elo"], result["win_rate"], result["returns_a"], result["returns_b"]
    side_a, side_b = result["sides"]
    return [f"**Self-play {'beats' if elo[i] > elo[j] else 'does not beat'} MAPPO-vs-random** ({selfplay[0]} "
            f"against {mappo[0]}): Elo {_fmt(elo[i], 0)} against {_fmt(elo[j], 0)}. Head to head, over both sides, "
            f"self-play wins {_fmt(rate[i][j])} of the episodes (a draw counts half). Per-capita returns "
            f"({side_a}, {side_b}): "
            f"self-play as {side_a} against MAPPO-vs-random {_fmt(ra[i][j])}, {_fmt(rb[i][j])}; MAPPO-vs-random as "
            f"{side_a} against self-play {_fmt(ra[j][i])}, {_fmt(rb[j][i])}.", ""]


def publish(*, docs: str = "docs", episodes: int = DOCS_EPISODES, crossplay_episodes: int = CROSSPLAY_EPISODES,
            seed: int = DOCS_SEED, resolution: int = DOCS_RESOLUTION, tasks=None, baselines: str | None = None,
            selfplay: str | None = None, crossplay_only: bool = False, heldout_only: bool = False) -> None:
    """Writes docs/heldout.md, docs/crossplay.md, their data (docs/heldout/*.json, *.csv) and the
    heatmaps (docs/crossplay/*.png) from random, the heuristic and the MAPPO pixel runs under
    `baselines` (default docs/baselines) that hold an actor.pt, and the self-play runs under
    `selfplay` (default docs/selfplay: snapshots and final actors, cross-play only). With
    `crossplay_only` only the cross-play matrices of `tasks` are played again; the page keeps the
    other competitive tasks' sections from their docs/crossplay/TASK.json."""
    tasks = list(POPULATIONS) if tasks is None else list(tasks)
    command = (f"python -m marl_render.evaluate --docs --episodes {episodes} --crossplay-episodes "
               f"{crossplay_episodes} --seed {seed} --resolution {resolution}"
               + (f" --baselines {baselines}" if baselines else "") + (f" --selfplay {selfplay}" if selfplay else ""))
    baselines = os.path.join(docs, "baselines") if baselines is None else baselines
    selfplay = os.path.join(docs, "selfplay") if selfplay is None else selfplay
    runs, snapshots = baseline_runs(baselines), selfplay_runs(selfplay)
    finals = baseline_runs(selfplay)  # each self-play run's final actor (its snapshots play cross-play only)
    found = sum(len(v) for v in runs.values())
    finals_found = sum(len(v) for v in finals.values())
    note = (f"Policies: random, the heuristic, {found} MAPPO pixel run(s) of {baselines} with an actor.pt"
            + ("" if found else " (none of the published runs keeps its actor.pt yet: rerun this command once "
                                 "they do)") + f" and the final actors of {finals_found} self-play run(s) of "
            f"{selfplay}. Resolution {resolution} px (a trained actor's own where one plays), "
                                               f"seed {seed}.")
    if not crossplay_only:
        publish_heldout(docs, tasks, {task: [*runs.get(task, []), *finals.get(task, [])]
                                      for task in {*runs, *finals}}, episodes, seed, resolution, command, note)
    if heldout_only:  # the cross-play page as it is (the two can be regenerated side by side)
        return
    results = []
    os.makedirs(os.path.join(docs, "crossplay"), exist_ok=True)
    for task in [task for task in POPULATIONS if env_class(task).sides]:  # the cross-play tasks
        path = os.path.join(docs, "crossplay", f"{task}.json")
        if task not in tasks:
            if crossplay_only and os.path.isfile(path):  # kept as it was
                with open(path) as f:
                    results.append(json.load(f))
            continue
        roster = crossplay_roster(task, runs.get(task, []), snapshots.get(task, []))
        print(f"cross-play {task}: {len(roster)} policies ...", file=sys.stderr, flush=True)
        previous = None
        if os.path.isfile(path):  # its pairs played on the same settings are not played again
            with open(path) as f:
                previous = json.load(f)
        result = crossplay(task, roster, episodes=crossplay_episodes, seed=seed, resolution=resolution,
                           previous=previous)
        result["folders"] = {label: spec for label, spec in roster.items() if os.path.isdir(spec)}
        with open(path, "w") as f:
            strict_json.dump(result, f, indent=1)
        heatmap(result, os.path.join(docs, "crossplay", f"{task}.png"))
        results.append(result)
    with open(os.path.join(docs, "crossplay.md"), "w") as f:
        f.write(crossplay_page(results, command + (f" --crossplay-only --task {' '.join(tasks)}" if crossplay_only
                                                   else ""), note))


def publish_heldout(docs: str, tasks: list, runs: dict, episodes: int, seed: int, resolution: int, command: str,
                    note: str) -> None:
    """docs/heldout.md and its JSON and CSV files in docs/heldout/: random, the heuristic and the trained
    runs (MAPPO-vs-random and self-play final actors) on every held-out scenario."""
    scenarios = [name for task in tasks for name in list_heldout(task)]
    references: dict = {}
    print(f"held-out tables: {len(scenarios)} scenarios ...", file=sys.stderr, flush=True)
    rows_by_policy = {label: evaluate(label, scenarios, episodes=episodes, seed=seed, resolution=resolution,
                                      references=references, gap=True) for label in ("random", "heuristic")}
    unplayable = []
    for task, folders in runs.items():
        for folder in folders:
            if task not in tasks:
                continue
            # An actor's agent one-hot fixes its team sizes: it plays the scenarios defined for them only.
            trained_with = load_policy(folder).num_agents
            defined = [heldout_scenario(name) for name in list_heldout(task)]
            fitting = [scenario.name for scenario in defined if scenario.num_agents == trained_with]
            if len(fitting) < len(defined):
                sizes = sorted({scenario.num_agents for scenario in defined} - {trained_with})
                unplayable.append(f"{os.path.relpath(folder)} (trained with {trained_with} agents) does not play "
                                  f"{task}'s scenarios defined for {', '.join(map(str, sizes))} agents.")
            if fitting:
                rows_by_policy[f"{run_label(folder).split(' seed')[0]} {os.path.relpath(folder)}"] = evaluate(
                    folder, fitting, episodes=episodes, seed=seed, resolution=resolution,
                    references=references, gap=True)
    if unplayable:
        note += " " + " ".join(unplayable)
    os.makedirs(os.path.join(docs, "heldout"), exist_ok=True)
    for label, rows in rows_by_policy.items():
        write(rows, os.path.join(docs, "heldout", heldout_file_name(label)))
    with open(os.path.join(docs, "heldout.md"), "w") as f:
        f.write(heldout_page(rows_by_policy, command, note))


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
        rows = evaluate(args.policy, scenarios, episodes=args.episodes, seed=args.seed, resolution=args.resolution,
                        max_steps=args.max_steps, gap=args.gap, levels=args.levels, appearance=args.appearance)
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
