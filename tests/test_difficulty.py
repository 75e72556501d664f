"""Difficulty presets (Scenario.difficulties): difficulty="easy" | "medium" | "hard" sets a task's
keywords, explicit keywords win, "medium" is the defaults, and bad names are refused by name."""
from __future__ import annotations

import dataclasses

import pytest

from marl_render.envs import env_class, list_envs, make_env, make_vec_env
from marl_render.envs.registry import split_kwargs

TASKS = ("capture_flag", "cartpole", "clean_up", "commons", "cooking", "coop_mining", "forage", "matrix", "push",
         "rooms", "speaker_listener", "spread", "tag", "territory")


@pytest.mark.parametrize("name", TASKS)
def test_every_task_has_three_presets_and_medium_is_the_default(name):
    scenario = env_class(name)
    assert sorted(scenario.difficulties) == ["easy", "hard", "medium"] and scenario.difficulties["medium"] == {}
    default = split_kwargs(scenario, {})
    assert split_kwargs(scenario, {"difficulty": "medium"}) == default
    for level in ("easy", "hard"):
        options, params = split_kwargs(scenario, {"difficulty": level})
        assert (options, params) != default
        for key, value in scenario.difficulties[level].items():
            assert getattr(params if key in {f.name for f in dataclasses.fields(params)} else options, key) == value


def test_explicit_keywords_override_the_preset_and_front_ends_take_it():
    options, params = split_kwargs(env_class("forage"), {"difficulty": "hard", "num_items": 5})
    assert params.num_items == 5 and params.respawn_delay == 30
    with make_env("rooms", num_worlds=1, resolution=8, difficulty="easy") as env:
        assert env.scenario.params.open_wall == 0.6
    envs = make_vec_env("spread", num_worlds=1, resolution=8, difficulty="hard")
    assert envs.core.scenario.num_landmarks == 6
    envs.close()


def test_bad_difficulties_are_refused_by_name():
    with pytest.raises(ValueError, match=r"must be one of \['easy', 'hard', 'medium'\] \(or None\), got 'brutal'"):
        make_env("rooms", difficulty="brutal")
    with pytest.raises(ValueError, match="difficulty must be one of"):
        make_env("rooms", difficulty=2)
    plain = type("Plain", (env_class("spread"),), {"difficulties": {}})
    with pytest.raises(ValueError, match="Plain has no difficulty presets"):
        split_kwargs(plain, {"difficulty": "easy"})
    assert set(TASKS) <= set(list_envs())
