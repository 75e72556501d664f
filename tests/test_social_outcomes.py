"""The evaluation CLI's rows carry the social outcomes of mixed-motive tasks (envs/episodes.py)."""
from __future__ import annotations

import torch

from marl_render.envs import evaluation as reference
from marl_render.envs.episodes import EpisodeOutcomes
from marl_render.evaluate import evaluate


class _Spec:
    info = {"efficiency": torch.float32, "peace": torch.float32, "collected": torch.int64}


class _Env:
    spec, num_worlds = _Spec(), 3


def test_each_world_keeps_the_values_of_the_step_its_episode_ended():
    outcomes = EpisodeOutcomes(_Env())
    running = torch.ones(3, dtype=torch.bool)
    steps = (([False, True, False], [1.0, 2.0, 3.0]), ([True, True, False], [4.0, 5.0, 6.0]),
             ([True, True, True], [7.0, 8.0, 9.0]))
    for done, value in steps:
        info = {"done_worlds": torch.tensor(done), "efficiency": torch.tensor(value), "peace": torch.tensor(value) * 10}
        outcomes.add(info, running)
        running &= ~info["done_worlds"]
    # world 1 ended at step 1 (2.0), world 0 at step 2 (4.0), world 2 at step 3 (9.0)
    assert outcomes.fields() == {"efficiency_mean": 5.0, "peace_mean": 50.0}


def test_the_evaluation_rows_of_a_mixed_motive_task_carry_them():
    row, = evaluate("heuristic", ["commons/resident_with_greedy"], episodes=2, resolution=8, max_steps=5)
    assert {"efficiency_mean", "equality_mean", "sustainability_mean", "peace_mean"} <= set(row)
    assert 0.0 <= row["equality_mean"] <= 1.0 and row["peace_mean"] <= 5 * 5


def test_the_reference_evaluation_of_a_mixed_motive_task_reports_them_and_of_others_not():
    """python -m marl_render.envs.evaluation (docs/reference_returns.json, the cards' social tables): the
    episodes' mean social outcomes of a mixed-motive task; efficiency is the collective return, so the
    per-agent mean return times the agents (every agent evaluated in clean_up)."""
    row = reference.evaluate("clean_up", reference.heuristic_policy, episodes=2, resolution=8, max_steps=12,
                             num_agents=3, episode_end=False)
    assert set(row) >= {"efficiency_mean", "equality_mean", "sustainability_mean", "peace_mean"}
    assert abs(row["efficiency_mean"] - 3 * row["mean"]) < 1e-9
    assert row["peace_mean"] == 3 * 12  # nobody zaps: every agent-step in play
    assert not {"efficiency_mean", "peace_mean"} & set(reference.evaluate("spread", reference.random_policy,
                                                                          episodes=2, resolution=8, max_steps=3))
