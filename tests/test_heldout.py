"""Policies, bots, held-out scenarios and their focal-only envs, the evaluation CLI and Elo."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from pettingzoo.test import api_test, parallel_api_test
from torchrl.envs.utils import check_env_specs

from marl_render import evaluate as evaluation
from marl_render.baselines.networks import Actor
from marl_render.bots import POPULATIONS, bot_names, make_bot
from marl_render.elo import elo_ratings, win_probability
from marl_render.envs import FocalEnv, Population, list_envs, make_env
from marl_render.heldout import HELDOUT, heldout_scenario, list_heldout
from marl_render.policies import RandomPolicy, load_policy
from marl_render.populations import pages, scores
from marl_render.wrappers.gymnasium import make_vec_env
from marl_render.wrappers.pettingzoo import make_aec_env, make_parallel_env
from marl_render.wrappers.rllib import make_rllib_env
from marl_render.wrappers.sb3 import make_sb3_env
from marl_render.wrappers.torchrl import make_torchrl_env

DOCS = Path(__file__).resolve().parent.parent / "docs"


def test_list_names_at_least_three_tagged_scenarios_per_multi_agent_task(capsys):
    assert evaluation.main(["--list"]) == 0
    printed = capsys.readouterr().out
    multi_agent = [name for name in list_envs() if name != "cartpole"]
    assert sorted(POPULATIONS) == sorted(multi_agent)
    assert len(list_heldout()) >= 24
    for task in multi_agent:
        assert len(list_heldout(task)) >= 3, task
    for name in list_heldout():
        scenario = HELDOUT[name]
        assert re.search(rf"^{re.escape(name)}  \[(resident|visitor)\]", printed, re.M), name
        assert scenario.description and scenario.description in printed
        assert scenario.tags == (("resident",) if 2 * len(scenario.focal) > scenario.num_agents else ("visitor",))


def test_no_test_bot_is_in_a_training_population_and_scenarios_use_test_bots_only():
    for task, population in POPULATIONS.items():
        assert population["train"] and population["test"]
        assert not set(population["train"]) & set(population["test"]), task
    for scenario in HELDOUT.values():
        for names in scenario.bots_by_role.values():
            assert set(names) <= set(POPULATIONS[scenario.task]["test"]), scenario.name
            assert not set(names) & set(POPULATIONS[scenario.task]["train"]), scenario.name


@pytest.mark.parametrize("name", list_heldout())
def test_every_scenario_through_pettingzoo_torchrl_and_the_vector_env(name):
    scenario = HELDOUT[name]
    with make_env(scenario.task, heldout=name, num_worlds=1, resolution=8) as core:
        full = make_env(scenario.task, num_worlds=1, resolution=8, **scenario.env_kwargs())
        background = [n for n in full.agent_names if n not in scenario.focal]
        full.close()
        assert list(core.agent_names) == [n for n in scenario.focal]
        assert not set(core.agent_names) & set(background)  # background slots are never agents
    env = make_parallel_env(scenario.task, heldout=name, resolution=8, max_steps=12)
    try:
        parallel_api_test(env)
        assert set(env.possible_agents) == set(scenario.focal)
    finally:
        env.close()
    torchrl_env = make_torchrl_env(scenario.task, heldout=name, num_worlds=2, resolution=8, max_steps=12)
    try:
        check_env_specs(torchrl_env)
        agents = [n for names in torchrl_env.group_map.values() for n in names]
        assert sorted(agents) == sorted(scenario.focal)
    finally:
        torchrl_env.close()
    vector = make_vec_env(scenario.task, 2, heldout=name, resolution=8)
    try:
        obs, _ = vector.reset(seed=1)
        F = len(scenario.focal)
        pixels = obs["pixels"] if isinstance(obs, dict) else obs  # a Dict with a task's vectors (matrix's inventory)
        assert vector.num_envs == 2 * F and pixels.shape == (2 * F, 8, 8, 3)
        obs, reward, terminated, truncated, _ = vector.step(vector.action_space.sample())
        pixels = obs["pixels"] if isinstance(obs, dict) else obs
        assert pixels.shape == (2 * F, 8, 8, 3) and reward.shape == (2 * F,)
    finally:
        vector.close()


def test_sb3_rllib_and_aec_envs_expose_only_the_focal_agents():
    env = make_sb3_env("tag", num_worlds=2, heldout="tag/prey_vs_interceptors", resolution=8)
    try:
        assert env.num_envs == 2  # 2 worlds x 1 focal prey
        env.reset()
        env.step_async(np.zeros(2, dtype=np.int64))
        obs, reward, done, info = env.step_wait()
        assert obs.shape[0] == 2 and reward.shape == (2,)
    finally:
        env.close()
    rllib = make_rllib_env({"env": "push", "heldout": "push/blue_vs_chasers", "num_worlds": 2, "resolution": 8,
                            "num_envs": 4})  # 2 worlds x 2 focal blue players
    try:
        obs, _ = rllib.reset(seed=0)
        assert obs.shape == (4, 8, 8, 3) and obs.dtype == np.float32
    finally:
        rllib.close()
    aec = make_aec_env("speaker_listener", heldout="speaker_listener/permuted_speaker", resolution=8, max_steps=10)
    try:
        api_test(aec)
        assert aec.possible_agents == ["listener_0"]
    finally:
        aec.close()


def test_bots_differ_across_worlds_and_a_step_calls_each_distinct_bot_once():
    with make_env("tag", heldout="tag/pair_with_interceptor", num_worlds=16, resolution=8, seed=3) as env:
        env.reset(seed=3)
        prey = [row[1] for row in env.sampled_bots()]  # slot order: predator_2, prey_0
        assert set(prey) == {"wandering_prey", "corner_prey"}
        assert all(row[0] == "interceptor" for row in env.sampled_bots())
        for _ in range(3):
            before = env.bot_calls
            obs, reward, terminated, truncated, info = env.step(env.random_actions())
            assert env.bot_calls - before == 3  # interceptor, wandering_prey, corner_prey: one call each
        assert obs["pixels"].shape == (16, 2, 8, 8, 3) and reward.shape == (16, 2)
        assert info["background_reward"].shape == (16,)
        # the caught prey's -10 shows in the background's reward, never in the focal rewards
        assert torch.equal(env.alive, env.core.alive[:, :2])


def test_bots_are_resampled_at_reset_deterministically_for_a_seed():
    def draws(seed):
        with make_env("push", heldout="push/red_vs_chasers", num_worlds=8, resolution=8, seed=seed) as env:
            first = env.reset(seed=seed) and env.sampled_bots()
            second = env.reset() and env.sampled_bots()
            return first, second
    a, b = draws(5), draws(5)
    assert a == b and a[0] != a[1]
    assert draws(6)[0] != a[0]


def test_focal_env_refuses_bad_actions_and_populations_without_changing_anything():
    with make_env("tag", heldout="tag/predators_vs_wanderers", num_worlds=2, resolution=8) as env:
        env.reset(seed=0)
        state = env.get_state()
        with pytest.raises(ValueError, match=r"actions must have shape \[2, 3\].*predator_0"):
            env.step(torch.zeros(2, 4, dtype=torch.int64))
        with pytest.raises(ValueError, match="actions must be"):
            env.step(torch.full((2, 3), 9))
        after = env.get_state()
        assert all(torch.equal(state[k], after[k]) for k in state if isinstance(state[k], torch.Tensor))
    with pytest.raises(ValueError, match="no bots for team"):
        make_env("tag", num_worlds=1, resolution=8, background=Population({"prey": [RandomPolicy()]},
                                                                           focal=["predator_0"]))
    with pytest.raises(ValueError, match="not of 'push'"):
        make_env("push", heldout="tag/prey_vs_interceptors", num_worlds=1)
    with pytest.raises(ValueError, match="fixes"):
        make_env("tag", heldout="tag/prey_vs_interceptors", num_agents=6, num_worlds=1)


def test_focal_env_state_round_trip_and_step_before_reset():
    with make_env("push", heldout="push/red_vs_chasers", num_worlds=4, resolution=8, seed=2) as env:
        with pytest.raises(RuntimeError, match="reset"):
            env.step(torch.zeros(4, 2, dtype=torch.int64))
        env.reset(seed=2)
        state, bots = env.get_state(), env.sampled_bots()
        actions = [env.random_actions(torch.Generator().manual_seed(k)) for k in range(4)]
        first = [env.step(a)[0]["pixels"] for a in actions]
        env.set_state(state)  # the bots (ball chasers, goalkeepers) read the simulation state only
        assert env.sampled_bots() == bots
        again = [env.step(a)[0]["pixels"] for a in actions]
        assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True))
        with pytest.raises(ValueError, match="background_bots"):
            env.set_state({**state, "background_bots": state["background_bots"] + 5})


def test_training_with_a_background_population_of_training_bots():
    bots = [make_bot("tag", name) for name in POPULATIONS["tag"]["train"]]
    with make_env("tag", num_worlds=4, resolution=8, background=Population({"prey": bots})) as env:
        assert isinstance(env, FocalEnv) and env.agent_names == ["predator_0", "predator_1", "predator_2"]
        obs = env.reset(seed=1)
        assert obs["pixels"].shape == (4, 3, 8, 8, 3)
        env.step(env.heuristic_actions())


def test_seeded_evaluation_is_deterministic_and_scores_heuristic_at_one():
    rows = evaluation.evaluate("heuristic", ["spread/two_with_wanderer"], episodes=4, resolution=8, max_steps=40)
    again = evaluation.evaluate("heuristic", ["spread/two_with_wanderer"], episodes=4, resolution=8, max_steps=40)
    assert rows == again
    assert rows[0]["normalised_score"] == 1.0 and rows[0]["bots_sampled"] == {"wanderer": 4}
    random_rows = evaluation.evaluate("random", ["spread/two_with_wanderer"], episodes=4, resolution=8, max_steps=40)
    assert random_rows[0]["normalised_score"] == 0.0
    assert random_rows[0]["focal_return_mean"] < rows[0]["focal_return_mean"]


def test_evaluate_cli_writes_json_and_csv(tmp_path):
    out = tmp_path / "rows"
    assert evaluation.main(["--policy", "nearest_landmark", "--scenario", "spread/one_among_nearest",
                            "--episodes", "2", "--resolution", "8", "--max-steps", "10", "--out", str(out)]) == 0
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [r["scenario"] for r in rows] == ["spread/one_among_nearest"]
    assert (tmp_path / "rows.csv").read_text().splitlines()[0].startswith("scenario,task,tags,policy")
    with pytest.raises(SystemExit):
        evaluation.main(["--policy", "no_such_bot", "--scenario", "spread", "--episodes", "2"])


def test_elo_recovers_known_ratings():
    # 3 beats 1 of 4 games against the anchor: 400 log10(3) above it, by maximum likelihood.
    ratings = elo_ratings([[0, 1], [3, 0]], smoothing=0.0)
    assert ratings[0] == 0 and ratings[1] == pytest.approx(400 * math.log10(3), abs=1e-6)
    truth = np.array([0.0, 150.0, -80.0])
    wins = np.array([[0 if i == j else 1e6 * win_probability(truth[i], truth[j]) for j in range(3)]
                     for i in range(3)])
    assert elo_ratings(wins, smoothing=0.0) == pytest.approx(truth, abs=1e-3)
    with pytest.raises(ValueError, match="wins must be a square matrix"):
        elo_ratings([[0, 1, 2]])


def _saved_run(folder: Path, task: str = "tag") -> None:
    """A run folder as python -m marl_render.baselines writes it (result.json + actor.pt)."""
    folder.mkdir(parents=True)
    hp = {"resolution": 16, "grayscale": False, "frames": 2, "action_repeat": 2, "hidden": 16, "encoder": "conv",
          "precision": "float32"}
    torch.manual_seed(0)
    actor = Actor("pixels", (16, 16, 6), 4, 5, 16)
    torch.save(actor.state_dict(), folder / "actor.pt")
    (folder / "result.json").write_text(json.dumps({"env": task, "obs": "pixels", "hyperparameters": hp,
                                                    "trained_agents": ["predator_0", "predator_1", "predator_2"]}))


def test_load_policy_plays_held_out_scenarios(tmp_path):
    _saved_run(tmp_path / "run")
    policy = load_policy(str(tmp_path / "run"))
    assert policy.env_kwargs == {"resolution": 16, "grayscale": False}
    references: dict = {}  # random's and the heuristic's rows, computed once
    rows, again = (evaluation.evaluate(str(tmp_path / "run"), ["tag/predators_vs_wanderers"], episodes=2, max_steps=30,
                                       references=references) for _ in range(2))
    assert rows == again and math.isfinite(rows[0]["focal_return_mean"])
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "result.json").write_text("{")
    with pytest.raises(FileNotFoundError, match="actor.pt"):
        load_policy(str(tmp_path / "broken"))


def test_documented_example_evaluates_a_saved_policy(tmp_path, monkeypatch):
    page = (DOCS / "populations.md").read_text()
    example = re.search(r"```python\n(.*?)```", page, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    _saved_run(tmp_path / "runs" / "tag")
    namespace: dict = {}
    exec(compile(example, "docs/populations.md", "exec"), namespace)
    assert [row["scenario"] for row in namespace["rows"]] == list_heldout("tag")


def test_every_bot_acts_validly_in_its_task():
    for task in POPULATIONS:
        with make_env(task, num_worlds=3, resolution=8) as env:
            env.reset(seed=0)
            worlds = torch.arange(3).repeat_interleave(env.num_agents)
            slots = torch.arange(env.num_agents).repeat(3)
            obs = {k: v.flatten(0, 1) for k, v in env.reset(seed=0).items()}
            for name in bot_names(task):
                actions = make_bot(task, name).act(env, obs, worlds, slots)
                env.check_actions(actions.reshape(3, env.num_agents))


def test_agent_ids_tell_one_shared_policy_which_role_each_entry_plays():
    vector = make_vec_env("tag", 2, resolution=8, agent_ids=True)
    try:
        obs, _ = vector.reset(seed=0)
        ids = obs["agent_id"]  # entries: world 0's agents, then world 1's; 4 agents then 2 teams
        assert ids.shape == (8, 6) and ids.dtype == np.float32
        expected = np.concatenate((np.eye(4), [[1, 0], [1, 0], [1, 0], [0, 1]]), 1)
        np.testing.assert_array_equal(ids, np.concatenate((expected, expected)))
        obs, *_ = vector.step(vector.action_space.sample())
        np.testing.assert_array_equal(obs["agent_id"][4:], expected)
    finally:
        vector.close()
    env = make_torchrl_env("push", num_worlds=2, resolution=8, agent_ids=True, heldout="push/red_vs_chasers")
    try:
        check_env_specs(env)
        assert env.reset()["red", "agent_id"].shape == (2, 2, 6)
    finally:
        env.close()
    with make_env("tag", num_worlds=1, resolution=8) as plain:
        assert "agent_id" not in plain.reset()  # off by default


def test_jax_env_of_a_held_out_scenario():
    jnp = pytest.importorskip("jax.numpy")
    from marl_render.envs import make_jax_env

    env = make_jax_env("tag", num_worlds=2, heldout="tag/prey_vs_interceptors", resolution=8)
    try:
        assert env.reset(seed=0)["pixels"].shape == (2, 1, 8, 8, 3)
        assert env.step(jnp.zeros((2, 1), dtype=jnp.int32))[1].shape == (2, 1)
    finally:
        env.close()


def test_a_side_the_trainer_never_trained_has_no_training_condition_and_no_gap(tmp_path):
    """A MAPPO-vs-random run trains one team: on a scenario whose focal slots are the other team's
    there is no training condition to compare with, and the page says so instead of a number."""
    run = tmp_path / "tag_run"
    run.mkdir()
    (run / "result.json").write_text(json.dumps({"env": "tag", "trained_agents": ["predator_0", "predator_1",
                                                                                   "predator_2"]}))
    prey = heldout_scenario("tag/prey_vs_interceptors")
    assert prey.focal == ("prey_0",)
    assert not scores.trains_focal_side(str(run), prey)
    assert scores.trains_focal_side(str(run), heldout_scenario("tag/predators_vs_wanderers"))
    assert scores.trains_focal_side("random", prey) and scores.trains_focal_side(str(tmp_path), prey)
    rows = [{"scenario": "tag/prey_vs_interceptors", "tags": "visitor", "focal_return_mean": -1.0,
             "focal_return_std": 0.5, "background_return_mean": 1.0, "normalised_score": 0.2,
             "training_condition_return": None, "generalisation_gap": None, "focal_side_trained": False,
             "random_return": -2.0, "heuristic_return": 0.0, "bots_sampled": {"noisy0.5": 3}},
            {"scenario": "tag/predators_vs_wanderers", "tags": "visitor", "focal_return_mean": 3.0,
             "focal_return_std": 1.0, "background_return_mean": -3.0, "normalised_score": 0.5,
             "training_condition_return": 4.0, "generalisation_gap": 1.0, "random_return": 1.0,
             "heuristic_return": 5.0, "bots_sampled": {"evader": 3}}]
    page = pages.heldout_page({"MAPPO-vs-random run": rows}, "cmd", "note")
    assert "| tag/prey_vs_interceptors | visitor | -1.00 ± 0.50 | 1.00 | 0.20 | side not trained | side not " \
           "trained | noisy0.5 3 |" in page
    assert "Mean generalisation gap over 1 scenarios, each normalised by its heuristic - random: 0.25 (1 on a side " \
           "never trained, without a gap)." in page


def test_the_held_out_page_is_its_json_files(tmp_path):
    """docs/heldout.md rebuilt from docs/heldout/*.json (no replay) is the committed page, byte for byte:
    the page's numbers are those of its published JSON files."""
    docs = Path(__file__).resolve().parents[1] / "docs"
    (tmp_path / "heldout").mkdir()
    for path in (docs / "heldout").glob("*.json"):
        (tmp_path / "heldout" / path.name).write_bytes(path.read_bytes())
    (tmp_path / "heldout.md").write_bytes((docs / "heldout.md").read_bytes())
    assert pages.rewrite_heldout_page(str(tmp_path)) == (docs / "heldout.md").read_text()
