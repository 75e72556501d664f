"""python -m marl_render.evaluate and its functions: a policy plays only its own task, bad arguments
are refused naming the option before any episode is played, and the output is clean."""
from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import pytest
import torch

from marl_render import evaluate as evaluation
from marl_render.baselines.networks import Actor
from marl_render.envs import env_class, make_env
from marl_render.policies import load_policy
from marl_render.populations import pages, scores


def saved_run(folder: Path, task: str | None, actions: int = 5, **extra) -> str:
    """A run folder as python -m marl_render.baselines writes it (result.json + actor.pt); `task` None:
    a result.json that does not record it."""
    folder.mkdir(parents=True)
    hp = {"resolution": 16, "grayscale": False, "frames": 1, "action_repeat": 1, "hidden": 16, "encoder": "conv",
          "precision": "float32"}
    torch.manual_seed(0)
    torch.save(Actor("pixels", (16, 16, 3), 4, actions, 16).state_dict(), folder / "actor.pt")
    record = {"obs": "pixels", "hyperparameters": hp, "seeds": {"train": 0}, **extra}
    if task is not None:
        record["env"] = task
    (folder / "result.json").write_text(json.dumps(record))
    return str(folder)


@pytest.fixture
def nothing_played(monkeypatch):
    """Any episode played fails the test: the errors below must come before the work."""
    def play(env, policy):
        raise AssertionError("an episode was played before the error")
    monkeypatch.setattr(scores, "play", play)  # what cross-play and the held-out scores call


