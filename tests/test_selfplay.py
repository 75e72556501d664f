"""Self-play in the reference trainer: the snapshot pool's draws (window, latest, swap), batched
snapshot actions, a tiny self-play run of a task registered by the user (its record in result.json
and its snapshots as run folders), --import and module:Class in the trainer and the evaluation CLI,
and errors named for bad settings."""
import json
import os
import pathlib
import sys
import types

import pytest
import torch

from marl_render import evaluate as evaluation
from marl_render.baselines import run
from marl_render.baselines.networks import Actor
from marl_render.baselines.selfplay import SelfPlay, SnapshotPool, team_index
from marl_render.envs import list_envs, registry
from marl_render.policies import load_policy
from marl_render.populations import pages, scores

TESTS = pathlib.Path(__file__).resolve().parent
# 4 updates of 4 worlds x 4 decisions (16 env steps each) of 6-step episodes, 12 px: a snapshot every 2
# updates, a new draw due every update.
TINY = ["--env-steps", "64", "--worlds", "4", "--rollout", "4", "--resolution", "12", "--episodes", "2",
        "--checkpoint-every", "0", "--self-play", "--snapshot-every", "32", "--swap-every", "16", "--window", "2"]


@pytest.fixture(scope="module", autouse=True)
def forget_user_tasks():
    """The user's task registers itself on import: after this file, neither it nor its module is left
    behind for other tests (which count the registered tasks)."""
    yield
    for name in ("beacon_duel", "selfplay_user_task:BeaconDuel"):
        registry._REGISTRY.pop(name, None)
    sys.modules.pop("selfplay_user_task", None)


@pytest.fixture
def user_module(monkeypatch):
    """tests/selfplay_user_task.py importable by name, as from the folder a user runs the CLI in."""
    monkeypatch.syspath_prepend(str(TESTS))


def tiny_actor(agents: int = 2, actions: int = 5, favourite: int | None = None) -> Actor:
    """A state actor; with `favourite` its greedy and (almost surely) sampled action is that one."""
    actor = Actor("state", (3,), agents, actions, 8)
    if favourite is not None:
        with torch.no_grad():
            actor.head[-1].bias.copy_(torch.full((actions,), -50.0).index_fill(0, torch.tensor(favourite), 50.0))
    return actor


def pool_of(snapshots: int, worlds: int = 8, seed: int = 0, **settings) -> SnapshotPool:
    """A pool of `snapshots` actors over 2 teams of 1 agent; snapshot k always plays action k."""
    pool = SnapshotPool(SelfPlay(**settings), torch.tensor([0, 1]), worlds, seed)
    for k in range(snapshots):
        pool.add(tiny_actor(favourite=k), env_steps=100 * k, updates=k)
    return pool


# ---------------------------------------------------------------------- the pool
def test_draws_take_the_latest_with_its_chance_else_one_of_the_window():
    pool = pool_of(5, window=2, play_latest=0.0)
    assert set(pool.draw(400).tolist()) == {3, 4}  # the last 2 of snapshots 0-4
    assert set(pool_of(5, window=2, play_latest=1.0).draw(50).tolist()) == {4}
    draws = pool_of(5, window=5, play_latest=0.5).draw(4000)
    latest = float((draws == 4).float().mean())  # 0.5 + 0.5 / 5
    assert latest == pytest.approx(0.6, abs=0.03) and set(draws.tolist()) == set(range(5))
    # Deterministic for a seed, another seed another sequence.
    assert torch.equal(pool_of(5, seed=3).draw(64), pool_of(5, seed=3).draw(64))
    assert not torch.equal(pool_of(5, seed=3).draw(64), pool_of(5, seed=4).draw(64))


def test_worlds_draw_again_at_their_reset_once_per_swap_period_and_rotate_their_team():
    pool = pool_of(3, worlds=4, window=3, play_latest=0.0, swap_every=100)
    pool.start()
    opponents, teams = pool.opponent.clone(), pool.learning_team.clone()
    assert teams.tolist() == [0, 1, 0, 1]  # half the worlds learn each team
    assert pool.learner_slots().tolist() == [[True, False], [False, True], [True, False], [False, True]]
    reset = torch.tensor([True, True, False, False])
    pool.redraw(reset, env_steps=99)  # still the first swap period: nothing changes
    assert torch.equal(pool.opponent, opponents) and torch.equal(pool.learning_team, teams)
    pool.redraw(reset, env_steps=100)  # due: the reset worlds only
    assert pool.learning_team.tolist() == [1, 0, 0, 1] and torch.equal(pool.opponent[2:], opponents[2:])
    assert pool.epoch.tolist() == [1, 1, 0, 0]
    before = pool.opponent.clone()
    pool.redraw(reset, env_steps=150)  # drawn in this period already
    assert torch.equal(pool.opponent, before) and pool.learning_team.tolist() == [1, 0, 0, 1]


