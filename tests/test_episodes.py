"""Random episode ends and the social outcome metrics (envs/episodes.py)."""
from __future__ import annotations

import pytest
import torch

from marl_render.envs import env_class, make_env
from marl_render.envs.episodes import EpisodeBook, EpisodeEnd, describe_end, ends_of, social_outcomes


# ----------------------------------------------------------------------------- random ends
def test_episode_end_is_checked():
    with pytest.raises(ValueError, match="min_steps must be an int in"):
        EpisodeEnd(0, 5, 0.5)
    with pytest.raises(ValueError, match="interval must be an int in"):
        EpisodeEnd(5, 2.5, 0.5)
    with pytest.raises(ValueError, match=r"probability must be a number in \(0, 1\], got 0"):
        EpisodeEnd(5, 5, 0)
    with pytest.raises(TypeError, match="episode_end must be None"):
        make_env("spread", num_worlds=1, resolution=8, episode_end="random")


def test_ends_are_the_minimum_plus_whole_intervals_capped_at_max_steps():
    """Inverse transform by hand: K = floor(log(1 - u) / log(1 - p)) failures, p = 0.5:
    u = 0.4 -> 0.74 -> 0; u = 0.6 -> 1.32 -> 1; u = 0.8 -> 2.32 -> 2."""
    uniform = torch.tensor([0.0, 0.4, 0.6, 0.8], dtype=torch.float64)
    assert ends_of(uniform, EpisodeEnd(10, 5, 0.5), 100).tolist() == [10, 10, 15, 20]
    assert ends_of(uniform, EpisodeEnd(10, 5, 0.5), 18).tolist() == [10, 10, 15, 18]
    assert ends_of(uniform, EpisodeEnd(10, 5, 1.0), 100).tolist() == [10] * 4


def test_defaults_on_for_mixed_motive_tasks_off_elsewhere():
    assert env_class("commons").mixed_motive and env_class("matrix").mixed_motive
    assert not env_class("spread").mixed_motive
    assert describe_end(env_class("spread")) == "fixed: truncated after max_steps=100"
    assert env_class("commons").episode_end_description() == (
        "random (Melting Pot's): at least 150 steps, then it ends with probability 0.25 at that step and every 15 "
        "steps after it, at max_steps=300 at the latest")
    with make_env("spread", num_worlds=2, resolution=8) as env:
        assert env.episodes.end is None and "episode_end" not in env.spec.info
    with make_env("commons", num_worlds=2, resolution=8, episode_end=False) as env:
        assert env.episodes.end is None
    with make_env("spread", num_worlds=2, resolution=8, episode_end=(4, 2, 0.5)) as env:
        assert env.episodes.end == EpisodeEnd(4, 2, 0.5)


def test_worlds_truncate_at_their_drawn_end_and_the_state_round_trips():
    with make_env("spread", num_worlds=8, resolution=8, seed=5, episode_end=(2, 3, 0.5), max_steps=30) as env:
        env.reset()
        ends = env.get_state()["episode_end"]
        assert ends.dtype == torch.int64 and bool(((ends - 2) % 3 == 0).all()) and bool((ends <= 30).all())
        assert len(set(ends.tolist())) > 1  # 8 worlds, not all alike
        saved = env.get_state()
        for step in range(1, int(ends.max()) + 1):
            _, _, _, truncated, _ = env.step(env.random_actions())
            assert torch.equal(truncated.all(1), ends <= step) and torch.equal(env.episode_over(), ends <= step)
        bad = {**saved, "episode_end": torch.zeros_like(ends)}
        with pytest.raises(ValueError, match=r"state\['episode_end'\] must be in \[1, max_steps=30\]"):
            env.set_state(bad)
        env.set_state(saved)
        assert torch.equal(env.get_state()["episode_end"], ends)


def test_the_end_is_reproducible_and_with_levels_a_function_of_the_level_alone():
    def ends(worlds, slots, history, seed):
        with make_env("spread", num_worlds=worlds, resolution=8, seed=seed, levels="train",
                      episode_end=(2, 3, 0.3)) as env:
            env.reset()
            for _ in range(history):
                env.step(env.random_actions())
            mask = torch.zeros(worlds, dtype=torch.bool)
            mask[list(slots)] = True
            env.reset_to_level(mask, torch.full((worlds,), 77))
            return env.get_state()["episode_end"][list(slots)].tolist()
    first = ends(1, (0,), 0, 0)
    assert ends(8, (2, 5), 3, 1) == first * 2
    levels = make_env("spread", num_worlds=64, resolution=8, seed=0, levels="train", episode_end=(2, 3, 0.3))
    levels.reset()
    assert len(set(levels.get_state()["episode_end"].tolist())) > 3  # different levels, different ends
    levels.close()
    with make_env("spread", num_worlds=4, resolution=8, seed=9, episode_end=(2, 3, 0.3)) as a, \
            make_env("spread", num_worlds=4, resolution=8, seed=9, episode_end=(2, 3, 0.3)) as b:
        a.reset()
        b.reset()
        assert torch.equal(a.get_state()["episode_end"], b.get_state()["episode_end"])


