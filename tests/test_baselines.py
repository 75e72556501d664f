"""python -m marl_render.baselines end to end with a tiny budget (files and their fields, not
training results), its argument errors, and the report generator on those files."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from marl_render.baselines import report, run
from marl_render.baselines.ppo import FrameStack
from marl_render.baselines.settings import Hyperparameters, task_hyperparameters

TINY = ["--budget-minutes", "0.02", "--worlds", "2", "--resolution", "8", "--episodes", "2", "--rollout", "4"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two tiny runs: spread from pixels, tag (random prey) from the state."""
    root = tmp_path_factory.mktemp("baselines")
    assert run.main(["--env", "spread", "--out", str(root / "spread"), *TINY]) == 0
    assert run.main(["--env", "tag", "--obs", "state", "--out", str(root / "tag-state"), *TINY]) == 0
    return root


def _check_return(r: dict, episodes: int):
    assert set(r) >= {"mean", "std", "min", "max", "episodes", "evaluated_agents"}
    assert r["episodes"] == episodes
    assert all(isinstance(r[k], float) and math.isfinite(r[k]) for k in ("mean", "std", "min", "max"))
    assert r["min"] <= r["mean"] <= r["max"]


@pytest.mark.parametrize("folder, env, obs, trained",
                         [("spread", "spread", "pixels", 3), ("tag-state", "tag", "state", 3)])
def test_result_json_has_every_field(runs, folder, env, obs, trained):
    result = json.loads((runs / folder / "result.json").read_text())
    assert result["env"] == env and result["obs"] == obs
    assert result["command"].startswith("python -m marl_render.baselines --env ")
    assert result["seeds"] == {"train": 0, "evaluation": 1000}
    assert set(result["versions"]) >= {"marl_render", "torch", "torchrl", "tensordict"}
    assert result["hyperparameters"] == {**vars(task_hyperparameters(env)), "worlds": 2, "resolution": 8,
                                         "rollout": 4}
    assert len(result["trained_agents"]) == trained
    assert isinstance(result["env_steps"], int) and result["env_steps"] >= 2 * 4  # one update at least
    assert result["updates"] == len(result["curve"]) >= 1
    for key in ("wall_clock_seconds", "training_seconds", "evaluation_seconds"):
        assert isinstance(result[key], float) and result[key] > 0
    steps = [p["env_steps"] for p in result["curve"]]
    assert steps == sorted(steps) and steps[-1] == result["env_steps"]
    for point in result["curve"]:
        assert set(point) >= {"env_steps", "seconds", "episode_return", "episodes_ended", "entropy"}
        assert point["episode_return"] is None or isinstance(point["episode_return"], float)
    for policy in ("policy", "random", "heuristic"):
        _check_return(result["evaluation"][policy], 2)


def test_curve_png_is_written(runs):
    with Image.open(runs / "spread" / "curve.png") as image:
        assert image.format == "PNG"
        pixels = np.asarray(image.convert("L"))
    assert pixels.shape[0] > 200 and pixels.shape[1] > 400
    assert pixels.min() < 100 < pixels.max()  # lines drawn on a light background


def test_report_reads_the_learners_runs(runs, tmp_path):
    """The report on two real runs (tests/test_report.py checks it in detail on synthetic runs)."""
    out = tmp_path / "baselines.md"
    assert report.main(["--results", str(runs), "--out", str(out), "--readme", ""]) == 0
    rows = {line.split("|")[1].strip(): line for line in out.read_text().splitlines() if line.startswith("| ")}
    for folder, env, column in (("spread", "spread", 4), ("tag-state", "tag", 5)):
        result = json.loads((runs / folder / "result.json").read_text())
        learned = result["evaluation"]["policy"]["mean"]
        cell = rows[env].split("|")[column].strip()
        assert cell == f"{report.number(learned, report.digits(learned))} (seed 0 only)"
        assert (runs / folder / "curves.png").is_file()
    layout = json.loads((runs / "marl_eval.json").read_text())["marl_render"]
    assert set(layout) == {"spread", "tag"} and set(layout["tag"]) == {"mappo_state"}
    assert len(layout["spread"]["mappo_pixels"]["seed_0"]["absolute_metrics"]["return"]) >= 1