def test_each_snapshot_in_play_acts_once_for_all_the_slots_it_plays():
    pool = pool_of(3, worlds=6, window=3)
    pool.opponent = torch.tensor([0, 2, 2, 0, 2, 2])
    pool.learning_team = torch.tensor([0, 0, 1, 1, 0, 1])
    calls = []
    for k, actor in enumerate(pool.actors):
        actor.register_forward_hook(lambda module, inputs, output, k=k: calls.append((k, len(inputs[0]))))
    actions = torch.full((6, 2), 9)
    out = pool.act(torch.randn(6, 2, 3), torch.eye(2), torch.ones(6, 2, 5, dtype=torch.bool), actions)
    assert sorted(calls) == [(0, 2), (2, 4)]  # snapshot 1 faces nobody; one call per snapshot in play
    # The learner's slots keep their actions; each opponent slot plays its world's snapshot (k plays k).
    assert out.tolist() == [[9, 0], [9, 2], [2, 9], [0, 9], [9, 2], [2, 9]]


def test_the_pool_tallies_what_each_snapshot_faced():
    pool = pool_of(2, worlds=3)
    pool.opponent = torch.tensor([1, 0, 1])
    pool.count(4, torch.tensor([True, False, True]))
    pool.count(4, torch.tensor([False, True, False]))
    assert [(s["env_steps_faced"], s["episodes_faced"]) for s in pool.snapshots] == [(8, 1), (16, 2)]


@pytest.mark.parametrize("settings, message", [
    (dict(window=0), "window must be an int >= 1, got 0"),
    (dict(play_latest=1.5), r"play_latest must be a probability in \[0, 1\], got 1.5"),
    (dict(play_latest=-0.1), r"play_latest must be a probability in \[0, 1\], got -0.1"),
    (dict(play_latest=float("nan")), r"play_latest must be a probability in \[0, 1\], got nan"),
    (dict(snapshot_every=0), "snapshot_every must be an int >= 1, got 0"),
    (dict(swap_every=2.5), "swap_every must be an int >= 1, got 2.5"),
])
def test_bad_pool_settings_are_named(settings, message):
    with pytest.raises(ValueError, match=message):
        SelfPlay(**settings)


def test_a_task_of_one_team_is_refused():
    with pytest.raises(ValueError, match=r"two or more teams; this one has 1: \['agents'\]"):
        team_index({"agents": ["agent_0", "agent_1"]})


