"""The examples as users run them: every script's --help, the cheap ones end to end with tiny
settings (files checked: they exist and decode to the right size), and the pieces of
record_video.py, train_mappo.py and make_env_docs.py that their results rest on."""
import importlib.util
import json
import os
import re
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image, ImageFont

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
SCRIPTS = sorted(p.name for p in EXAMPLES.glob("*.py"))
OPTIONS = {  # beyond --help and --out, which every example takes
    "demo.py": ["--worlds", "--agents", "--resolution", "--bench-worlds", "--steps"],
    "custom_scene.py": ["--worlds", "--resolution"],
    "random_pettingzoo.py": ["--env", "--episodes", "--steps", "--resolution", "--seed"],
    "random_torchrl.py": ["--env", "--worlds", "--steps", "--max-steps", "--resolution", "--seed"],
    "record_video.py": ["--env", "--steps", "--resolution", "--scale", "--seed"],
    "train_mappo.py": ["--minutes", "--worlds", "--agents", "--resolution", "--max-steps", "--seed"],
    "distributed_collect.py": ["--env", "--workers", "--worlds", "--resolution", "--steps-per-batch", "--batches"],
    "make_env_docs.py": ["--seed"],
    "jax_policy_gradient.py": ["--worlds", "--resolution", "--steps", "--horizon", "--seed"],
    "skinned_walkers.py": ["--worlds", "--agents", "--resolution", "--steps", "--seed"],
}


# The end-to-end runs of the examples, {name: (script, arguments)}, each from its own scratch directory
# (relative paths land there). They share one child process (torch, torchrl and GL start once, not once
# per script); each runs as `python SCRIPT ARGS` would (as __main__, its own sys.argv, directory, stdout
# and stderr, torch's thread count reset), and each test reads its own run's result.
RUNS = {
    "demo": ("demo.py", ["--out", "o", "--worlds", 2, "--agents", 3, "--resolution", 32, "--bench-worlds", 4,
                         "--steps", 2]),
    "custom_scene": ("custom_scene.py", ["--out", "o", "--worlds", 3, "--resolution", 24, 40]),
    "skinned_walkers": ("skinned_walkers.py", ["--out", "o", "--worlds", 2, "--agents", 3, "--resolution", 32,
                                               "--steps", 4]),
    "random_pettingzoo": ("random_pettingzoo.py", ["--env", "tag", "--episodes", 1, "--steps", 3, "--resolution", 16,
                                                   "--out", "."]),
    "random_torchrl": ("random_torchrl.py", ["--env", "spread", "--worlds", 3, "--steps", 3, "--max-steps", 2,
                                             "--resolution", 16, "--out", "."]),
    "record_video": ("record_video.py", ["--env", "tag", "--steps", 3, "--resolution", 16, "--scale", 2,
                                         "--out", "v/tag.gif"]),
    "train_mappo": ("train_mappo.py", ["--minutes", 0, "--worlds", 3, "--resolution", 16, "--max-steps", 4,
                                       "--rollout", 6, "--epochs", 1, "--out", "mappo"]),
    # tests/test_docs.py checks the GIFs
    "make_env_docs": ("make_env_docs.py", ["--out", ".", "--no-animations"]),
    # 8-step batches of 40-step episodes: no episode ends in the first batch
    "train_mappo_budget": ("train_mappo.py", ["--minutes", 0.2, "--worlds", 8, "--resolution", 16, "--max-steps", 40,
                                              "--rollout", 8, "--epochs", 1, "--out", "mappo"]),
    # 4 updates of 8 decisions x 4 steps x 4 worlds = 512 steps; one episode of every world takes 800
    "ppo_cartpole": ("ppo_cartpole_pixels.py", ["--worlds", 4, "--resolution", 16, "--steps", 512, "--max-steps", 200,
                                                "--rollout", 8, "--epochs", 1, "--out", "ppo"]),
}
RUN_DRIVER = """
import contextlib, io, json, os, runpy, sys, traceback
import torch
threads = torch.get_num_threads()
results = []
for path, args, cwd in json.loads(sys.stdin.read()):
    out, err = io.StringIO(), io.StringIO()
    sys.argv, sys.path[0] = [path, *args], os.path.dirname(path)
    os.chdir(cwd)
    torch.set_num_threads(threads)
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            runpy.run_path(path, run_name="__main__")
    except SystemExit as exc:
        code = exc.code or 0
    except BaseException:
        code = traceback.format_exc()
    results.append([code, out.getvalue(), err.getvalue()])
print(json.dumps(results))
"""


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict:
    """{name: (its directory, its exit code or error, its stdout, its stderr)} once every run of RUNS has ended."""
    folders = {name: tmp_path_factory.mktemp(name) for name in RUNS}
    todo = [(str(EXAMPLES / script), [str(a) for a in args], str(folders[name]))
            for name, (script, args) in RUNS.items()]
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    result = subprocess.run([sys.executable, "-c", RUN_DRIVER], input=json.dumps(todo), env=env, capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return {name: (folders[name], code, out, err)
            for name, (code, out, err) in zip(RUNS, json.loads(result.stdout.strip().splitlines()[-1]), strict=True)}


def run(runs: dict, name: str) -> tuple[Path, str, str]:
    """(directory, stdout, stderr) of RUNS[name], which must have exited with 0."""
    folder, code, out, err = runs[name]
    assert code == 0, f"{RUNS[name]}: exit {code}\n{out}\n{err[-3000:]}"
    return folder, out, err


def load(script: str) -> types.ModuleType:
    """An example as a module (its main() does not run)."""
    spec = importlib.util.spec_from_file_location(script[:-3], EXAMPLES / script)
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(EXAMPLES))  # make_env_docs imports record_video, as it does when run
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(EXAMPLES))
    return module