# ----------------------------------------------------------------------------- social outcomes
def test_social_outcomes_of_a_hand_worked_episode():
    """3 agents, 4 steps. Rewards: t1 (1, 0, 0), t2 0, t3 (1, 0, 0), t4 (0, 2, 0); tagged out after
    t1 and t2: agent 2, after t4: agent 1. Returns (2, 2, 0): efficiency 4; equality 1 - sum_ij
    |Ri - Rj| / (2 A sum |R|) = 1 - 8 / 24 = 2/3; sustainability: agent 0 at t1, t3 (mean 2), agent 1
    at t4 (4), agent 2 never: (2 + 4) / 2 = 3; peace: 12 agent-steps - 3 tagged = 9."""
    book = EpisodeBook(None, True, 1, 3, 10, torch.device("cpu"), "test", None)
    book.start(torch.tensor([True]), torch.Generator(), None)
    rewards = ((1, 0, 0), (0, 0, 0), (1, 0, 0), (0, 2, 0))
    tagged = ((0, 0, 1), (0, 0, 1), (0, 0, 0), (0, 1, 0))
    acting = torch.ones(1, 3, dtype=torch.bool)
    for t, (reward, out) in enumerate(zip(rewards, tagged, strict=True), 1):
        info = book.record(torch.tensor([reward], dtype=torch.float32), acting, torch.tensor([out], dtype=torch.bool),
                           torch.tensor([t]))
    assert info["efficiency"].tolist() == [4.0]
    assert info["equality"].item() == pytest.approx(2 / 3, abs=1e-7)
    assert info["sustainability"].tolist() == [3.0]
    assert info["peace"].tolist() == [9.0]
    assert all(value.dtype == torch.float32 and value.shape == (1,) for value in info.values())


def test_social_outcomes_edge_cases():
    zero = torch.zeros(2, 3, dtype=torch.float64)
    out = social_outcomes(zero, zero, torch.zeros(2, 3, dtype=torch.int64), torch.tensor([6, 6]))
    assert out["equality"].tolist() == [1.0, 1.0] and out["sustainability"].tolist() == [0.0, 0.0]
    # negative returns (rock-paper-scissors): |R| in the denominator keeps equality in [0, 1]
    returns = torch.tensor([[1.0, -1.0, 0.0]], dtype=torch.float64)
    out = social_outcomes(returns, returns * 0, torch.zeros(1, 3, dtype=torch.int64), torch.tensor([3]))
    assert out["efficiency"].tolist() == [0.0]
    assert out["equality"].item() == pytest.approx(1 - 8 / 12)  # pairs: 2 + 1 + 1 (x2) = 8; 2 A sum|R| = 12


def test_social_metrics_follow_the_episode_and_reset_with_it():
    with make_env("commons", num_worlds=2, resolution=8, seed=0, max_steps=4, autoreset="same_step",
                  episode_end=False) as env:
        assert {"efficiency", "equality", "sustainability", "peace"} <= set(env.spec.info)
        env.reset()
        total = torch.zeros(2)
        for step in range(1, 5):
            _, reward, _, _, info = env.step(env.random_actions())
            total += reward.sum(1)
            peace = env.get_state()["social_peace"]  # agents not tagged out, summed over the steps so far
            if step < 4:  # the 4th ends the episode: the tallies start again (same_step autoreset)
                assert torch.equal(info["peace"], peace.float()) and bool((peace <= step * 5).all())
        assert torch.equal(info["efficiency"], total) and bool(info["done_worlds"].all())
        assert env.get_state()["social_returns"].abs().sum() == 0  # reset with the new episode
    with make_env("commons", num_worlds=1, resolution=8, social_metrics=False) as env:
        assert "efficiency" not in env.spec.info


def test_the_multiprocess_env_reports_the_workers_episode_ends():
    """p = 1: every episode ends at min_steps = 2, well before max_steps = 10; the parent asks its workers."""
    with make_env("spread", num_worlds=2, num_processes=2, resolution=8, seed=0, max_steps=10,
                  episode_end=EpisodeEnd(2, 1, 1.0)) as env:
        env.reset()
        env.step(env.random_actions())
        assert env.episode_over().tolist() == [False, False]
        _, _, _, truncated, _ = env.step(env.random_actions())
        assert env.episode_over().tolist() == [True, True] and bool(truncated.all())