@pytest.mark.parametrize("args, message", [
    (["--env", "nope"], "invalid choice"),
    (["--env", "spread", "--worlds", "0"], "--worlds must be >= 1, got 0"),
    (["--env", "spread", "--budget-minutes", "-1"], "--budget-minutes must be > 0, got -1"),
])
def test_bad_arguments_are_named(args, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        run.parse_args(args)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_help_runs_as_a_module():
    result = subprocess.run([sys.executable, "-m", "marl_render.baselines", "--help"], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 0
    assert "--budget-minutes" in result.stdout and "--obs" in result.stdout


def test_task_hyperparameters_apply_task_defaults_then_overrides():
    assert task_hyperparameters("spread") == Hyperparameters()
    cartpole = task_hyperparameters("cartpole", frames=None, lr=1e-3)
    assert cartpole.action_repeat > 1 and cartpole.frames > 1 and cartpole.lr == 1e-3
    with pytest.raises(TypeError, match="unknown hyperparameter"):
        task_hyperparameters("spread", learning_rate=1.0)


def test_frame_stack_keeps_the_last_frames_and_restarts_worlds():
    import torch
    stack = FrameStack(3)
    first = torch.zeros(2, 1, 1)
    assert stack.reset(first).tolist() == [[[0, 0, 0]], [[0, 0, 0]]]
    stack.push(torch.ones(2, 1, 1))
    stack.push(torch.full((2, 1, 1), 2.0))
    assert stack.stack.tolist() == [[[0, 1, 2]], [[0, 1, 2]]]
    stack.restart(torch.full((2, 1, 1), 5.0), torch.tensor([False, True]))
    assert stack.stack.tolist() == [[[0, 1, 2]], [[5, 5, 5]]]


def test_learning_accuracy_study_runs_and_reports(tmp_path):
    """Two settings, two seeds, a tiny budget: every run's files, the report's json, table and plot."""
    from marl_render.baselines import learning_accuracy

    out = tmp_path / "learning"
    argv = ["--minutes", "0.03", "--seeds", "0", "1", "--settings", "32px", "32px-msaa4", "--episodes", "2",
            "--jobs", "2", "--out", str(out), "--worlds", "2", "--rollout", "4"]
    assert learning_accuracy.main(argv) == 0
    for setting in ("32px", "32px-msaa4"):
        for seed in (0, 1):
            result = json.loads((out / f"{setting}-seed{seed}" / "result.json").read_text())
            assert result["seeds"]["train"] == seed and result["hyperparameters"]["worlds"] == 2
    msaa = json.loads((out / "32px-msaa4-seed0" / "result.json").read_text())
    assert msaa["env_options"] == {"multisamples": 4} and msaa["hyperparameters"]["resolution"] == 32
    summary = json.loads((tmp_path / "learning.json").read_text())
    assert summary["seeds"] == [0, 1] and set(summary["settings"]) == {"32px", "32px-msaa4"}
    for entry in summary["settings"].values():
        assert entry["seeds"] == 2 and [r["seed"] for r in entry["runs"]] == [0, 1]
        assert entry["env_steps_per_second_mean"] > 0
    text = (tmp_path / "learning.md").read_text()
    assert "| 32px-msaa4: MSAA 4 samples |" in text and "1.00x |" in text
    assert (tmp_path / "learning.png").stat().st_size > 10_000
    # A second call keeps the finished runs and only rewrites the report.
    before = (out / "32px-seed0" / "result.json").stat().st_mtime_ns
    assert learning_accuracy.main(argv) == 0
    assert (out / "32px-seed0" / "result.json").stat().st_mtime_ns == before


def test_env_and_train_options_reach_the_envs(tmp_path):
    out = tmp_path / "push"
    assert run.main(["--env", "push", "--out", str(out), *TINY, "--train-option", "shaping=0.5",
                     "--env-option", "max_steps=20"]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["env_options"] == {"max_steps": 20} and result["train_options"] == {"shaping": 0.5}
    assert "--train-option shaping=0.5" in result["command"]


@pytest.mark.parametrize(("args", "message"), [
    (["--train-option", "shaping"], "expected KEY=VALUE"),
    (["--env-option", "max_steps=twenty"], "must be a Python literal"),
    (["--env-option", "resolution=16"], "set it with the learner's own option"),
])
def test_bad_env_options_are_named(args, message, capsys):
    with pytest.raises(SystemExit):
        run.parse_args(["--env", "push", *args])
    assert message in capsys.readouterr().err


def test_learning_accuracy_checks_the_learner_options_before_running(tmp_path, capsys):
    from marl_render.baselines import learning_accuracy

    with pytest.raises(SystemExit):
        learning_accuracy.main(["--out", str(tmp_path / "runs"), "--worlds", "0"])
    assert "--worlds must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()