def png(path: Path) -> np.ndarray:
    assert path.is_file(), f"{path} was not written"
    with Image.open(path) as image:
        assert image.format == "PNG"
        return np.asarray(image.convert("RGB"))


# Runs `python SCRIPT --help` for every script in one subprocess (torch and torchrl are imported
# once, not once per script): {script: [exit code or the error, stdout]}.
HELP_DRIVER = """
import contextlib, io, json, os, runpy, sys
results = {}
for path in sys.argv[1:]:
    out = io.StringIO()
    sys.argv = [path, "--help"]
    sys.path.insert(0, os.path.dirname(path))
    try:
        with contextlib.redirect_stdout(out):
            runpy.run_path(path, run_name="__main__")
        code = "ran without exiting: --help ignored"
    except SystemExit as exc:
        code = exc.code
    except Exception as exc:
        code = f"{type(exc).__name__}: {exc}"
    results[os.path.basename(path)] = [code, out.getvalue()]
print(json.dumps(results))
"""


@pytest.fixture(scope="module")
def help_texts(tmp_path_factory):
    cwd = tmp_path_factory.mktemp("help")
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    result = subprocess.run([sys.executable, "-c", HELP_DRIVER, *(str(EXAMPLES / s) for s in SCRIPTS)], cwd=cwd,
                            env=env, capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stderr[-3000:]
    assert list(cwd.iterdir()) == []  # --help writes nothing
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("script", SCRIPTS)
def test_help_lists_the_options(script, help_texts):
    code, out = help_texts[script]
    assert code == 0, f"{script} --help: {code}"
    assert out.startswith("usage: ")
    for option in ["--out", *OPTIONS.get(script, [])]:
        assert f"{option} " in out or f"{option}\n" in out, f"{script} --help does not list {option}:\n{out}"
    # every option but --help says its default (one entry per option, "  -x" or "  --x" at line start)
    entries = re.split(r"\n(?=  -)", out.split("\noptions:\n", 1)[1])
    for entry in entries:
        if not entry.lstrip().startswith("-h"):
            assert "(default:" in entry, f"{script} --help shows no default for:\n{entry}"


def test_demo_writes_the_grid_of_views(runs):
    tmp_path, out, _ = run(runs, "demo")
    grid = png(tmp_path / "o" / "demo.png")
    assert grid.shape == (2 * 34 * 2, 3 * 34 * 2, 3)  # worlds x agents tiles of 32 px + 2 px gaps, shown at 2x
    assert grid[:64, :64].std() > 0  # the first view has content
    assert "throughput:" in out and "views/s" in out
    assert not (tmp_path / "out").exists()  # --out is honoured, nothing goes to ./out


def test_custom_scene_writes_a_row_per_world(runs):
    tmp_path, _, _ = run(runs, "custom_scene")
    grid = png(tmp_path / "o" / "custom_scene.png")
    assert grid.shape == (3 * 24, 2 * 40, 3)
    left, right = grid[:24, :40], grid[:24, 40:]
    assert (np.abs(left[..., 0].astype(int) - left[..., 2]) > 0).any() and not np.array_equal(left, right)


def test_skinned_walkers_writes_the_overview_and_compares_with_rigid(runs):
    tmp_path, out, _ = run(runs, "skinned_walkers")
    picture = png(tmp_path / "o" / "skinned_walkers.png")
    row = round(640 * 32 / (3 * 32 + 2 * 2))  # the agents' views with 2 px gaps, scaled to 640 wide
    assert picture.shape == (360 + row, 640, 3)
    assert picture[:360].std() > 0 and picture[360:].std() > 0
    assert "skinned / rigid = " in out and "views/s" in out
    assert not (tmp_path / "out").exists()


def test_random_pettingzoo_writes_the_render(runs):
    from marl_render.wrappers.pettingzoo import make_parallel_env

    tmp_path, out, _ = run(runs, "random_pettingzoo")
    assert "episode 0: 3 steps so far" in out
    env = make_parallel_env("tag", resolution=16, max_steps=3, render_mode="rgb_array")
    env.reset(seed=0)
    expected = env.render().shape
    env.close()
    assert png(tmp_path / "random_pettingzoo.png").shape == expected


def test_random_torchrl_writes_the_overviews(runs):
    tmp_path, out, _ = run(runs, "random_torchrl")
    assert "agents: pixels (3, 3, 3, 16, 16, 3) torch.uint8" in out
    assert "3 episodes finished" in out  # every world ends its episode at step 2
    assert png(tmp_path / "random_torchrl.png").shape == (128, 3 * 128, 3)


def test_record_video_writes_a_gif_of_labelled_tiles(runs):
    gif = run(runs, "record_video")[0] / "v" / "tag.gif"
    with Image.open(gif) as image:
        assert image.format == "GIF" and image.n_frames == 4  # the reset and 3 steps
        assert image.size == (32 + 128, 4 * 32)  # 4 views of 16 px at 2x in a column, the overview as high


def test_record_video_rejects_an_unknown_format():
    record_video = load("record_video.py")
    with pytest.raises(SystemExit) as exc:
        record_video.parse_args(["--out", "episode.avi"])
    assert exc.value.code == 2


def test_frame_image_labels_every_tile():
    record_video = load("record_video.py")
    font = ImageFont.load_default(size=10)
    views = torch.zeros(2, 16, 16, 3, dtype=torch.uint8)
    overview = torch.zeros(8, 8, 3, dtype=torch.uint8)
    image = record_video.frame_image(views, overview, ["agent_0", "prey_1 (left)"], 2, font)
    assert image.shape == (64, 32 + 64, 3) and image.dtype == np.uint8
    white = (image > 200).all(-1)
    tiles = {"agent_0": (slice(0, 32), slice(0, 32)), "prey_1": (slice(32, 64), slice(0, 32)),
             "overview": (slice(0, 64), slice(32, 96))}
    for name, (rows, cols) in tiles.items():
        tile = white[rows, cols]
        assert tile[:14].any(), f"no label on the {name} tile"
        assert not tile[16:].any(), f"the {name} label spills below the tile's top"
    assert not np.array_equal(white[:14, :32], white[32:46, :32])  # the two agents' labels differ
    assert (image[0, 5] == 25).all() and (image[31, 5] == 25).all()  # tile outlines
    assert (image[20, 16] == 0).all()  # the view itself is untouched away from its label


def test_agent_labels_mark_agents_that_left():
    record_video = load("record_video.py")
    env = types.SimpleNamespace(agent_names=["predator_0", "prey_0"], alive=torch.tensor([[True, False], [True, True]]))
    assert record_video.agent_labels(env) == ["predator_0", "prey_0 (left)"]


def test_completed_episodes_sums_the_rewards_of_each_episode():
    from tensordict import TensorDict

    train_mappo = load("train_mappo.py")
    reward = torch.zeros(2, 5, 2, 1)  # [worlds, steps, agents, 1]
    reward[0, :, 0], reward[0, :, 1] = 1.0, 3.0  # world 0: mean over agents 2 per step
    reward[1] = 1.0
    done = torch.zeros(2, 5, 1, dtype=torch.bool)
    done[0, 1] = done[0, 4] = True  # world 0 ends an episode at steps 1 and 4; world 1 never
    batch = TensorDict({"next": {"agents": {"reward": reward}, "done": done}}, batch_size=(2, 5))
    ended, running = train_mappo.completed_episodes(batch, torch.tensor([10.0, 0.0]))
    assert ended.tolist() == [10.0 + 2 * 2, 3 * 2]  # the first episode began in an earlier batch
    assert running.tolist() == [0.0, 5.0]


def test_evaluate_returns_the_episode_sum_per_agent_over_the_worlds_given():
    from marl_render.envs import make_env, make_torchrl_env

    train_mappo = load("train_mappo.py")
    worlds, steps, seed = 3, 4, 5

    def noop(td):
        td.set(("agents", "action"), torch.zeros(worlds, 3, dtype=torch.long))
        return td

    env = make_torchrl_env("spread", num_worlds=worlds, resolution=8, max_steps=steps)
    mean_return, episodes = train_mappo.evaluate(env, noop, seed, random=False)
    env.close()
    core = make_env("spread", num_worlds=worlds, resolution=8, max_steps=steps)
    core.reset(seed=seed)
    total = sum(core.step(torch.zeros(worlds, 3, dtype=torch.long))[1] for _ in range(steps))  # [worlds, agents]
    core.close()
    assert episodes == worlds
    assert mean_return == pytest.approx(float(total.mean()), rel=1e-5)


def test_train_mappo_reports_episode_returns_of_the_worlds_given(runs):
    tmp_path, out, _ = run(runs, "train_mappo")
    out_dir = tmp_path / "mappo"
    result = json.loads((out_dir / "result.json").read_text())
    assert result["eval_episodes"] == 3 and result["episode_steps"] == 4  # --worlds episodes, not a fixed 32
    assert "(3 episodes)" in out
    for key in ("random_return", "untrained_return", "trained_return"):
        assert -100 < result[key] < 0  # spread's reward is negative; 4 steps of at most a few metres each
    assert result["curve"][0][3] is not None  # 6 steps of 4-step episodes: every world ended one
    assert png(out_dir / "curve.png").shape[0] > 100


def test_env_docs_are_up_to_date(runs):
    from marl_render.envs import list_envs

    tmp_path, _, _ = run(runs, "make_env_docs")
    written = (tmp_path / "envs.md").read_text()
    committed = (ROOT / "docs" / "envs.md").read_text()
    assert written == committed, "docs/envs.md is out of date: run python examples/make_env_docs.py"
    for name in list_envs():
        card = (tmp_path / "envs" / f"{name}.md").read_text()
        assert card == (ROOT / "docs" / "envs" / f"{name}.md").read_text(), f"docs/envs/{name}.md is out of date"
        assert f"](envs/{name}.md)" in written and f"]({name}.png)" in card and f"]({name}.gif)" in card
        picture = png(tmp_path / "envs" / f"{name}.png")
        assert picture.shape[0] >= 256 and picture.std() > 10
        assert png(ROOT / "docs" / "envs" / f"{name}.png").shape == picture.shape
    assert "](envs/appearance.png)" in written  # one world under eight appearances
    looks = png(tmp_path / "envs" / "appearance.png")
    assert looks.shape == png(ROOT / "docs" / "envs" / "appearance.png").shape and looks.std() > 10


def test_train_mappo_stops_by_its_budget_rule_whatever_the_speed_and_shows_no_nan(runs):
    train_mappo = load("train_mappo.py")
    tmp_path, _, stderr = run(runs, "train_mappo_budget")
    out_dir = tmp_path / "mappo"
    summary = json.loads((out_dir / "result.json").read_text())
    # The bookkeeping, from the run's own clock readings (so no machine is too slow for it): training gets
    # the budget less the evaluations (the final one is timed as the first), and it stops after the first
    # batch at which one more batch as long as the last would end past that.
    budget = summary["train_budget_seconds"]
    assert summary["budget_minutes"] == 0.2
    assert budget == pytest.approx(max(0.2 * 60 - summary["eval_seconds"] - summary["train_started_seconds"], 0.0),
                                   abs=1e-6)
    ends = [point[0] for point in summary["curve"]]  # seconds of training at the end of each batch
    assert ends and ends == sorted(ends)
    lasted = [end - before for end, before in zip(ends, [0.0] + ends[:-1], strict=True)]
    stops = [train_mappo.next_batch_overruns(end, seconds, budget) for end, seconds in zip(ends, lasted, strict=True)]
    assert stops == [False] * (len(ends) - 1) + [True]
    assert train_mappo.next_batch_overruns(10.0, 2.0, 11.9) and not train_mappo.next_batch_overruns(10.0, 2.0, 12.0)
    assert summary["curve"][0][3] is None  # no episode ended in the first batch ...
    progress = stderr.replace("\r", "\n")
    assert "episode return - (running episodes so far -" in progress  # ... and the bar says so
    assert "nan" not in progress


def test_ppo_cartpole_shorter_than_an_episode_still_plots_its_training(runs):
    tmp_path, out, _ = run(runs, "ppo_cartpole")
    out_dir = tmp_path / "ppo"
    result = json.loads((out_dir / "result.json").read_text())
    assert result["curve"] == []  # no training episode ended ...
    assert "no training episode ended in 512 steps" in out
    steps = [s for s, _ in result["rollout_curve"]]
    assert steps == [128, 256, 384, 512]  # ... but every update has its rollout's reward rate
    for _, rate in result["rollout_curve"]:
        assert 0 < rate <= 200  # cartpole's reward is in [0, 1] per step
    assert png(out_dir / "curve.png").shape[0] > 100