def refused(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exit_:
        evaluation.main(argv)
    assert exit_.value.code == 2
    return capsys.readouterr().err


# ---------------------------------------------------------------------- a policy plays its own task only
@pytest.mark.parametrize("trained, scenario", [("rooms", "speaker_listener/deaf_listener"),
                                               ("spread", "forage/one_among_noisy"),
                                               ("push", "tag/predators_vs_wanderers")])
def test_a_run_of_another_task_is_refused_naming_both(tmp_path, capsys, nothing_played, trained, scenario):
    run = saved_run(tmp_path / "run", trained)
    task = scenario.split("/")[0]
    err = refused(["--policy", run, "--scenario", scenario, "--episodes", "2"], capsys)
    assert f"was trained on '{trained}' (5 actions); it cannot play '{task}'" in err
    with pytest.raises(ValueError, match=f"trained on '{trained}'.*cannot play '{task}'"):
        evaluation.evaluate(run, [scenario], episodes=2)


def test_an_actor_whose_action_count_is_not_the_envs_is_refused_before_it_acts(tmp_path):
    policy = load_policy(saved_run(tmp_path / "run", None, actions=3))  # an old run: no task recorded
    assert policy.task is None and policy.num_actions == 3
    with make_env("tag", num_worlds=1, resolution=16) as env:
        with pytest.raises(ValueError, match=r"trained on its run's task with 3 discrete actions; env 'tag' has "
                                             rf"{env.num_actions} actions"):
            policy.check_env(env)
        other = load_policy(saved_run(tmp_path / "push", "push", actions=env.num_actions))
        with pytest.raises(ValueError, match=r"trained on 'push'; it cannot play env 'tag'"):
            other.check_env(env)


def test_a_run_that_named_its_task_as_module_class_plays_that_task(tmp_path):
    tag = env_class("tag")
    policy = load_policy(saved_run(tmp_path / "run", f"{tag.__module__}:{tag.__qualname__}"))
    policy.check_task("tag")  # the same class, by another name: accepted
    with make_env("tag", num_worlds=1, resolution=16) as env:
        policy.check_env(env)
    with pytest.raises(ValueError, match=r"cannot play 'push'"):
        policy.check_task("push")


def test_cross_play_refuses_a_run_of_another_task_in_the_roster(tmp_path, capsys, nothing_played):
    run = saved_run(tmp_path / "push_run", "push")
    err = refused(["--crossplay", "tag", "--roster", "random", run], capsys)
    assert f"--roster '{run}': policy '{run}' was trained on 'push'" in err and "cannot play 'tag'" in err


# ---------------------------------------------------------------------- --roster: errors before the matrix
def broken_folder(tmp_path: Path, content: str) -> str:
    folder = tmp_path / "broken"
    saved_run(folder, "tag")
    (folder / "result.json").write_text(content)
    return str(folder)


@pytest.mark.parametrize("content, words", [
    ("[1, 2]", r"result.json must hold a run's record \(a JSON object\), got a list"),
    ("{not json", r"result.json is not a readable result.json"),
    (json.dumps({"env": "tag", "snapshot": {"id": 3}, "seeds": {"train": 0}}),
     r"snapshot must record its id and env_steps \(ints\)"),
    (json.dumps({"env": "tag", "seeds": {"train": 0}}), r"lacks the run's settings"),
])
def test_a_broken_roster_folder_is_one_clean_error_naming_roster(tmp_path, capsys, nothing_played, content, words):
    folder = broken_folder(tmp_path, content)
    err = refused(["--crossplay", "tag", "--roster", "random", folder], capsys)
    assert f"error: --roster '{folder}': " in err and "Traceback" not in err
    assert re.search(words, err)


def test_a_roster_of_one_or_with_an_entry_twice_is_refused_before_the_matrix(tmp_path, capsys, nothing_played):
    assert "--roster must name at least 2 policies" in refused(["--crossplay", "tag", "--roster", "random"], capsys)
    err = refused(["--crossplay", "tag", "--roster", "random", "heuristic", "random"], capsys)
    assert "--roster names 'random' twice" in err
    run = saved_run(tmp_path / "run", "tag")
    err = refused(["--crossplay", "tag", "--roster", run, "random", run + os.sep], capsys)
    assert "--roster names" in err and "twice" in err
    with pytest.raises(ValueError, match=r"roster must hold at least 2 policies"):
        evaluation.crossplay("tag", {"random": "random"})


# ---------------------------------------------------------------------- --out, --seed, --torch-threads
def test_an_out_that_cannot_take_the_files_is_refused_before_the_work(tmp_path, capsys, nothing_played):
    (tmp_path / "file").write_text("")
    for argv in (["--policy", "random", "--scenario", "spread", "--episodes", "2"],
                 ["--crossplay", "tag", "--roster", "random", "heuristic"]):
        err = refused([*argv, "--out", str(tmp_path / "file" / "x")], capsys)
        assert f"--out '{tmp_path / 'file' / 'x'}': {tmp_path / 'file'} is a file, not a folder" in err
        err = refused([*argv, "--out", str(tmp_path / "dir") + "/"], capsys)
        assert "names a folder, and --out is the prefix of the files written" in err
    assert not (tmp_path / "dir").exists()


def test_seeds_beyond_the_envs_range_are_refused_naming_seed(capsys, nothing_played):
    with pytest.raises(ValueError, match=r"seed must be an int in \[0, 2\*\*63\), got 18446744073709551616"):
        evaluation.evaluate("random", ["spread/two_with_nearest"], episodes=2, seed=2 ** 64)
    with pytest.raises(ValueError, match=r"seed must be an int in \[0, 2\*\*63\)"):
        evaluation.crossplay("tag", {"random": "random", "heuristic": "heuristic"}, seed=-1)
    err = refused(["--policy", "random", "--scenario", "spread", "--seed", str(2 ** 64)], capsys)
    assert "--seed must be an int in [0, 2**63), got 18446744073709551616" in err


def test_scenarios_given_as_one_string_are_refused_not_split_into_characters(nothing_played):
    with pytest.raises(TypeError, match=r"scenarios must be a list of held-out scenario names, got the str "
                                        r"'spread/two_with_nearest': pass \['spread/two_with_nearest'\]"):
        evaluation.evaluate("random", "spread/two_with_nearest", episodes=2)


@pytest.mark.parametrize("threads", ["0", "5000"])
def test_torch_threads_are_bounded(capsys, threads):
    err = refused(["--list", "--torch-threads", threads], capsys)
    assert f"--torch-threads must be in [1, 1024], got {threads}" in err


# ---------------------------------------------------------------------- output
def test_a_closed_pipe_ends_the_listing_quietly(monkeypatch, capsys):
    read, write = os.pipe()
    os.close(read)  # `--list | head` once head has gone
    stream = os.fdopen(write, "w", buffering=1)
    monkeypatch.setattr(sys, "stdout", stream)
    try:
        assert evaluation.main(["--list"]) == 1
        stream.write("x" * 100_000)  # the pipe's end now writes nowhere, without a second error
        stream.flush()
    finally:
        monkeypatch.undo()
        stream.close()
    assert capsys.readouterr().err == ""


def test_scores_that_round_to_zero_print_without_a_minus_sign():
    assert [pages._fmt(v) for v in (-0.001, -0.0, 0.004, -0.006, None, float("nan"))] == [
        "0.00", "0.00", "0.00", "-0.01", "n/a", "n/a"]
    assert pages._fmt(-0.4, 0) == "0" and pages._fmt(-0.6, 0) == "-1"
