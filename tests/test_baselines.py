"""python -m marl_render.baselines end to end with a tiny budget (files and their fields, not
training results), its argument errors, and the report generator on those files."""
import contextlib
import json
import math
import os
import runpy
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

from marl_render.baselines import report, reproducible, run
from marl_render.baselines.ppo import FrameStack
from marl_render.baselines.settings import Hyperparameters, task_hyperparameters

# 3 updates of 2 worlds x 4 decisions; checkpoints after updates 2 and 3 (16 and 24 env steps).
TINY = ["--env-steps", "24", "--checkpoint-every", "12", "--checkpoint-episodes", "2", "--worlds", "2",
        "--resolution", "12", "--episodes", "2", "--rollout", "4"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two tiny runs: spread from pixels, tag (random prey) from the state."""
    root = tmp_path_factory.mktemp("baselines")
    assert run.main(["--env", "spread", "--out", str(root / "spread"), *TINY]) == 0
    assert run.main(["--env", "tag", "--obs", "state", "--out", str(root / "tag-state"), *TINY,
                     "--no-overlap"]) == 0
    return root


def _check_return(r: dict, episodes: int):
    assert set(r) >= {"mean", "std", "min", "max", "episodes", "per_episode"}
    assert r["episodes"] == episodes == len(r["per_episode"])
    assert all(isinstance(r[k], float) and math.isfinite(r[k]) for k in ("mean", "std", "min", "max"))
    assert r["min"] <= r["mean"] <= r["max"]
    assert r["mean"] == pytest.approx(sum(r["per_episode"]) / episodes)
    assert (r["min"], r["max"]) == (min(r["per_episode"]), max(r["per_episode"]))


@pytest.mark.parametrize("folder, env, obs, trained",
                         [("spread", "spread", "pixels", 3), ("tag-state", "tag", "state", 3)])
def test_result_json_has_every_field(runs, folder, env, obs, trained):
    result = json.loads((runs / folder / "result.json").read_text())
    assert result["env"] == env and result["obs"] == obs
    assert result["command"].startswith("python -m marl_render.baselines --env ")
    assert result["seeds"] == {"train": 0, "evaluation": 1000} and result["evaluation_set"] == "development"
    assert set(result["versions"]) == {"marl_render", "torch", "torchrl", "tensordict", "numpy", "panda3d", "python"}
    assert result["mode"] == "default" and result["machine"]["cpu"] == reproducible.cpu()
    assert result["arithmetic"] == {"environment": {name: os.environ.get(name) for name in reproducible.ENVIRONMENT},
                                    "onednn": True, "deterministic_algorithms": False, "torch_threads": 1}
    assert result["hyperparameters"] == {**vars(task_hyperparameters(env)), "worlds": 2, "resolution": 12,
                                         "rollout": 4, "overlap": obs == "pixels"}
    assert len(result["trained_agents"]) == trained
    assert result["budget"] == {"env_steps": 24, "updates": 3, "max_minutes": None}
    assert result["env_steps"] == 24 and result["updates"] == 3 and result["truncated"] is False
    for key in ("wall_clock_seconds", "training_seconds", "evaluation_seconds", "env_seconds_in_training"):
        assert isinstance(result[key], float) and result[key] > 0
    stages = result["stage_seconds"]
    rollout = ("env", "observation", "policy_forward", "gae")
    update = ("minibatch", "loss_forward_backward", "optimiser")
    assert set(stages) == {*rollout, *update} and all(v >= 0 for v in stages.values())
    assert stages["env"] == result["env_seconds_in_training"]
    overlap = result["hyperparameters"]["overlap"]
    assert overlap == (obs == "pixels")  # the default, and --no-overlap for the state run
    if overlap:  # the next rollout (its env steps counted) is collected while the update runs, beside it
        assert [p["env_steps"] for p in result["curve"]] == [16, 24, 24]
        assert max(sum(stages[k] for k in side) for side in (rollout, update)) <= result["training_seconds"]
    else:
        assert [p["env_steps"] for p in result["curve"]] == [8, 16, 24]
        assert sum(stages.values()) <= result["training_seconds"]
    for point in result["curve"]:
        assert set(point) >= {"env_steps", "seconds", "episode_return", "episodes_ended", "entropy"}
        assert point["episode_return"] is None or isinstance(point["episode_return"], float)
    assert [c["env_steps"] for c in result["checkpoints"]] == [16, 24]
    for checkpoint in result["checkpoints"]:
        assert checkpoint["evaluation_set"] == "development" and checkpoint["seconds"] > 0
        _check_return(checkpoint, 2)
    for policy in ("policy", "random", "heuristic"):
        _check_return(result["evaluation"][policy], 2)
        assert len(result["evaluation"][policy]["evaluated_agents"]) == trained


@pytest.mark.parametrize("folder, env, obs", [("spread", "spread", "pixels"), ("tag-state", "tag", "state")])
def test_the_saved_actor_is_the_policy_that_was_scored(runs, folder, env, obs):
    """actor.pt, loaded into a fresh actor, plays the final evaluation's episodes return for return: the
    row is the run's own final network (with --overlap and without)."""
    from marl_render.baselines.policy import GreedyPolicy
    from marl_render.baselines.ppo import MAPPO
    from marl_render.envs.evaluation import evaluate

    result = json.loads((runs / folder / "result.json").read_text())
    hp = Hyperparameters(**result["hyperparameters"])
    trainer = MAPPO(env, hp, obs, 1, result["env_options"])  # another seed: other initial weights
    trainer.close()
    trainer.actor_net.load_state_dict(torch.load(runs / folder / "actor.pt"))
    threads = torch.get_num_threads()
    torch.set_num_threads(hp.torch_threads)
    try:
        score = evaluate(env, GreedyPolicy(trainer.actor_net, trainer.trained, obs, hp.frames, hp.action_repeat),
                         episodes=2, seed=result["seeds"]["evaluation"], resolution=hp.resolution,
                         grayscale=hp.grayscale, state_obs=obs == "state", **result["env_options"])
    finally:
        torch.set_num_threads(threads)
    assert score["per_episode"] == result["evaluation"]["policy"]["per_episode"]


def test_overlap_scores_the_last_learnt_weights_and_each_seed_its_own():
    """With --overlap the rollouts act one update behind, but the policy a run returns (and scores) holds
    the weights of its last update, and the acting copy has them too once training ends."""
    from marl_render.baselines import train

    hp = task_hyperparameters("spread", worlds=2, rollout=4, resolution=12, overlap=True)
    def snapshot(run_, point):
        run_.snapshots = [*getattr(run_, "snapshots", []),
                          {k: v.clone() for k, v in run_.trainer.actor_net.state_dict().items()}]

    finals = {}
    for seed in (0, 1):
        run_ = train("spread", updates=3, seed=seed, hyperparameters=hp, progress=snapshot)
        final = run_.policy().actor.state_dict()
        assert len(run_.snapshots) == 3
        assert all(torch.equal(final[k], run_.snapshots[-1][k]) for k in final)
        assert not all(torch.equal(final[k], run_.snapshots[-2][k]) for k in final)  # the last update changed it
        acting = dict(run_.trainer.acting_actor.named_parameters())
        assert all(torch.equal(acting[k], p) for k, p in run_.trainer.actor_net.named_parameters())
        finals[seed] = final
    assert not torch.equal(finals[0]["head.4.weight"], finals[1]["head.4.weight"])


def test_curve_png_is_written(runs):
    with Image.open(runs / "spread" / "curve.png") as image:
        assert image.format == "PNG"
        pixels = np.asarray(image.convert("L"))
    assert pixels.shape[0] > 200 and pixels.shape[1] > 400
    assert pixels.min() < 100 < pixels.max()  # lines drawn on a light background


def test_curve_compare_draws_runs_of_a_task_in_one_picture(runs, tmp_path, capsys):
    from marl_render.baselines import curve

    spread = str(runs / "spread" / "result.json")
    out = tmp_path / "compare.png"
    assert curve.main(["--compare", f"old={spread}", f"new={spread}", "--out", str(out)]) == 0
    pixels = np.asarray(Image.open(out).convert("L"))
    assert pixels.shape[0] > 200 and pixels.shape[1] > 400 and pixels.min() < 100 < pixels.max()
    with pytest.raises(SystemExit):
        curve.main(["--compare", spread, "--out", str(tmp_path / "bad.png")])
    assert "--compare takes LABEL=RESULT_JSON, got" in capsys.readouterr().err
    assert not (tmp_path / "bad.png").exists()


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
    (["--env", "spread", "--max-minutes", "-1"], "--max-minutes must be a finite number > 0, got -1.0"),
    (["--env", "spread", "--budget-minutes", "nan"], "--max-minutes must be a finite number > 0, got nan"),
    (["--env", "spread", "--max-minutes", "inf"], "--max-minutes must be a finite number > 0, got inf"),
    (["--env", "spread", "--env-steps", "0"], "--env-steps must be >= 1, got 0"),
    (["--env", "spread", "--updates", "-3"], "--updates must be >= 1, got -3"),
    (["--env", "spread", "--updates", "3", "--env-steps", "9"], "not allowed with argument"),
    (["--env", "spread", "--gamma", "5"], "--gamma must be > 0.0 and <= 1.0, got 5.0"),
    (["--env", "spread", "--gamma", "nan"], "--gamma must be > 0.0 and <= 1.0, got nan"),
    (["--env", "spread", "--clip", "-1"], "--clip must be > 0.0, got -1.0"),
    (["--env", "spread", "--lr", "0"], "--lr must be > 0.0, got 0.0"),
    (["--env", "spread", "--gae-lambda", "1.5"], "--gae-lambda must be >= 0.0 and <= 1.0, got 1.5"),
    (["--env", "spread", "--hidden", "0"], "--hidden must be >= 1, got 0"),
    (["--env", "spread", "--entropy", "-0.1"], "--entropy must be >= 0.0, got -0.1"),
    (["--env", "spread", "--checkpoint-every", "-1"], "--checkpoint-every must be >= 0"),
    (["--env", "spread", "--episodes", "0"], "--episodes must be >= 1, got 0"),
    (["--env", "spread", "--env-option", "autoreset=True"], "autoreset: not supported, the learner resets"),
    (["--env", "spread", "--env-option", "autoreset='next_step'"], "autoreset: not supported"),
    (["--env", "spread", "--train-option", "continuous=True"], "continuous: not supported"),
    (["--env", "spread", "--out", "/proc/self/baselines"], "--out must be a folder this process can write to"),
    (["--env", "spread", "--resolution", "8"], "--resolution must be >= 12 for the 'patch' encoder, got 8"),
])
def test_bad_arguments_are_named(args, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        run.parse_args(args)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_an_out_that_is_a_file_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("an env was evaluated or trained before the arguments were checked")
    monkeypatch.setattr(run, "evaluate", no_work)
    monkeypatch.setattr(run, "train", no_work)
    taken = tmp_path / "result"
    taken.write_text("not a folder")
    for out in (taken, taken / "below"):
        with pytest.raises(SystemExit):
            run.main(["--env", "spread", "--out", str(out), *TINY])
        assert "--out must be a folder this process can write to" in capsys.readouterr().err
    assert taken.read_text() == "not a folder"
    (tmp_path / "new").mkdir()
    run.parse_args(["--env", "spread", "--out", str(tmp_path / "new" / "a" / "b")])
    assert list((tmp_path / "new").iterdir()) == []  # checked, nothing left behind


def test_ctrl_c_ends_the_trainer_in_one_line_leaving_the_earlier_run(tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(run, "train", interrupted)
    out = tmp_path / "run"
    out.mkdir()
    (out / "result.json").write_text("the earlier run")
    assert run.main(["--env", "spread", "--obs", "state", "--out", str(out), *TINY]) == 130
    err = capsys.readouterr().err
    assert err == ("python -m marl_render.baselines: interrupted (Ctrl-C) before writing anything: --out holds what "
                   "it held before\n")
    assert [p.name for p in out.iterdir()] == ["result.json"] and (out / "result.json").read_text() == "the earlier run"


@pytest.mark.parametrize("threads", ["5000", "1025", "-1"])
def test_torch_threads_are_bounded(tmp_path, capsys, threads):
    with pytest.raises(SystemExit):
        run.parse_args(["--env", "spread", "--torch-threads", threads, "--out", str(tmp_path / "out")])
    assert f"--torch-threads must be >= 0 and <= 1024, got {threads}" in capsys.readouterr().err


def test_an_option_the_env_refuses_ends_in_one_line_before_training(tmp_path, capsys, monkeypatch):
    def no_training(*args, **kwargs):
        raise AssertionError("trained with options the env refuses")
    monkeypatch.setattr(run, "train", no_training)
    out = tmp_path / "run"
    assert run.main(["--env", "spread", "--out", str(out), *TINY, "--resolution", "100000"]) == 2
    err = capsys.readouterr().err
    assert "error: the spread env refused its options" in err
    assert "resolution must be at most" in err and "got (100000, 100000)" in err
    assert "Traceback" not in err and not (out / "result.json").exists()


def run_module(name: str, argv: list, monkeypatch) -> int | str | None:
    """`python -m name *argv` in this process (runpy runs the module as __main__, as -m does; a fresh
    interpreter's `-m` is tested by test_the_same_command_gives_the_same_numbers): its exit code."""
    monkeypatch.setattr(sys, "argv", [name, *argv])
    with pytest.raises(SystemExit) as exit_, warnings.catch_warnings():
        # runpy's note that the package imported the module before: it runs the module's code afresh
        warnings.filterwarnings("ignore", f"'{name}' found in sys.modules", RuntimeWarning)
        runpy.run_module(name, run_name="__main__", alter_sys=False)
    return exit_.value.code


def test_the_reference_evaluation_refuses_zero_episodes(monkeypatch, capsys):
    assert run_module("marl_render.envs.evaluation", ["--env", "spread", "--episodes", "0"], monkeypatch) == 2
    assert "--episodes must be >= 1, got 0" in capsys.readouterr().err


def _numbers(result: dict):
    """result.json without what measures time or the machine's load."""
    if isinstance(result, dict):
        return {k: _numbers(v) for k, v in result.items() if "seconds" not in k and k != "machine"}
    if isinstance(result, list):
        return [_numbers(v) for v in result]
    return result


def test_the_same_command_gives_the_same_numbers(tmp_path):
    """Training stops on env steps, not on the clock: two runs of one command agree in every number but
    the timings, in separate processes (as a user would run them)."""
    results = []
    for name in ("first", "second"):
        command = [sys.executable, "-m", "marl_render.baselines", "--env", "spread", "--out", str(tmp_path / name),
                   *TINY, "--env-steps", "16", "--episodes", "3"]
        subprocess.run(command, check=True, capture_output=True, timeout=300)
        results.append(json.loads((tmp_path / name / "result.json").read_text()))
    first, second = map(_numbers, results)
    assert first["curve"][0]["loss_objective"] != 0.0 and first["evaluation"]["policy"]["per_episode"]
    assert first == {**second, "command": first["command"]}


def test_publication_set_scores_the_final_policy_and_the_references(tmp_path):
    out = tmp_path / "publication"
    assert run.main(["--env", "spread", "--out", str(out), *TINY, "--env-steps", "8", "--eval-set", "publication",
                     "--checkpoint-every", "0"]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["evaluation_set"] == "publication" and result["seeds"]["evaluation"] == 7_000_000
    assert result["checkpoints"] == []
    for policy in ("policy", "random", "heuristic"):
        _check_return(result["evaluation"][policy], 2)


def test_weights_and_result_are_saved_before_the_curve_is_drawn(tmp_path, monkeypatch):
    def no_plot(result, path):
        raise RuntimeError("drawing failed")
    monkeypatch.setattr(run, "plot_curve", no_plot)
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="drawing failed"):
        run.main(["--env", "spread", "--out", str(out), *TINY, "--env-steps", "8", "--checkpoint-every", "0"])
    assert json.loads((out / "result.json").read_text())["env_steps"] == 8
    assert set(torch.load(out / "actor.pt")) >= {"head.0.weight"}
    assert sorted(p.name for p in out.iterdir()) == ["actor.pt", "result.json"]  # no temporary file left


def test_result_json_is_written_after_the_weights(tmp_path, monkeypatch):
    """A run whose weights could not be saved leaves no result.json that says it is done."""
    def no_save(*args, **kwargs):
        raise OSError("disk full")
    monkeypatch.setattr(run.torch, "save", no_save)
    out = tmp_path / "run"
    with pytest.raises(OSError, match="disk full"):
        run.main(["--env", "spread", "--out", str(out), *TINY, "--env-steps", "8", "--checkpoint-every", "0"])
    assert list(out.iterdir()) == []


def test_a_missing_matplotlib_stops_the_run_at_once_naming_the_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError
    with pytest.raises(SystemExit) as exit_:
        run.main(["--env", "spread", "--out", str(tmp_path / "run"), "--env-steps", "100000000"])
    # A string exit code: Python prints it on stderr and exits with status 1.
    assert exit_.value.code == ("error: python -m marl_render.baselines (its curve.png) needs matplotlib, which is "
                                "not installed: pip install 'marl-render[plots]'")
    assert capsys.readouterr().err == ""  # nothing else on stderr before it
    assert not (tmp_path / "run").exists()


def test_max_minutes_stops_training_and_marks_the_run_truncated(tmp_path):
    out = tmp_path / "capped"
    assert run.main(["--env", "spread", "--out", str(out), *TINY, "--env-steps", "100000000", "--max-minutes",
                     "1e-9", "--checkpoint-every", "0"]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["truncated"] is True and result["updates"] == 1
    assert result["env_steps"] == 16  # the update's rollout, and the next one collected beside it
    assert result["budget"]["env_steps"] == 100_000_000 and result["budget"]["max_minutes"] == 1e-9


def test_help_runs_as_a_module(monkeypatch, capsys):
    assert run_module("marl_render.baselines", ["--help"], monkeypatch) == 0
    out = capsys.readouterr().out
    for option in ("--env-steps", "--updates", "--max-minutes", "--eval-set", "--checkpoint-every", "--obs"):
        assert option in out


def test_task_hyperparameters_apply_task_defaults_then_overrides():
    assert task_hyperparameters("spread") == Hyperparameters()
    cartpole = task_hyperparameters("cartpole", frames=None, lr=1e-3)
    assert cartpole.action_repeat > 1 and cartpole.frames > 1 and cartpole.lr == 1e-3
    with pytest.raises(TypeError, match="unknown hyperparameter"):
        task_hyperparameters("spread", learning_rate=1.0)


def test_frame_stack_keeps_the_last_frames_and_restarts_worlds():
    stack = FrameStack(3)
    first = torch.zeros(2, 1, 1)
    assert stack.reset(first).tolist() == [[[0, 0, 0]], [[0, 0, 0]]]
    stack.push(torch.ones(2, 1, 1))
    stack.push(torch.full((2, 1, 1), 2.0))
    assert stack.stack.tolist() == [[[0, 1, 2]], [[0, 1, 2]]]
    stack.restart(torch.full((2, 1, 1), 5.0), torch.tensor([False, True]))
    assert stack.stack.tolist() == [[[0, 1, 2]], [[5, 5, 5]]]


STUDY = ["--env-steps", "16", "--seeds", "0", "1", "--settings", "32px", "32px-msaa4", "--episodes", "2",
         "--jobs", "2", "--worlds", "2", "--rollout", "4", "--checkpoint-every", "0"]
# What a study finds in a run folder that is not a finished run (each is rerun): a result.json cut off
# mid-write, and one from a run stopped by a safety cap.
UNFINISHED = {"32px-seed0": '{"env": "spread", "evaluation": {"poli',
              "32px-seed1": json.dumps({"env": "spread", "truncated": True, "evaluation": {"policy": {"mean": 1.0}}})}


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """Two settings, two seeds, a tiny budget, into a folder where two runs left unfinished results (one
    study of four training processes serves the tests of the files, the report and the reruns)."""
    from marl_render.baselines import learning_accuracy

    root = tmp_path_factory.mktemp("study")
    out = root / "learning"
    for folder, text in UNFINISHED.items():
        (out / folder).mkdir(parents=True)
        (out / folder / "result.json").write_text(text)
    argv = [*STUDY, "--out", str(out)]
    assert learning_accuracy.main(argv) == 0
    return root, argv


def test_learning_accuracy_study_runs_and_reports(study):
    """Every run's files, the report's json, table and plot."""
    from marl_render.baselines import learning_accuracy

    root, argv = study
    out = root / "learning"
    for setting in ("32px", "32px-msaa4"):
        for seed in (0, 1):
            result = json.loads((out / f"{setting}-seed{seed}" / "result.json").read_text())
            assert result["seeds"]["train"] == seed and result["hyperparameters"]["worlds"] == 2
            assert result["env_steps"] == 16 and (out / f"{setting}-seed{seed}" / "actor.pt").is_file()
    msaa = json.loads((out / "32px-msaa4-seed0" / "result.json").read_text())
    assert msaa["env_options"] == {"multisamples": 4} and msaa["hyperparameters"]["resolution"] == 32
    summary = json.loads((root / "learning.json").read_text())
    assert summary["seeds"] == [0, 1] and summary["env_steps"] == 16
    assert set(summary["settings"]) == {"32px", "32px-msaa4"}
    for entry in summary["settings"].values():
        assert entry["seeds"] == 2 and [r["seed"] for r in entry["runs"]] == [0, 1]
        assert entry["env_steps_per_second_mean"] > 0
    text = (root / "learning.md").read_text()
    assert "| 32px-msaa4: MSAA 4 samples |" in text and "1.00x |" in text
    assert (root / "learning.png").stat().st_size > 10_000
    # A second call keeps the finished runs and only rewrites the report.
    before = (out / "32px-seed0" / "result.json").stat().st_mtime_ns
    assert learning_accuracy.main(argv) == 0
    assert (out / "32px-seed0" / "result.json").stat().st_mtime_ns == before


def test_env_and_train_options_reach_the_envs(tmp_path):
    out = tmp_path / "push"
    assert run.main(["--env", "push", "--out", str(out), *TINY, "--env-steps", "8", "--train-option", "shaping=0.5",
                     "--env-option", "max_steps=20", "--levels", "5", "--eval-levels", "published",
                     "--appearance", "train"]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["env_options"] == {"max_steps": 20, "appearance": "train"}
    assert result["train_options"] == {"shaping": 0.5, "levels": 5} and result["evaluation_levels"] == "published"
    assert "--train-option shaping=0.5" in result["command"] and "--levels 5" in result["command"]


@pytest.mark.parametrize(("args", "message"), [
    (["--train-option", "shaping"], "expected KEY=VALUE"),
    (["--env-option", "max_steps=twenty"], "must be a Python literal"),
    (["--env-option", "resolution=16"], "set it with the learner's own option"),
    (["--train-option", "levels=5"], "set it with the learner's own option --levels / --eval-levels"),
    (["--levels", "0"], "expected a count n >= 1 or one of ['train', 'test', 'published']"),
    (["--eval-levels", "easy"], "expected a count n >= 1"),
    (["--appearance", "test"], "invalid choice"),
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


def test_learning_accuracy_refuses_duplicate_seeds(tmp_path, capsys):
    from marl_render.baselines import learning_accuracy

    with pytest.raises(SystemExit):
        learning_accuracy.main(["--out", str(tmp_path / "runs"), "--seeds", "0", "1", "0"])
    assert "--seeds must be distinct, got 0 1 0" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


def test_learning_accuracy_reruns_a_truncated_or_partial_result(study):
    """A result.json cut off mid-write, or from a run stopped by a safety cap, is not a finished run."""
    root, _ = study
    for folder in UNFINISHED:
        result = json.loads((root / "learning" / folder / "result.json").read_text())
        assert result["truncated"] is False and result["env_steps"] == 16
        assert result["seeds"]["train"] == int(folder[-1])


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupting_learning_accuracy_stops_its_training_run(tmp_path, sig):
    """The study runs each training in its own process group and ends it however the study ends."""
    out = tmp_path / "learning"
    child = None
    # A shell starts background jobs (`make test &`, CI scripts) with SIGINT ignored, and children inherit
    # that: the study is started with Ctrl-C's usual handler, as from a terminal, whatever ran the suite.
    launcher = ("import runpy, signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
                "runpy.run_module('marl_render.baselines.learning_accuracy', run_name='__main__', alter_sys=True)")
    study = subprocess.Popen([sys.executable, "-c", launcher, "--env-steps",
                              "100000000", "--seeds", "0", "--settings", "32px", "--episodes", "2", "--out", str(out),
                              "--worlds", "2", "--rollout", "4", "--checkpoint-every", "0"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        line = ""
        while "(pid " not in line:
            line = study.stdout.readline()
            assert line, "the study ended before starting its run"
        child = int(line.split("(pid ")[1].split(")")[0])
        deadline = time.monotonic() + 120
        while "update 1/" not in (out / "32px-seed0" / "run.log").read_text():  # the child is training
            assert time.monotonic() < deadline and study.poll() is None
            time.sleep(0.2)
        study.send_signal(sig)
        study.wait(60)
    finally:
        if study.poll() is None:  # the study did not stop: kill it, and its run's group, which it would have
            study.kill()
            if child is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(child, signal.SIGKILL)
    assert study.returncode != 0
    deadline = time.monotonic() + 30
    while True:
        try:
            os.kill(child, 0)  # the child's group was stopped and reaped by the study
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline, f"training run {child} outlived the study"
        time.sleep(0.2)
    assert not (out / "32px-seed0" / "result.json").exists()


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_ppo_loss_is_torchrl_clip_ppo_loss(precision):
    """The learner's plain-torch loss gives TorchRL's ClipPPOLoss values and gradients (same networks,
    a minibatch with masked actions and ratios on both sides of the clip range)."""
    from tensordict import TensorDict
    from tensordict.nn import TensorDictModule
    from torchrl.modules import ProbabilisticActor
    from torchrl.objectives import ClipPPOLoss

    from marl_render.baselines.networks import Actor, CentralCritic
    from marl_render.baselines.ppo import ppo_loss

    torch.manual_seed(0)
    actor, critic = Actor("pixels", (8, 8, 3), 3, 5, 16, precision=precision), CentralCritic(12, 3, 16)
    n, g = 64, torch.Generator().manual_seed(1)
    mask = torch.rand(n, 5, generator=g) < 0.7
    mask[:, 0] = True
    batch = dict(observation=actor.prepare(torch.randint(0, 256, (n, 8, 8, 3), dtype=torch.uint8, generator=g)),
                 agent=torch.eye(3)[torch.randint(0, 3, (n,), generator=g)], mask=mask,
                 global_state=torch.randn(n, 12, generator=g))
    with torch.no_grad():
        log_probs = actor(batch["observation"], batch["agent"], mask).log_softmax(-1)
    action = torch.multinomial(log_probs.exp(), 1, generator=g).squeeze(-1)
    behaviour = log_probs.gather(-1, action[:, None]).squeeze(-1) + 0.3 * torch.randn(n, generator=g)
    batch.update(action=action, sample_log_prob=behaviour, advantage=torch.randn(n, generator=g),
                 value_target=torch.randn(n, generator=g))
    hp = Hyperparameters()
    loss = ClipPPOLoss(
        ProbabilisticActor(TensorDictModule(actor, in_keys=["observation", "agent", "mask"], out_keys=["logits"]),
                           in_keys=["logits"], out_keys=["action"], distribution_class=torch.distributions.Categorical,
                           return_log_prob=True, log_prob_key="sample_log_prob"),
        TensorDictModule(critic, in_keys=["global_state", "agent"], out_keys=["state_value"]),
        clip_epsilon=hp.clip, entropy_coeff=hp.entropy, critic_coeff=hp.critic_coef, loss_critic_type="l2",
        normalize_advantage=True)
    loss.set_keys(sample_log_prob="sample_log_prob")
    theirs = loss(TensorDict({**batch, "advantage": batch["advantage"][:, None],
                              "value_target": batch["value_target"][:, None]}, batch_size=[n]))
    assert 0.1 < float(theirs["clip_fraction"]) < 0.9  # the clip is exercised
    ours = ppo_loss(actor, critic, batch, hp)
    parameters = [*actor.parameters(), *critic.parameters()]
    for key in ("loss_objective", "loss_entropy", "loss_critic", "entropy", "explained_variance"):
        assert float(ours[key]) == pytest.approx(float(theirs[key]), rel=1e-5, abs=1e-7), key
    gradients = [torch.autograd.grad(out["loss_objective"] + out["loss_critic"] + out["loss_entropy"], parameters)
                 for out in (ours, theirs)]
    for mine, reference in zip(*gradients, strict=True):
        torch.testing.assert_close(mine, reference, rtol=1e-4, atol=1e-6)


def test_generalized_advantage_is_torchrl_gae():
    """The trainer's plain-torch GAE equals TorchRL's generalized_advantage_estimate bit for bit on a
    time-major [T, W, At] rollout with done (truncated) steps, terminated steps and both at once."""
    from torchrl.objectives.value.functional import generalized_advantage_estimate

    from marl_render.baselines.advantage import generalized_advantage

    g = torch.Generator().manual_seed(0)
    T, W, At = 37, 5, 3
    value, next_value, reward = (torch.randn(T, W, At, generator=g) for _ in range(3))
    terminated = torch.rand(T, W, At, generator=g) < 0.1
    done = terminated | (torch.rand(T, W, At, generator=g) < 0.1)  # a truncation is done but not terminated
    assert bool((done & ~terminated).any()) and bool(terminated.any())
    ours = generalized_advantage(0.97, 0.9, value, next_value, reward, done, terminated)

    def by_time(x):  # [T, W, At] -> [W * At, T, 1]: TorchRL's layout
        return x.permute(1, 2, 0).reshape(W * At, T, 1)

    theirs = generalized_advantage_estimate(0.97, 0.9, *map(by_time, (value, next_value, reward, done, terminated)))
    for mine, reference in zip(ours, theirs, strict=True):
        assert torch.equal(by_time(mine), reference)
    with pytest.raises(ValueError, match=r"one shape \[T, \.\.\.\], got .*'done': \(37, 5\)"):
        generalized_advantage(0.97, 0.9, value, next_value, reward, done[:, :, 0], terminated)


def test_the_training_guide_python_block_runs(tmp_path, monkeypatch, capsys):
    """docs/training.md's Python example, as written but for a budget that runs in seconds."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "training.md").read_text()
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    for written, small in (('task_hyperparameters("spread", worlds=16)',
                            'task_hyperparameters("spread", worlds=2, rollout=4, resolution=16)'),
                           ("env_steps=100_000", "env_steps=24"), ("checkpoint_every=25_000", "checkpoint_every=8"),
                           ("episodes=32", "episodes=2")):
        assert written in code, f"docs/training.md no longer contains {written!r}: update this test"
        code = code.replace(written, small)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "docs/training.md", "exec"), {"__name__": "__main__"})  # as a script runs it
    printed = capsys.readouterr().out.splitlines()
    steps, updates, seconds, checkpoint = printed[0].split()
    assert (steps, updates) == ("24", "3") and float(seconds) > 0 and math.isfinite(float(checkpoint))
    assert math.isfinite(float(printed[1]))


def test_throughput_runs_variants_in_turn_and_reads_their_results(tmp_path, capsys):
    from marl_render.baselines import throughput

    tiny = "--env spread --updates 1 --worlds 2 --resolution 12 --rollout 4"
    assert throughput.main(["--rounds", "1", "--out", str(tmp_path), "--variant", f"plain=::{tiny}",
                            "--variant", f"bf16=::{tiny} --precision bfloat16"]) == 0
    summary = json.loads((tmp_path / "throughput.json").read_text())
    assert summary == json.loads(capsys.readouterr().out)
    assert list(summary) == ["plain", "bf16"] and summary["plain"]["ratio_to_first"] == 1.0
    for label in ("plain", "bf16"):
        row = summary[label]["rounds"][0]
        assert row["env_steps"] == 8 and row["env_steps_per_second"] > 0 and 0 < row["env_share"] < 1
    assert json.loads((tmp_path / "bf16-round0" / "result.json").read_text())["hyperparameters"]["precision"] == \
        "bfloat16"
    with pytest.raises(SystemExit):
        throughput.main(["--out", str(tmp_path), "--variant", "no-separator"])


@pytest.mark.parametrize("channels, resolution", [(3, 32), (6, 48), (1, 12), (3, 30)])
def test_the_patch_encoder_first_layer_is_a_stride_4_convolution(channels, resolution):
    """prepare() lays out 4x4 patches (bytes moved as words) and the first layer scales by 1/255: the
    same function as Conv2d(C, 16, 4, stride=4) on pixels in [0, 1], its weights laid out alike."""
    from torch import nn

    from marl_render.baselines.networks import PixelEncoder

    torch.manual_seed(0)
    encoder = PixelEncoder(channels, resolution, "patch")
    pixels = torch.randint(0, 256, (5, resolution, resolution, channels), dtype=torch.uint8)
    conv = nn.Conv2d(channels, 16, 4, stride=4)
    with torch.no_grad():
        conv.weight.copy_(encoder.patch.weight.reshape(16, 4, 4, channels).permute(0, 3, 1, 2))
        conv.bias.copy_(encoder.patch.bias)
        reference = conv(pixels.permute(0, 3, 1, 2).float() / 255).permute(0, 2, 3, 1)
        patches = encoder.prepare(pixels, torch.float32)
        ours = nn.functional.linear(patches, encoder.patch.weight / 255.0, encoder.patch.bias)
    assert patches.shape == (5, resolution // 4, resolution // 4, 16 * channels)
    assert patches[1, 2, 0, :3 * channels].tolist() == pixels[1, 8, 0:3].flatten().float().tolist()
    torch.testing.assert_close(ours, reference, rtol=0, atol=1e-6)
    assert encoder(encoder.prepare(pixels, torch.float32)).shape == (5, encoder.features)
    with pytest.raises(ValueError, match="at least 12 pixels per side, got 11"):
        PixelEncoder(channels, 11, "patch")


def test_the_actor_starts_orthogonal():
    """init="orthogonal" (the default): the encoder's and the hidden layers' weights are orthogonal with
    ReLU's gain sqrt(2) and zero biases, the output layer near uniform; "torch" keeps torch's draws."""
    from marl_render.baselines.networks import Actor

    torch.manual_seed(0)
    actor = Actor("pixels", (16, 16, 3), 3, 5, 32, encoder="patch", init="orthogonal")
    for layer in (actor.encoder.patch, actor.encoder.conv, actor.head[0], actor.head[2]):
        rows = layer.weight.detach().flatten(1)  # [out, in], out <= in: orthogonal rows of norm sqrt(2)
        torch.testing.assert_close(rows @ rows.T, 2 * torch.eye(len(rows)), rtol=0, atol=1e-5)
        assert layer.bias.abs().max() == 0
    assert actor.head[4].weight.abs().max() < 0.01 and actor.head[4].bias.abs().max() == 0
    assert Hyperparameters().init == "orthogonal"
    torch.manual_seed(0)
    bound = 1 / math.sqrt(48)  # torch's Linear draws uniform in +-1/sqrt(fan in)
    patch = Actor("pixels", (16, 16, 3), 3, 5, 32, encoder="patch", init="torch").encoder.patch
    assert 0 < patch.bias.abs().max() <= bound and patch.weight.abs().max() <= bound
    with pytest.raises(ValueError, match="init must be one of \\['orthogonal', 'torch'\\], got 'xavier'"):
        Actor("pixels", (16, 16, 3), 3, 5, 32, init="xavier")