@pytest.mark.parametrize("args, message", [
    (["--env", "tag", "--self-play", "--window", "0"], "--window must be an int >= 1, got 0"),
    (["--env", "tag", "--self-play", "--play-latest", "1.5"], "--play-latest must be a probability in [0, 1]"),
    (["--env", "tag", "--self-play", "--play-latest", "-1"], "--play-latest must be a probability in [0, 1]"),
    (["--env", "tag", "--self-play", "--snapshot-every", "0"], "--snapshot-every must be an int >= 1, got 0"),
    (["--env", "tag", "--window", "3"], "--window applies to self-play only: add --self-play"),
    (["--env", "spread", "--self-play"], "--self-play: self-play needs a task with two or more teams; this one has 1"),
    (["--env", "nowhere:Task"], "--env nowhere:Task: could not import it (ModuleNotFoundError"),
    (["--env", "json:dumps"], "--env json:dumps: expected module:Class naming a Scenario subclass"),
    (["--import", "no_such_module_here", "--env", "tag"], "--import no_such_module_here: the module did not import"),
    (["--env", "beacon_duel"], "argument --env: invalid choice: 'beacon_duel'"),  # not imported: unknown
])
def test_bad_self_play_and_task_options_are_named(args, message, capsys, tmp_path):
    assert "beacon_duel" not in list_envs()
    with pytest.raises(SystemExit) as exit_info:
        run.parse_args([*args, "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err or pytest.fail(f"{message!r} not in the error")


# ---------------------------------------------------------------------- end to end, a user's task
@pytest.fixture(scope="module")
def duel_runs(tmp_path_factory):
    """The same tiny self-play run twice: the task registered by --import, then named module:Class."""
    root = tmp_path_factory.mktemp("selfplay")
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(TESTS))
        assert run.main(["--import", "selfplay_user_task", "--env", "beacon_duel", "--out", str(root / "imported"),
                         *TINY]) == 0
        assert run.main(["--env", "selfplay_user_task:BeaconDuel", "--out", str(root / "by_class"), *TINY]) == 0
    return root


def test_a_self_play_run_records_which_snapshots_played(duel_runs):
    result = json.loads((duel_runs / "imported" / "result.json").read_text())
    record = result["self_play"]
    assert (record["snapshot_every"], record["window"], record["play_latest"], record["swap_every"]) == (32, 2, 0.5, 16)
    assert result["env"] == "beacon_duel" and result["env_steps"] == 64 and result["updates"] == 4
    assert result["trained_agents"] == ["red_0", "blue_0"]  # both teams; the evaluation scores red
    assert result["evaluation"]["policy"]["evaluated_agents"] == ["red_0"]
    snapshots = record["snapshots"]
    # Snapshot 0 is the untrained actor; then one per 32 env steps (overlap: the step count when taken
    # includes the rollout collected during the update).
    assert [s["id"] for s in snapshots] == list(range(len(snapshots))) and snapshots[0]["env_steps"] == 0
    taken = [s["env_steps"] for s in snapshots]
    assert len(taken) >= 2 and taken == sorted(set(taken))
    # Every env step of every world faced exactly one snapshot, every ended episode one.
    assert sum(s["env_steps_faced"] for s in snapshots) == result["env_steps"]
    assert sum(s["episodes_faced"] for s in snapshots) == sum(p["episodes_ended"] for p in result["curve"]) > 0
    assert snapshots[0]["env_steps_faced"] > 0


def test_each_snapshot_is_a_run_folder_load_policy_reads(duel_runs):
    result = json.loads((duel_runs / "imported" / "result.json").read_text())
    for snapshot in result["self_play"]["snapshots"]:
        folder = duel_runs / "imported" / snapshot["folder"]
        own = json.loads((folder / "result.json").read_text())
        assert own["snapshot"]["id"] == snapshot["id"] and own["env"] == "beacon_duel"
        policy = load_policy(str(folder))
        assert policy.num_agents == 2 and policy.env_kwargs == {"resolution": 12, "grayscale": False}
    first = torch.load(duel_runs / "imported" / "snapshots" / "000" / "actor.pt", weights_only=True)
    last = torch.load(duel_runs / "imported" / "actor.pt", weights_only=True)
    assert not torch.equal(first["head.0.weight"], last["head.0.weight"])  # the learner moved on


def test_the_same_self_play_run_gives_the_same_numbers_by_name_or_by_class(duel_runs):
    def numbers(value):
        if isinstance(value, dict):
            return {k: numbers(v) for k, v in value.items()
                    if "seconds" not in k and k not in ("machine", "command", "env")}
        return [numbers(v) for v in value] if isinstance(value, list) else value

    imported, by_class = (json.loads((duel_runs / name / "result.json").read_text())
                          for name in ("imported", "by_class"))
    assert by_class["env"] == "selfplay_user_task:BeaconDuel"
    assert numbers(imported) == numbers(by_class)


def test_the_evaluation_cli_plays_a_user_task_cross_play_with_snapshots(duel_runs, user_module, tmp_path, capsys):
    folder = duel_runs / "imported"
    roster = ["random", "heuristic", str(folder / "snapshots" / "000"), str(folder)]
    out = tmp_path / "duel"
    assert evaluation.main(["--import", "selfplay_user_task", "--crossplay", "beacon_duel", "--roster", *roster,
                            "--crossplay-episodes", "2", "--out", str(out)]) == 0
    result = json.loads(out.with_suffix(".json").read_text())
    assert result["policies"] == ["random", "heuristic", "snapshot 0@0k seed0", "self-play seed0"]
    assert result["sides"] == ["red", "blue"] and result["env_kwargs"] == {"resolution": 12, "grayscale": False}
    wins, draws = torch.tensor(result["wins"]), torch.tensor(result["draws"])
    assert (wins + wins.T + draws + draws.T).tolist() == [[4.0] * 4] * 4  # 2 episodes in each order
    assert result["elo"][0] == 0.0 and len(result["elo"]) == 4


def test_the_evaluation_cli_names_a_task_it_cannot_import(capsys):
    with pytest.raises(SystemExit):
        evaluation.main(["--import", "no_such_module_here", "--crossplay", "tag"])
    assert "--import no_such_module_here: the module did not import" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        evaluation.main(["--crossplay", "spread", "--roster", "random", "random"])
    assert "cross-play needs a task of two or more teams" in capsys.readouterr().err


def test_the_docs_take_spread_snapshots_and_the_final_actor_of_each_self_play_run(tmp_path):
    run_folder = tmp_path / "tag" / "seed0"
    for folder, record in [(run_folder, {"self_play": {}}),
                           *[(run_folder / "snapshots" / f"{k:03d}", {"snapshot": {"id": k}}) for k in range(10)]]:
        folder.mkdir(parents=True)
        (folder / "result.json").write_text(json.dumps({"env": "tag", "obs": "pixels", **record}))
        (folder / "actor.pt").write_bytes(b"")
    picked = evaluation.selfplay_runs(str(tmp_path), per_run=4)
    assert picked == {"tag": [str(run_folder / "snapshots" / k) for k in ("000", "003", "006", "009")]
                      + [str(run_folder)]}
    assert evaluation.baseline_runs(str(tmp_path)) == {"tag": [str(run_folder)]}  # snapshots are no baselines


def test_the_held_out_page_plays_mappo_runs_and_self_play_final_actors_but_not_snapshots(tmp_path, monkeypatch):
    def make_run(folder, record):
        folder.mkdir(parents=True)
        (folder / "result.json").write_text(json.dumps({"env": "tag", "obs": "pixels", "seeds": {"train": 0},
                                                        **record}))
        (folder / "actor.pt").write_bytes(b"")
    mappo, selfplay = tmp_path / "baselines" / "tag" / "seed0", tmp_path / "selfplay" / "tag" / "seed0"
    make_run(mappo, {})
    make_run(selfplay, {"self_play": {}})
    make_run(selfplay / "snapshots" / "000", {"snapshot": {"id": 0, "env_steps": 0}})
    small = tmp_path / "baselines" / "tag" / "seed1"  # trained with 3 agents: tag's scenarios have 4
    make_run(small, {"seeds": {"train": 1}})
    monkeypatch.setattr(scores, "load_policy", lambda folder: types.SimpleNamespace(
        num_agents=3 if folder == str(small) else 4))
    played = []

    def fake_evaluate(spec, scenarios, **kwargs):  # one row per scenario, as evaluate gives
        played.append(spec)
        return [{"scenario": name, "tags": "visitor", "focal_return_mean": 1.0, "focal_return_std": 0.0,
                 "background_return_mean": 0.0, "normalised_score": 0.5, "bots_sampled": {"interceptor": 1},
                 "training_condition_return": 2.0, "generalisation_gap": 1.0} for name in scenarios]
    monkeypatch.setattr(scores, "evaluate_heldout", fake_evaluate)
    monkeypatch.setattr(scores, "crossplay", lambda task, roster, **kwargs: {
        "task": task, "sides": ["predator", "prey"], "episodes": 1, "policies": list(roster),
        "elo": [0.0] * len(roster), "win_rate": [[0.5] * len(roster)] * len(roster),
        "returns_a": [[0.0] * len(roster)] * len(roster), "returns_b": [[0.0] * len(roster)] * len(roster)})
    monkeypatch.setattr(pages, "heatmap", lambda result, path: None)
    docs = tmp_path / "docs"
    evaluation.publish(docs=str(docs), tasks=["tag"], baselines=str(tmp_path / "baselines"),
                       selfplay=str(tmp_path / "selfplay"))
    assert played == ["random", "heuristic", str(mappo), str(selfplay)]  # the snapshot plays cross-play only
    page = (docs / "heldout.md").read_text()
    assert f"{os.path.relpath(small)} (trained with 3 agents) does not play tag's scenarios defined for 4 agents." \
        in page
    assert f"## MAPPO-vs-random {os.path.relpath(mappo)}" in page
    assert f"## self-play {os.path.relpath(selfplay)}" in page
    assert "2 MAPPO pixel run(s)" in page and "the final actors of 1 self-play run(s)" in page
    assert len(list((docs / "heldout").glob("selfplay_*.json"))) == 1
    assert (docs / "crossplay.md").is_file()
    (docs / "crossplay.md").unlink()
    monkeypatch.setattr(scores, "crossplay", None)  # --heldout-only plays no cross-play
    evaluation.publish(docs=str(docs), tasks=["tag"], baselines=str(tmp_path / "baselines"),
                       selfplay=str(tmp_path / "selfplay"), heldout_only=True)
    assert not (docs / "crossplay.md").exists() and played[4:] == played[:4]


def test_the_docs_pages_are_regenerated_together_or_one_at_a_time(capsys):
    with pytest.raises(SystemExit):
        evaluation.main(["--docs", "--crossplay-only", "--heldout-only"])
    assert "--crossplay-only and --heldout-only exclude each other" in capsys.readouterr().err


def test_the_crossplay_page_says_whether_self_play_beats_mappo_vs_random():
    result = {"task": "tag", "sides": ["predator", "prey"], "episodes": 2, "policies": [
        "random", "MAPPO-vs-random seed0", "self-play seed0"], "elo": [0.0, 100.0, 250.0],
        "win_rate": [[0.5, 0.2, 0.1], [0.8, 0.5, 0.3], [0.9, 0.7, 0.5]],
        "returns_a": [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0], [6.0, 7.0, 8.0]], "returns_b": [[0.0] * 3] * 3}
    text = evaluation.crossplay_page([result], "command", "note")
    assert ("**Self-play beats MAPPO-vs-random** (self-play seed0 against MAPPO-vs-random seed0): Elo 250 against "
            "100. Head to head, over both sides, self-play wins 0.70") in text
    assert "self-play as predator against MAPPO-vs-random 7.00, 0.00; MAPPO-vs-random as predator against " \
           "self-play 5.00, 0.00" in text
    result["elo"] = [0.0, 300.0, 250.0]
    assert "**Self-play does not beat MAPPO-vs-random**" in evaluation.crossplay_page([result], "c", "n")
    result["policies"][1] = "heuristic"
    text = evaluation.crossplay_page([result], "c", "n")
    assert "No MAPPO-vs-random policy with an actor.pt was found for tag" in text


