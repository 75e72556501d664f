"""Write the task pages of the docs from the tasks themselves: docs/envs.md (the index) and one
card per task, docs/envs/NAME.md, with its picture NAME.png and animation NAME.gif.

    python examples/make_env_docs.py [--out docs] [--seed S] [--no-animations | --animate TASK ...]

For every env in ``list_envs()`` it builds the env with its defaults and reads what a card
shows from the objects: the task's Params (defaults, and the comment beside each field as its
meaning), observation keys, shapes, dtypes and values (from a reset), actions, agent names and
teams, physics terms and settings, the keys, shapes and dtypes of the step info (from a step),
the PettingZoo spaces and the TorchRL specs; the rules are the env module's own docstring; the
returns come from docs/reference_returns.json and the runs in docs/baselines, the speed from
docs/bench/env_all.json. The picture of each env (OUT/envs/NAME.png) is every agent's view of
one world after a seeded reset (PICTURE_SEEDS, or --seed), labelled, beside the overview
camera; its animation (NAME.gif) one episode of the heuristic, the first two agents' views beside
the overview. OUT/envs/appearance.png is one world under four train and four held-out
appearances (the `appearance` option, docs/appearance.md); OUT/montage.png, the landing page's
picture, is one agent's view of each task; OUT/authoring.png is docs/authoring.md's task.
OUT/envs/NAME-difficulty.png is the overview of one world at each difficulty preset, whose
random and heuristic returns come from docs/difficulty_returns.json (written by the evaluation
command the card names).

``card(name, seed, picture_dir)`` makes the same card for any registered task, a user's too.
What the code has no names for (the one-line summaries of reward and episode end, the meaning of
the continuous action dimensions and of the info keys, a paragraph under the title) is the task's
own ``card`` (envs/roster.py's Card, on the task class); a built-in env without one stops the
script with an error naming the task's file (a user's task gets blank cells).

tests/test_examples.py runs this script and fails when a page differs from its output.
"""
import argparse
import dataclasses
import inspect
import json
import math
import os
import re
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from marl_render.baselines import report, social
from marl_render.envs import env_class, list_envs, make_env, make_parallel_env, make_torchrl_env
from marl_render.envs.roster import card_of
from record_video import frame_image  # examples/record_video.py: labelled views beside the overview

WORLDS = 2  # worlds of the envs built here; shapes print it as "W"
PICTURE_SEEDS = {"tag": 3}  # reset seeds of the pictures (default 0): tag's 0 shows the predators only walls
ANIMATION_FRAMES = 40  # at most this many frames of an episode in a card's GIF (every k-th step)
PICTURE_HEIGHT = 256  # views are enlarged (nearest neighbour, at least 2x) to a column at least this high
DOCS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs")
APPEARANCE_ENV, APPEARANCE_IDS = "spread", (1, 2, 3, 4)  # the appearances picture: one world, these ids per split
DIFFICULTIES = ("easy", "medium", "hard")
DIFFICULTY_COMMAND = ("python -m marl_render.envs.evaluation --env all --difficulty all --json "
                      "> docs/difficulty_returns.json")

DRIVER_INFO = {  # step info keys of every task -> meaning (a task's own: its card's info)
    "step_count": "steps of the episode just stepped",
    "done_worlds": "every agent of the world terminated or truncated",
    # The social outcomes of a mixed-motive task (envs/episodes.py), for the episode so far:
    "efficiency": "social outcome: the collective return (the sum of every agent's return)",
    "equality": "social outcome: one minus the Gini coefficient of the agents' returns (1: all equal)",
    "sustainability": "social outcome: the mean step at which rewards were earned (0: none earned)",
    "peace": "social outcome: the agent-steps not spent tagged out",
}
SOCIAL = ("efficiency", "equality", "sustainability", "peace")  # the social outcomes' columns (Perolat et al. 2017)
SOCIAL_COMMAND = ("python -m marl_render.envs.evaluation --env {names} --json  # the rows of "
                  "docs/reference_returns.json")
SCHELLING_COMMAND = "python -m marl_render.baselines.schelling --env {name} --episodes 8 --out docs/schelling/{name}"
CONDITION = {"pixels": "always", "depth": "`depth=True`", "state": "`state_obs=True`",
             "action_mask": "discrete actions (the default)"}


def missing(what: str, name: str) -> KeyError:
    """The error of a built-in task whose card lacks `what` (envs/roster.py's Card, on the class)."""
    cls = env_class(name)
    return KeyError(f"no {what} for {name!r}: add it to the card of {cls.__name__} ({cls.__module__}: "
                    f"card = Card(...), envs/roster.py)")


