"""The trainer's workflow options: several seeds in one command with the across-seed summary,
TensorBoard logging, the training levels scored beside --eval-levels, and a progress line that
counts only the env steps learned from."""
from __future__ import annotations

import json
import re
import sys

import pytest

from marl_render.baselines import run as trainer
from marl_render.envs.evaluation import evaluate
from marl_render.policies import load_policy

TINY = ["--env", "forage", "--updates", "2", "--worlds", "2", "--rollout", "4", "--resolution", "16", "--hidden", "8",
        "--episodes", "2", "--checkpoint-every", "8", "--checkpoint-episodes", "2", "--env-option", "max_steps=10"]


def test_seeds_tensorboard_and_the_training_levels_in_one_command(tmp_path, capsys, monkeypatch):
    pytest.importorskip("tensorboard")  # the tensorboard extra, which make installs
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    monkeypatch.setattr(trainer, "PROGRESS_SECONDS", 0.0)  # a progress line after every update
    out, logs = tmp_path / "runs", tmp_path / "tb"
    assert trainer.main([*TINY, "--seeds", "0", "1", "--levels", "3", "--appearance", "train", "--eval-levels",
                         "published", "--out", str(out), "--tensorboard", str(logs)]) == 0
    printed = capsys.readouterr().out
    # With --overlap (forage's default) the second rollout is collected during the first update: it
    # was counted at update 1, and both updates showed 16 env steps.
    assert re.findall(r"update (\d)/2, (\d+) env steps", printed) == [("1", "8"), ("2", "16")] * 2
    assert "development set" not in printed and "levels 'published', env seed 1000" in printed
    results = [json.loads((out / f"seed{seed}" / "result.json").read_text()) for seed in (0, 1)]
    assert [r["seeds"]["train"] for r in results] == [0, 1]
    assert results[1]["command"].endswith(f"--seed 1 --out {out / 'seed1'} --tensorboard {logs / 'seed1'}")
    assert "--seeds" not in results[1]["command"]
    summary = json.loads((out / "seeds.json").read_text())
    assert summary["seeds"] == [0, 1]
    assert summary["returns"] == [r["evaluation"]["policy"]["mean"] for r in results]
    assert "forage from pixels: 2 seeds (levels 'published', env seed 1000)" in printed
    # the training levels scored beside the test levels, as load_policy's policy plays them
    own = results[0]["evaluation_training_levels"]
    assert own["levels"] == 3
    replay = evaluate("forage", load_policy(str(out / "seed0")), episodes=2, seed=1000, resolution=16, levels=3,
                      appearance="train", max_steps=10)
    assert own["policy"]["per_episode"] == replay["per_episode"]
    assert {"random", "heuristic"} <= set(own)
    events = EventAccumulator(str(logs / "seed0"))
    events.Reload()
    assert [s.step for s in events.Scalars("train/entropy")] == [8, 16]
    assert [s.value for s in events.Scalars("evaluation/policy")] == pytest.approx([results[0]["evaluation"]["policy"]
                                                                                    ["mean"]])
    assert not list(logs.glob("events*"))  # every seed logs into its own folder


@pytest.mark.parametrize("argv, message", [
    (["--seed", "1", "--seeds", "2"], "--seed and --seeds exclude each other"),
    (["--seeds", "1", "2", "1"], "--seeds must name each seed once, got [1]"),
])
def test_seed_options_are_checked_before_any_work(argv, message, capsys, tmp_path):
    with pytest.raises(SystemExit) as exit:
        trainer.main([*TINY, *argv, "--out", str(tmp_path / "x")])
    assert exit.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_tensorboard_without_its_extra_fails_in_one_line_before_training(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "tensorboard", None)  # import tensorboard raises ModuleNotFoundError
    with pytest.raises(SystemExit) as exit:
        trainer.main([*TINY, "--out", str(tmp_path / "x"), "--tensorboard", str(tmp_path / "tb")])
    assert "pip install 'marl-render[tensorboard]'" in str(exit.value.code)
    assert not (tmp_path / "x").exists()


def test_seed_command_reproduces_one_seed_of_a_seeds_run():
    argv = ["--env", "tag", "--seeds", "0", "1", "--out", "o", "--tensorboard=t", "--updates", "3"]
    assert trainer.seed_command(argv, 1, "o/seed1", "t/seed1") == [
        "--env", "tag", "--updates", "3", "--seed", "1", "--out", "o/seed1", "--tensorboard", "t/seed1"]


def test_the_published_self_play_commands_give_the_hyperparameters_their_runs_trained_with():
    """training.md's commands of docs/selfplay/*: parsed, the very hyperparameters of each run's
    result.json, and torch's initial weights (the runs predate the init option, whose default is now
    orthogonal: without --init torch they would not reproduce)."""
    import dataclasses
    import shlex
    from pathlib import Path

    from marl_render.baselines.settings import FIELDS, task_hyperparameters

    root = Path(__file__).resolve().parent.parent
    lines = [line for line in (root / "docs" / "training.md").read_text().splitlines()
             if line.startswith("python -m marl_render.baselines ") and "--out docs/selfplay/" in line]
    assert len(lines) == 3
    for line in lines:
        argv = shlex.split(line)[3:]
        args = trainer.parse_args(argv)
        hp = dataclasses.asdict(task_hyperparameters(args.env, **{name: getattr(args, name) for name in FIELDS}))
        recorded = json.loads((root / args.out / "result.json").read_text())
        assert recorded["command"].split(" --out ")[0] in line.replace(" --init torch", "")
        trained = {"init": "torch", **recorded["hyperparameters"]}  # no init recorded: torch's, the only one then
        assert hp == trained, line