def test_cross_play_takes_the_pairs_it_played_before_from_the_earlier_result(duel_runs, user_module, monkeypatch):
    import selfplay_user_task  # noqa: F401 (registers beacon_duel)

    pair = {"random": "random", "heuristic": "heuristic"}
    first = evaluation.crossplay("beacon_duel", pair, episodes=2, resolution=12)
    assert [(p["row"], p["column"]) for p in first["pairs"]] == [
        ("random", "random"), ("random", "heuristic"), ("heuristic", "random"), ("heuristic", "heuristic")]
    played = []
    real_play = evaluation.play
    monkeypatch.setattr(scores, "play", lambda env, policy: played.append(policy.name) or real_play(env, policy))
    roster = {**pair, "snapshot": str(duel_runs / "imported" / "snapshots" / "001")}
    second = evaluation.crossplay("beacon_duel", roster, episodes=2, resolution=12, previous=first)
    assert len(played) == 5  # the 9 pairs less the 4 known ones, which keep their outcomes
    assert second["pairs"][:2] + second["pairs"][3:5] == first["pairs"]
    assert [row[:2] for row in second["returns_a"][:2]] == first["returns_a"]
    assert second["pairs"][2]["column"].endswith("snapshots/001#" + second["pairs"][2]["column"][-16:])
    evaluation.crossplay("beacon_duel", pair, episodes=3, resolution=12, previous=first)  # other settings: all played
    assert len(played) == 5 + 4