def shape(tensor_shape) -> str:
    """"[W, 3, 64, 64, 3]": a shape whose first dimension is the worlds'."""
    return "[" + ", ".join(["W", *map(str, tensor_shape[1:])]) + "]"


def dtype(value) -> str:
    return str(value).replace("torch.", "")


def table(header, rows) -> list:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]


def own_kwargs(cls) -> str:
    """The task's own keyword arguments with their defaults: the fields of its Params."""
    own = [f"`{field.name}={field.default!r}`" for field in dataclasses.fields(cls.Params)]
    return ", ".join(own) or "none"


def physics_text(env) -> str:
    if env.physics is None:
        return "none of envs/planar.py's planar terms; its own dynamics (see the rules)"
    p = env.physics
    return (f"terms {', '.join(sorted(env.physics_terms))}; dt {p.dt:g} s per step in {p.substeps} substeps, "
            f"{p.integrator}, restitution {p.restitution:g}, drag {p.drag:.3g} /s, speed limit {p.max_speed:g} m/s")


def docstring_parts(cls) -> tuple:
    """(title, rules) of the env's module docstring (a user's task: its class docstring, where it has
    one of its own): its first line, and the rest."""
    own = cls.__dict__.get("__doc__")
    doc = inspect.cleandoc(own) if own and not builtin(cls) else inspect.getdoc(sys.modules[cls.__module__])
    doc = doc or ""
    title, _, rules = doc.partition("\n")
    return title.strip(), rules.strip()


def observations(name: str):
    """Rows of the observation table and the step info table, from a reset and one step."""
    with make_env(name, num_worlds=WORLDS, state_obs=True, depth=True, seed=0) as env:
        obs = env.reset()
        obs_rows = [(f"`{key}`", shape(value.shape), dtype(value.dtype), value_range(value),
                     CONDITION.get(key, "always")) for key, value in obs.items()]
        info = env.step(env.random_actions(torch.Generator().manual_seed(0)))[-1]
    meanings = {**DRIVER_INFO, **card_of(env_class(name)).info}
    info_rows = []
    for key, value in info.items():
        if key not in meanings and builtin(name):
            raise missing(f"info meaning of {key!r}", name)
        info_rows.append((f"`{key}`", shape(value.shape), dtype(value.dtype), meanings.get(key, "")))
    return obs_rows, info_rows


def value_range(value: torch.Tensor) -> str:
    """The values a key held at that reset: "[low, high]", or "False / True" for bools."""
    if value.dtype == torch.bool:
        return " / ".join(str(v) for v in sorted({bool(v) for v in value.unique()}))
    return f"[{value.min().item():.3g}, {value.max().item():.3g}]"


def builtin(task) -> bool:
    """A task (its name or class) of the suite (envs/), whose card must explain every key; a user's
    task gets blanks."""
    cls = env_class(task) if isinstance(task, str) else task
    return cls.__module__.startswith("marl_render.envs.")


def actions(env, name: str) -> list:
    lines = [f"Discrete (the default): `int64 {shape((WORLDS, env.num_agents))}`, values in "
             f"[0, {env.num_actions}).", ""]
    lines += table(("action", "meaning"), [(i, f"`{m}`") for i, m in enumerate(env.action_meanings)])
    with make_env(name, num_worlds=WORLDS, continuous=True) as continuous:
        dims = card_of(env_class(name)).continuous or (("",) * continuous.action_dim if not builtin(name) else ())
        if len(dims) != continuous.action_dim:
            raise missing(f"meaning of each of the {continuous.action_dim} continuous action dimensions", name)
        dims_shape = shape((WORLDS, env.num_agents, continuous.action_dim))
        lines += ["", f"Continuous (`continuous=True`): `float32 {dims_shape}`, each in [-1, 1].", ""]
        lines += table(("dimension", "meaning"), list(enumerate(dims)))
    return lines


def front_ends(name: str) -> list:
    parallel = make_parallel_env(name)
    agent = parallel.possible_agents[0]
    lines = [f"PettingZoo, `make_parallel_env({name!r})` (one world): `observation_space(agent)` = "
             f"`{parallel.observation_space(agent)}`, `action_space(agent)` = `{parallel.action_space(agent)}` "
             f"for every agent (`action_mask=True`, `state_obs=True` or `depth=True` make the observation a `Dict`).",
             ""]
    parallel.close()
    env = make_torchrl_env(name, num_worlds=WORLDS)
    rows = []
    for spec in (env.observation_spec, env.full_action_spec, env.full_reward_spec):
        rows += [(f"`{key}`", shape(spec[key].shape), dtype(spec[key].dtype)) for key in spec.keys(True, True)]
    done = ", ".join(f"`{key}`" for key in env.full_done_spec.keys(True, True))
    lines += [f"TorchRL, `make_torchrl_env({name!r}, num_worlds=W)` (batch `[W]`, one group per team):", ""]
    lines += table(("key", "shape", "dtype"), rows)
    lines += ["", f"and the bool done keys {done} (`[W, 1]`, per world: worlds are the unit of reset, so the "
                  f"one reset key is `_reset`; the per-agent flags are the group entries above)."]
    env.close()
    return lines


def picture(env, seed: int, path: str) -> None:
    """Every agent's view of world 0 after a reset with `seed`, labelled, beside the overview."""
    obs = env.reset(seed=seed)
    scale = picture_scale(env)
    font = ImageFont.load_default(size=max(9, env.resolution[0] * scale // 10))
    image = frame_image(obs["pixels"][0], env.render_overview()[0], env.agent_names, scale, font)
    Image.fromarray(image).save(path, optimize=True)


def appearance_picture(path: str) -> None:
    """One world (APPEARANCE_ENV after reset(seed=0), copied into every world by set_state) under the
    train and held-out looks of APPEARANCE_IDS: each one's agents' views beside its overview, a row
    per split."""
    rows = []
    for split in ("train", "heldout"):
        with make_env(APPEARANCE_ENV, num_worlds=len(APPEARANCE_IDS), appearance=split) as env:
            env.reset(seed=0)
            state = {key: value if key == "rng" else value[:1].expand_as(value).clone()
                     for key, value in env.get_state().items()}
            state["appearance_ids"] = torch.tensor(APPEARANCE_IDS, dtype=torch.int64)
            env.set_state(state)
            # Still bodies and no-op actions: the step changes nothing but the frame it returns.
            pixels = env.step(torch.zeros(env.num_worlds, env.num_agents, dtype=torch.int64))[0]["pixels"]
            overview = env.render_overview()
            scale = picture_scale(env) // 2
            font = ImageFont.load_default(size=max(9, env.resolution[0] * scale // 8))
            cells = []
            for world, look_id in enumerate(APPEARANCE_IDS):
                cell = Image.fromarray(frame_image(pixels[world], overview[world], env.agent_names, scale, font))
                ImageDraw.Draw(cell).text((cell.width - 4, cell.height - 4), f"{split} id {look_id}", font=font,
                                          fill="white", stroke_width=1, stroke_fill="black", anchor="rd")
                cells.append(np.asarray(cell))
            rows.append(np.concatenate(cells, axis=1))
    Image.fromarray(np.concatenate(rows, axis=0)).save(path, optimize=True)


def difficulty_picture(name: str, seed: int, path: str) -> None:
    """The overview of one world after reset(seed) at each difficulty preset, side by side, labelled."""
    cells = []
    for preset in DIFFICULTIES:
        with make_env(name, num_worlds=1, difficulty=preset) as env:
            env.reset(seed=seed)
            image = Image.fromarray(env.render_overview()[0].numpy())
        font = ImageFont.load_default(size=max(9, image.height // 12))
        ImageDraw.Draw(image).text((4, 2), preset, font=font, fill="white", stroke_width=1, stroke_fill="black")
        cells.append(np.asarray(image))
    Image.fromarray(np.concatenate(cells, axis=1)).save(path, optimize=True)


def difficulty_lines(name: str, seed: int, picture_dir: str | None) -> list:
    """The "Difficulty presets" part of a task's card: picture, keywords and returns (none for a task
    without presets)."""
    presets = env_class(name).difficulties
    if not presets:
        return []
    with open(os.path.join(DOCS, "difficulty_returns.json")) as f:
        returns = json.load(f)
    if name not in returns:
        raise KeyError(f"docs/difficulty_returns.json has no row for {name!r}: run `{DIFFICULTY_COMMAND}`")
    if picture_dir is not None:
        difficulty_picture(name, seed, os.path.join(picture_dir, f"{name}-difficulty.png"))
    rows = []
    for preset in DIFFICULTIES:
        h, r = returns[name][preset]["heuristic"], returns[name][preset]["random"]
        keywords = ", ".join(f"`{k}={v!r}`" for k, v in presets[preset].items()) or "the defaults"
        rows.append((f"`{preset}`", keywords, f"{h['mean']:.2f} ± {h['std']:.2f}", f"{r['mean']:.2f} ± {r['std']:.2f}"))
    return (["", "## Difficulty presets", "",
             f"`make_env({name!r}, difficulty=...)` (explicit keywords override the preset's). Returns as in the "
             f"reference table ({returns[name]['easy']['heuristic']['episodes']} episodes); reproduce with "
             f"`{DIFFICULTY_COMMAND}`.", "",
             f"![{name} at the easy, medium and hard presets]({name}-difficulty.png)", "",
             f"*The overview of one world after `reset(seed={seed})` at each preset.*", ""]
            + table(("preset", "keywords", "heuristic", "random"), rows))


def appearance_section(picture_dir: str | None) -> list:
    if picture_dir is not None:
        appearance_picture(os.path.join(picture_dir, "appearance.png"))
    ids = ", ".join(map(str, APPEARANCE_IDS))
    return ["## Appearances: visual domain randomisation", "",
            "With `appearance=\"train\"` or `\"heldout\"` (or a `marl_render.Appearance`) every reset draws "
            "each world's look from its appearance id: light direction and colour, ambient, sky, floor and wall "
            "colours and patterns, a hue / saturation / value jitter of everything else, and the agents' camera "
            "field of view, height and pitch. No held-out sky, floor or wall shares a hue sector or a pattern "
            "with training. Details, the splits and the cost: [docs/appearance.md](appearance.md).", "",
            "![one world under four train and four held-out appearances](envs/appearance.png)", "",
            f"*`{APPEARANCE_ENV}` after `reset(seed=0)`, the same state in every world, under appearance ids {ids} "
            "of the train split (top) and of the held-out split (bottom): each world's agents' views beside its "
            "overview.*", ""]


def montage(path: str, tile: int = 128) -> None:
    """The landing page's picture: agent 0's own view of each task after its picture reset, enlarged
    to `tile` px (nearest neighbour) and labelled with the task's name, in one row."""
    tiles = []
    for name in list_envs():
        with make_env(name, num_worlds=1, seed=0) as env:
            view = env.reset(seed=PICTURE_SEEDS.get(name, 0))["pixels"][0, 0]
        image = Image.fromarray(view.numpy()).resize((tile, tile), Image.Resampling.NEAREST)
        ImageDraw.Draw(image).text((4, tile - 4), name, font=ImageFont.load_default(size=12), fill="white",
                                   stroke_width=1, stroke_fill="black", anchor="ld")
        tiles.append(np.asarray(image))
    Image.fromarray(np.concatenate(tiles, axis=1)).save(path, optimize=True)


def authoring_picture(path: str) -> None:
    """docs/authoring.md's picture: its tutorial task (rendezvous, defined by the page's blocks before
    section 6, run as written) after reset(seed=0): agent 0's view beside the overview."""
    with open(os.path.join(DOCS, "authoring.md")) as f:
        tutorial = f.read().split("## 6. A second task")[0]
    blocks = re.findall(r"```python\n(.*?)```", tutorial, flags=re.S)
    exec(compile("".join(blocks[:-1]), "docs/authoring.md", "exec"), {"__name__": "authoring_tutorial"})
    with make_env("rendezvous", num_worlds=1, seed=0) as env:
        pixels = env.reset(seed=0)["pixels"][0, :1]
        scale = picture_scale(env) * env.num_agents
        font = ImageFont.load_default(size=max(9, env.resolution[0] * scale // 10))
        image = frame_image(pixels, env.render_overview()[0], env.agent_names[:1], scale, font)
    Image.fromarray(image).save(path, optimize=True)


def picture_scale(env) -> int:
    return max(2, -(-PICTURE_HEIGHT // (env.num_agents * env.resolution[0])))


def card(name: str, seed: int | None, picture_dir: str | None, animate: bool = True) -> str:
    """The task card envs/NAME.md of any registered task, from its class: facts, Params, returns, speed,
    observations, actions, step info, front ends and rules. With `picture_dir` it also draws the
    picture NAME.png and (`animate`) the animation NAME.gif there."""
    cls = env_class(name)
    seed = PICTURE_SEEDS.get(name, 0) if seed is None else seed
    words = card_of(cls)
    if builtin(name) and not (words.reward and words.episode_end):
        raise missing("reward and episode_end", name)
    reward, episode = words.reward or "see the rules below", words.episode_end or "see the rules below"
    title, rules = docstring_parts(cls)
    obs_rows, info_rows = observations(name)
    with make_env(name, num_worlds=WORLDS) as env:
        low, high = cls.agent_range
        H, W = env.resolution
        oh, ow = cls.overview_resolution
        lines = [f"# {name}", "", "<!-- Generated by examples/make_env_docs.py from the task's class. -->", "",
                 title, ""] + ([words.text, ""] if words.text else [])
        if picture_dir is not None:
            picture(env, seed, os.path.join(picture_dir, f"{name}.png"))
        lines += [f"![{name}: every agent's view of one world, and the overview]({name}.png)", "",
                  f"*Every agent's view (left, {H}x{W} shown at {picture_scale(env)}x) of one world after "
                  f"`reset(seed={seed})`, and the overview camera (right, `render_overview()`).*", "",
                  f"![{name}: one episode of the heuristic]({name}.gif)", "",
                  f"*One episode of the scripted heuristic (`env.heuristic_actions()`) after `reset(seed={seed})`: "
                  "the first two agents' views beside the overview, one frame every "
                  f"{animation_stride(env)} steps.*", ""]
        teams = "; ".join(f"`{team}`: {', '.join(agents)}" for team, agents in env.groups.items())
        facts = [
            ("class", f"`{cls.__module__}.{cls.__name__}`"),
            ("make", f"`make_env({name!r}, num_worlds=W)`"),
            ("agents (default)", f"{env.num_agents} ({f'`num_agents` {low} to {high}' if high > low else 'fixed'})"),
            ("teams (groups)", teams),
            ("max_steps", env.max_steps),
            ("resolution", f"{H}x{W} per agent; overview {oh}x{ow}"),
            ("camera", f"field of view {math.degrees(cls.fov_y):g} degrees (vertical), near {cls.near:g} m, "
                       f"far {cls.far:g} m"),
            ("physics", physics_text(env)),
            ("reward", reward),
            ("episode end", episode),
            ("episode end (default)", f"{cls.episode_end_description()} (`episode_end=` of `make_env`: "
                                      "docs/authoring.md)"),
        ]
        lines += table(("", ""), [(f"**{k}**", v) for k, v in facts])
        lines += ["", "## Parameters", "", f"The task's own keywords, `{cls.__name__}.Params` (a frozen dataclass; "
                  "`make_env` passes them on, beside the options every task takes):", ""]
        lines += params_table(cls)
        lines += ["", "## Returns", ""] + returns_section(name)
        lines += social_section(name) + schelling_section(name)
        lines += ["", "## Speed", ""] + speed_section(name)
        lines += ["", "## Observations", "", "`obs = env.reset()` / `env.step(actions)[0]` of the batched core "
                  f"(`make_env({name!r}, num_worlds=W)`), shapes at the defaults; values as at `reset(seed=0)`:", ""]
        lines += table(("key", "shape", "dtype", "values", "present"), obs_rows)
        lines += ["", "## Actions", ""] + actions(env, name)
        if picture_dir is not None and animate:
            animation(env, seed, os.path.join(picture_dir, f"{name}.gif"))
    lines += difficulty_lines(name, seed, picture_dir)
    lines += ["", "## Step info", "", "`info = env.step(actions)[4]`, episode statistics included:", ""]
    lines += table(("key", "shape", "dtype", "meaning"), info_rows)
    lines += ["", "## Front ends", ""] + front_ends(name)
    lines += ["", "## Rules (the docstring of the task's module)", "", rules or "(none)", ""]
    return "\n".join(lines)


def params_table(cls) -> list:
    """One row per field of the task's Params: its default and the comment after it in the source
    (what it means), or the line of a comment above it."""
    fields = dataclasses.fields(cls.Params)
    if not fields:
        return ["None: the task has no keywords of its own."]
    meanings = {}
    try:
        source = inspect.getsource(cls.Params).splitlines()
    except (OSError, TypeError):  # defined where no source is kept (an interactive session)
        source = []
    for number, line in enumerate(source):
        match = re.match(r"\s+(\w+)\s*:[^=#]*(?:=[^#]*)?(?:#\s*(.*))?$", line)
        if match and match.group(1) in {f.name for f in fields}:
            above = source[number - 1].strip() if number else ""
            meanings[match.group(1)] = match.group(2) or (above[1:].strip() if above.startswith("#") else "")
    rows = [(f"`{f.name}`", f"`{f.default!r}`" if f.default is not dataclasses.MISSING else "required",
             meanings.get(f.name, "")) for f in fields]
    return table(("keyword", "default", "meaning"), rows)


def returns_section(name: str) -> list:
    """Random, heuristic and learned returns: docs/reference_returns.json and the runs in docs/baselines."""
    with open(os.path.join(DOCS, "reference_returns.json")) as f:
        reference = json.load(f).get(name)
    runs = report.load_results(Path(DOCS) / "baselines").get(name, {})
    if reference is None and not runs:
        return ["Not measured yet: `python -m marl_render.envs.evaluation --env " + name + "` gives random and "
                "heuristic; `python -m marl_render.baselines --env " + name + "` trains a policy."]
    rows = []
    if reference is not None:
        for policy in ("random", "heuristic"):
            r = reference[policy]
            rows.append((policy, f"{r['mean']:.3g} ± {r['std']:.2g}", r["episodes"], "`python -m marl_render.envs."
                         f"evaluation --env {name}`"))
    for obs, results in sorted(runs.items()):
        seeds = [r["evaluation"]["policy"] for r in results]
        values = " / ".join(f"{s['mean']:.3g} ± {s['std']:.2g}" for s in seeds)
        folders = ", ".join(f"`docs/baselines/{r['relative']}`" for r in results)
        rows.append((f"MAPPO from {obs}, {len(seeds)} seed{'s' * (len(seeds) > 1)}", values, seeds[0]["episodes"],
                     f"runs (result.json, command, curve): {folders}"))
    return (["Episode return of the evaluated agents (mean ± std over episodes; the learned policies greedy, one "
             "entry per training seed; "
             "learning results: [results](../results.md), [baselines](../baselines.md)):", ""]
            + table(("policy", "return", "episodes", "made by"), rows))


def social_section(name: str) -> list:
    """A mixed-motive task's social outcomes (Perolat et al. 2017; envs/episodes.py): random's and the
    heuristic's at the task's defaults (docs/reference_returns.json), then beside MAPPO's on the publication
    worlds (marl_render.baselines.social, from the published runs); none for other tasks."""
    if not env_class(name).mixed_motive:
        return []
    with open(os.path.join(DOCS, "reference_returns.json")) as f:
        reference = json.load(f).get(name, {})
    if not all(f"{key}_mean" in reference.get(policy, {}) for policy in ("random", "heuristic") for key in SOCIAL):
        raise KeyError(f"docs/reference_returns.json has no social outcomes for {name!r}: run "
                       f"`{SOCIAL_COMMAND.format(names=name)}` and put its rows in")
    return (["", "### Social outcomes", "",
             f"Per episode, over all {env_class(name).default_num_agents} agents (opponents included), mean over the "
             f"{reference['heuristic']['episodes']} episodes of the returns above (each task's default episode end); "
             "efficiency is the collective return, equality one minus the Gini coefficient of the returns, "
             "sustainability the mean step of the rewards, peace the agent-steps not tagged out "
             "(envs/episodes.py). Reproduce with "
             f"`{SOCIAL_COMMAND.format(names=name).split('  #')[0]}`.", ""]
            + table(("policy",) + SOCIAL, social_rows(name, reference))
            + ["", "Beside MAPPO: random, the heuristic and the trained policies (mean over the seeds whose outcomes "
                   "were measured) on the publication worlds, with the published rows' options "
                   "(`python -m marl_render.baselines.social`; [results](../results.md)):", ""]
            + table(("policy", "seeds") + SOCIAL, social.task_rows(name, os.path.join(DOCS, "baselines"))))


def social_rows(name: str, reference: dict) -> list:
    """Rows (policy, efficiency, equality, sustainability, peace) of random and the heuristic."""
    return [(policy, *(outcome(reference[policy][f"{key}_mean"]) for key in SOCIAL))
            for policy in ("random", "heuristic")]


def outcome(value: float) -> str:
    """A social outcome's cell: 3 significant digits, whole numbers from 1000 up (peace in agent-steps)."""
    return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"


def schelling_section(name: str) -> list:
    """The Schelling diagram (docs/schelling/NAME.json and .png) of a task that declares one."""
    cls = env_class(name)
    if not cls.schelling:
        return []
    path = os.path.join(DOCS, "schelling", f"{name}.json")
    if not os.path.isfile(path):
        raise KeyError(f"no docs/schelling/{name}.json: run `{SCHELLING_COMMAND.format(name=name)}`")
    with open(path) as f:
        result = json.load(f)
    others = result["others_cooperating"]
    rows = [(label, *(f"{v:.3g}" for v in result[key]))
            for label, key in ((f"cooperator (`{result['bots'][0]}`)", "cooperator"),
                               (f"defector (`{result['bots'][1]}`)", "defector"))]
    yes = {True: "yes", False: "no"}
    A, cooperator, defector = result["num_agents"], result["cooperator"], result["defector"]
    # The group's mean return per agent with k cooperators: k of them earn cooperator[k - 1], A - k defector[k].
    group = [(k * (cooperator[k - 1] if k else 0) + (A - k) * (defector[k] if k < A else 0)) / A for k in range(A + 1)]
    best = max(range(A + 1), key=group.__getitem__)
    return (["", "### Schelling diagram", "",
             f"![{name}: Schelling diagram](../schelling/{name}.png)", "",
             f"Mean return per episode of a cooperator and of a defector (the task's bots `{result['bots'][0]}` and "
             f"`{result['bots'][1]}`) against the number of other cooperators among the {result['num_agents']} "
             f"agents; {result['episodes_per_mix']} episodes of {result['max_steps']} steps (fixed ends) per mix, "
             f"seed {result['seed']}. Made by `{SCHELLING_COMMAND.format(name=name)}`.", ""]
            + table(("other cooperators",) + tuple(map(str, others)), rows)
            + ["", f"Defecting pays the individual at every count (defector > cooperator): "
                   f"**{yes[result['defecting_pays_the_individual']]}**. Cooperating pays the group (all cooperating "
                   f"earn each {result['cooperator'][-1]:.3g}, all defecting {result['defector'][0]:.3g}): "
                   f"**{yes[result['cooperating_pays_the_group']]}**. The group's mean return per agent with k = 0 .. "
                   f"{A} cooperators: {', '.join(f'{g:.3g}' for g in group)} (highest at k = {best})."])


def speed_section(name: str) -> list:
    """The task's row of `bench env --env all` (docs/bench/env_all.json)."""
    with open(os.path.join(DOCS, "bench", "env_all.json")) as f:
        bench = json.load(f)
    rows = [r for r in bench["results"] if r["env"] == name and r.get("api", "core") == "core"]
    if not rows:
        return [f"Not measured: `python -m marl_render.bench env --env {name} --worlds 256 --json`."]
    r = rows[0]
    machine = bench["machine"]
    cpu = f"{machine['cpu_model']}, " if machine.get("cpu_model") else ""  # recorded since issue 41's round
    return [f"`python -m marl_render.bench env --env all --worlds {r['worlds']}` ({cpu}{machine['gl_renderer']}, "
            f"{machine['cpu_threads']} CPU threads, `docs/bench/env_all.json`): "
            f"**{r['env_steps_per_s']:,.0f} env steps/s**, "
            f"{r['agent_frames_per_s']:,.0f} agent frames/s at {r['worlds']} worlds x {r['agents']} agents of "
            f"{r['resolution']} px, {r['ms_per_step']:.1f} ms a step, {r['render_share']:.0%} of it in the renderer "
            "([performance](../performance.md))."]


def animation_stride(env) -> int:
    return max(1, -(-env.max_steps // ANIMATION_FRAMES))


def animation(env, seed: int, path: str) -> None:
    """One episode of the heuristic in world 0 after reset(seed): the first two agents' views (2x) beside
    the overview, every animation_stride-th step, as a GIF of 64 colours (at most ~250 KB)."""
    obs = env.reset(seed=seed)
    shown, stride = env.agent_names[:2], animation_stride(env)
    font = ImageFont.load_default(size=12)
    frames = []
    for step in range(env.max_steps):
        if step % stride == 0:
            overview = env.render_overview(resolution=(2 * len(shown) * env.resolution[0],) * 2)[0]
            image = frame_image(obs["pixels"][0, :len(shown)], overview, shown, 2, font)
            frames.append(Image.fromarray(image).quantize(colors=64, method=Image.Quantize.MEDIANCUT))
        obs = env.step(env.heuristic_actions())[0]
        if bool(env.episode_over()[0]):
            break
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=max(50, 1000 * stride // 20), loop=0,
                   optimize=True)


def page(seed: int | None, picture_dir: str | None) -> str:
    names = list_envs()
    lines = ["# Environments", "",
             "<!-- Generated by examples/make_env_docs.py from the environments; edit that script or the "
             "env modules, then run `python examples/make_env_docs.py`. -->", "",
             "Every env is a `BatchedEnv` (envs/core.py) of W worlds x A agents: `make_env(name, num_worlds=W, "
             "...)` for the batched core, `make_parallel_env(name)` for PettingZoo (one world), "
             "`make_torchrl_env(name, num_worlds=W)` for TorchRL. Common keyword arguments: `num_worlds`, "
             "`num_agents`, `resolution` (int or (height, width)), `max_steps`, `continuous`, `state_obs`, `depth`, "
             "`shadows` (False, True: the arena's shadows, or a `marl_render.Shadows`), `device`, `seed`, "
             "`autoreset`, `grayscale`, the accuracy knobs `multisamples`, `supersample` and `physics_substeps` "
             "(what they cost: docs/accuracy/), `exact_tiles` (the agents' views bit-identical in any world slot "
             "and at any batch size, at 2-5x the render time: docs/levels.md), `readback` (`\"auto\"`, `\"gpu\"` or "
             "`\"host\"`: how frames reach `device`; docs/renderer.md), `num_processes` (worker processes that "
             "share the worlds: docs/distributed.md) "
             "and `compile_physics` (cartpole: its physics kernel through "
             "`torch.compile`, within 1e-12 of the default path; docs/performance.md, \"Compiled physics\"); "
             "arena tasks "
             "also take `lidar` (rays of the obs key `lidar`, float32 [W, A, rays] in [0, 1]) and `lidar_range`, "
             "and discrete ones `enforce_action_mask` (a step refuses actions the mask forbids; by default the "
             "mask is advice: docs/authoring.md); every task takes `appearance` (None, `\"train\"`, "
             "`\"heldout\"` or a `marl_render.Appearance`: per-world looks, below). Teams are named as their "
             "agents are (`red`: red_0, red_1, ...; one team of agent_0, agent_1, ... is `agents`). "
             "Agents that leave an episode (caught prey) stay in every tensor: "
             "reward 0, reported terminated, actions ignored (they must still be valid, e.g. 0), until their "
             "world is reset. `truncated` is True for the agents still in the episode when the world reaches "
             "`max_steps`.", ""]
    rows = []
    for name in names:
        cls = env_class(name)
        words = card_of(cls)
        if not (words.reward and words.episode_end):
            raise missing("reward and episode_end", name)
        rows.append((f"[`{name}`](envs/{name}.md)", cls.default_num_agents, cls.default_max_steps, words.reward,
                     words.episode_end))
    lines += table(("env", "agents", "max_steps", "reward", "episode end"), rows) + [""]
    lines += ["Each task has a card generated from its class (`python examples/make_env_docs.py`): its parameters, "
              "a picture and an animation of the heuristic, its returns and speed, observations, actions, step info, "
              "front-end spaces and rules. A task you register (`register_env`) gets the same card from "
              "`make_env_docs.card(name, ...)`. New to the suite? Start with `cartpole` (one agent, dense reward), "
              "then `spread` (cooperation, the standard MARL task), then the team games.", ""]
    lines += reference_returns(names)
    lines += appearance_section(picture_dir)
    lines += ["```{toctree}", ":hidden:", ""] + [f"envs/{name}" for name in names] + ["```", ""]
    return "\n".join(lines)


def reference_returns(names: list) -> list:
    """The table of docs/reference_returns.json (written by the evaluation command it names)."""
    path = os.path.join(os.path.dirname(__file__), "..", "docs", "reference_returns.json")
    with open(path) as f:
        results = json.load(f)
    absent = sorted(set(names) - set(results))
    if absent:
        raise KeyError(f"docs/reference_returns.json has no row for {absent}: run "
                       f"`python -m marl_render.envs.evaluation --env all --json > docs/reference_returns.json`")
    rows = []
    for name in names:
        h, r = results[name]["heuristic"], results[name]["random"]
        rows.append((f"`{name}`", f"{h['mean']:.2f} ± {h['std']:.2f}", f"{r['mean']:.2f} ± {r['std']:.2f}",
                     ", ".join(h["evaluated_agents"])))
    return (["## Reference returns: scripted heuristic and random", "",
             "Episode return (the sum of the evaluated agents' rewards over an episode, averaged over those agents), "
             f"mean ± std over {results[names[0]]['heuristic']['episodes']} episodes at each task's defaults. The "
             "heuristic (`env.heuristic_actions()`, each task's `Scenario.heuristic`) reads the state; random "
             "samples uniformly among the valid actions. In tasks with opponents (`Scenario.opponents`) the "
             "opponents play random actions in both rows. Reproduce with "
             "`python -m marl_render.envs.evaluation --env all --json > docs/reference_returns.json`.", ""]
            + table(("task", "heuristic", "random", "evaluated agents"), rows) + [""])


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--out", default="docs", help="folder for envs.md, envs/NAME.md, .png and .gif, montage.png "
                                                      "and authoring.png")
    parser.add_argument("--no-animations", dest="animations", action="store_false",
                        help="leave the GIFs out (the pages are the same; a GIF takes seconds per task)")
    parser.add_argument("--animate", nargs="+", metavar="TASK", default=None,
                        help="draw the GIFs of these tasks only (default: every task's, unless --no-animations)")
    parser.add_argument("--seed", type=int, default=None, help="reset seed of every picture; none: "
                                                                 f"{PICTURE_SEEDS}, else 0")
    return parser.parse_args(argv)


def main(argv=None) -> None:
    args = parse_args(argv)
    unknown = sorted(set(args.animate or ()) - set(list_envs()))
    if unknown:
        raise SystemExit(f"--animate: unknown tasks {unknown}; known: {list_envs()}")
    picture_dir = os.path.join(args.out, "envs")
    os.makedirs(picture_dir, exist_ok=True)
    pages = {os.path.join(args.out, "envs.md"): page(args.seed, picture_dir)}
    for name in list_envs():
        pages[os.path.join(picture_dir, f"{name}.md")] = card(name, args.seed, picture_dir,
                                                                  args.animations and name in (args.animate or [name]))
    for path, text in pages.items():
        with open(path, "w") as f:
            f.write(text)
    montage(os.path.join(args.out, "montage.png"))
    authoring_picture(os.path.join(args.out, "authoring.png"))
    print(f"wrote {len(pages)} pages, the pictures{' and animations' * args.animations} in {picture_dir}, "
          f"montage.png and authoring.png")


if __name__ == "__main__":
    main()