def test_a_rerun_into_the_same_out_replaces_the_earlier_runs_snapshots(tmp_path, user_module, capsys):
    out = tmp_path / "run"
    for k in range(6):  # an earlier, longer run's snapshots (one more than this run takes)
        stale = out / "snapshots" / f"{k:03d}"
        stale.mkdir(parents=True)
        (stale / "result.json").write_text(json.dumps({"env": "beacon_duel", "env_steps": 32 * k}))
    assert run.main(["--import", "selfplay_user_task", "--env", "beacon_duel", "--out", str(out), *TINY]) == 0
    assert "held an earlier run: its 6 snapshot(s) are replaced" in capsys.readouterr().out
    result = json.loads((out / "result.json").read_text())
    recorded = sorted(s["folder"] for s in result["self_play"]["snapshots"])
    assert sorted(f"snapshots/{p.name}" for p in (out / "snapshots").iterdir()) == recorded
    for snapshot in (out / "snapshots").iterdir():
        own = json.loads((snapshot / "result.json").read_text())
        assert own["env_steps"] <= result["env_steps"] and (snapshot / "actor.pt").is_file()
    # A run without self-play into the folder leaves no snapshots that its result.json does not describe.
    plain = TINY[:TINY.index("--self-play")]
    assert run.main(["--import", "selfplay_user_task", "--env", "beacon_duel", "--out", str(out), *plain]) == 0
    assert not (out / "snapshots").exists() and "self_play" not in json.loads((out / "result.json").read_text())
