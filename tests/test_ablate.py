"""Baselines a policy must beat: the best constant action and the view ablation (marl_render/baselines/ablate.py)."""
import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from marl_render.baselines import ablate, published, run
from marl_render.baselines.settings import EVALUATION_SETS
from marl_render.envs.evaluation import SEALED_SEEDS, best_constant_action, constant_policy, evaluate

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--env-steps", "8", "--checkpoint-every", "0", "--worlds", "2", "--resolution", "12", "--episodes", "3",
        "--rollout", "4"]


def test_a_constant_action_is_held_where_allowed_and_the_lowest_allowed_elsewhere():
    mask = torch.tensor([[[True, True, True], [False, True, True]],
                         [[False, False, True], [True, True, True]]])  # [W=2, A=2, 3 actions]
    assert constant_policy(0)(None, {"action_mask": mask}, None).tolist() == [[0, 1], [2, 0]]
    assert constant_policy(2)(None, {"action_mask": mask}, None).tolist() == [[2, 2], [2, 2]]


def test_the_best_constant_action_is_the_best_of_every_action_on_the_same_episodes():
    best = best_constant_action("tag", episodes=3, seed=5, resolution=8)
    each = [evaluate("tag", constant_policy(a), episodes=3, seed=5, resolution=8)["mean"] for a in range(5)]
    assert best["per_action"] == each and best["action"] == each.index(max(each)) and best["mean"] == max(each)
    assert best["episodes"] == 3 and len(best["per_episode"]) == 3


def test_the_best_constant_action_refuses_continuous_actions():
    with pytest.raises(ValueError, match="needs discrete actions; tag was built with continuous=True"):
        best_constant_action("tag", episodes=2, continuous=True)


def test_ablated_views_are_zeros_or_the_previous_worlds():
    pixels = torch.arange(3 * 2 * 4, dtype=torch.uint8).reshape(3, 2, 2, 2, 1)  # [W, A, H, W, C]
    assert ablate.ablate_view(pixels, "none") is pixels
    assert ablate.ablate_view(pixels, "zeros").eq(0).all() and ablate.ablate_view(pixels, "zeros").shape == pixels.shape
    shifted = ablate.ablate_view(pixels, "shifted")
    assert torch.equal(shifted[1:], pixels[:-1]) and torch.equal(shifted[0], pixels[-1])
    with pytest.raises(ValueError, match="view must be one of"):
        ablate.ablate_view(pixels, "noise")
    with pytest.raises(ValueError, match="needs at least 2 worlds"):
        ablate.ablate_view(pixels[:1], "shifted")
    with pytest.raises(ValueError, match="obs_key 'state' goes with view 'none' only"):
        ablate.AblatedPolicy(None, 1, 1, "zeros", obs_key="state")
    with pytest.raises(ValueError, match="view must be one of"):
        ablate.AblatedPolicy(None, 1, 1, "noise")


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("ablate")
    assert run.main(["--env", "spread", "--out", str(root / "spread"), *TINY]) == 0
    assert run.main(["--env", "spread", "--obs", "state", "--out", str(root / "spread-state"), *TINY]) == 0
    return root


def test_the_view_ablation_scores_the_runs_actor_on_its_own_episodes(tiny_runs):
    found = ablate.view_ablation(tiny_runs / "spread")
    result = json.loads((tiny_runs / "spread" / "result.json").read_text())
    assert found["reproduces_run"] is True  # as trained, episode for episode
    assert (found["seed"], found["episodes"], found["evaluation_set"]) == (1000, 3, "development")
    assert set(found["views"]) == set(ablate.VIEWS)
    assert all(len(v["per_episode"]) == 3 for v in found["views"].values())
    assert found["views"]["none"]["per_episode"] == result["evaluation"]["policy"]["per_episode"]


def test_the_view_ablation_refuses_a_run_from_the_state(tiny_runs):
    with pytest.raises(ValueError, match="needs a run from pixels; .* learned from 'state'"):
        ablate.view_ablation(tiny_runs / "spread-state")


def test_the_command_writes_ablation_json_and_refuses_a_folder_without_a_run(tiny_runs, tmp_path, capsys):
    folder = tmp_path / "run"
    shutil.copytree(tiny_runs / "spread", folder)
    assert ablate.main([str(folder)]) == 0
    written = json.loads((folder / ablate.ABLATION).read_text())
    assert written["views"]["none"]["per_episode"] == json.loads((folder / "result.json").read_text())[
        "evaluation"]["policy"]["per_episode"]
    assert f"{folder}: none " in capsys.readouterr().out
    with pytest.raises(SystemExit):
        ablate.main([str(tmp_path)])
    assert "must be a run folder holding result.json and actor.pt" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        ablate.main([])
    assert "give run folders, --constant, or both" in capsys.readouterr().err


def test_the_committed_tag_actors_from_pixels_beat_the_best_constant_action_and_need_their_view():
    """Issue 38: tag's pixel row, retrained with the default init, beats its best constant action
    ('backward', action 4, 3.44) in every seed, and each seed's view ablation costs it return; the
    committed numbers say so, and each ablation replays its run episode for episode."""
    constants = json.loads((ROOT / "docs" / "baselines" / ablate.CONSTANT_ACTIONS).read_text())
    assert constants["tag"]["action"] == 4 and constants["tag"]["mean"] == 3.4375
    for seed in published.SEEDS:
        folder = ROOT / "docs" / "baselines" / "tag" / f"seed{seed}"
        ablation = json.loads((folder / ablate.ABLATION).read_text())
        run = json.loads((folder / "result.json").read_text())
        assert ablation["reproduces_run"] is True and run["hyperparameters"]["init"] == "orthogonal"
        views = {view: score["mean"] for view, score in ablation["views"].items()}
        assert views["none"] == run["evaluation"]["policy"]["mean"] > constants["tag"]["mean"]
        assert views["zeros"] < views["none"] and views["shifted"] < views["none"], (seed, views)
    assert set(constants) == set(published.published_tasks())  # the tasks without runs (PENDING) have none
    assert all(c["evaluation_set"] == "publication" and c["seed"] == 7_000_000 and c["episodes"] == 64
               for c in constants.values())


def test_constant_for_some_tasks_replaces_their_entries_and_keeps_the_others(tmp_path, monkeypatch, capsys):
    (tmp_path / ablate.CONSTANT_ACTIONS).write_text(json.dumps({"tag": {"action": 4}, "spread": {"action": 0}}))
    monkeypatch.setattr(ablate, "constant_actions",
                        lambda tasks, evaluation_set, final: {t: {"action": 2, "mean": 1.0,
                                                                  "per_action": [0.0, 0.5, 1.0]} for t in tasks})
    assert ablate.main(["--constant", "--tasks", "spread", "matrix", "--root", str(tmp_path)]) == 0
    found = json.loads((tmp_path / ablate.CONSTANT_ACTIONS).read_text())
    assert found == {"matrix": {"action": 2, "mean": 1.0, "per_action": [0.0, 0.5, 1.0]},
                     "spread": {"action": 2, "mean": 1.0, "per_action": [0.0, 0.5, 1.0]}, "tag": {"action": 4}}
    assert list(found) == [env for env in published.RUNS if env in found]  # in the table's order
    with pytest.raises(SystemExit):
        ablate.main(["--tasks", "spread"])
    assert "--tasks and --eval-set go with --constant" in capsys.readouterr().err


# ---------------------------------------------------------------------- the sealed final set
FINAL_SEED = EVALUATION_SETS["final"]["seed"]


def test_the_sealed_set_needs_final_for_the_constant_actions_too(monkeypatch):
    assert FINAL_SEED in SEALED_SEEDS
    monkeypatch.setattr("marl_render.envs.evaluation.make_env", lambda *a, **k: pytest.fail("built an env"))
    with pytest.raises(ValueError, match="sealed 'final' evaluation set: it is scored only with final=True"):
        best_constant_action("tag", episodes=2, seed=FINAL_SEED)
    with pytest.raises(ValueError, match="sealed 'final' evaluation set"):
        ablate.constant_actions(["tag"], "final")
    with pytest.raises(ValueError, match="final=True applies to a sealed set's seed"):
        best_constant_action("tag", episodes=2, seed=5, final=True)


def as_final_run(source: Path, folder: Path) -> Path:
    """A copy of a tiny run whose result.json says it was scored on the sealed set (nothing is scored)."""
    shutil.copytree(source, folder)
    result = json.loads((folder / "result.json").read_text())
    result["evaluation_set"], result["seeds"]["evaluation"] = "final", FINAL_SEED
    (folder / "result.json").write_text(json.dumps(result))
    return folder


def test_a_final_run_is_ablated_only_with_final(tiny_runs, tmp_path, capsys):
    folder = as_final_run(tiny_runs / "spread", tmp_path / "final")
    with pytest.raises(ValueError, match="sealed 'final' evaluation set"):
        ablate.view_ablation(folder)
    with pytest.raises(SystemExit):
        ablate.main([str(folder)])
    assert "--final scores the sealed final set and is needed for it" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        ablate.main(["--final", str(tiny_runs / "spread")])  # --final with nothing sealed to score
    assert "--final scores the sealed final set" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        ablate.main(["--constant", "--eval-set", "final", "--root", str(tmp_path)])
    assert "--final scores the sealed final set" in capsys.readouterr().err
    assert not (folder / ablate.ABLATION).exists() and not (tmp_path / ablate.CONSTANT_ACTIONS).exists()


def test_final_lets_a_final_run_be_ablated(tiny_runs, tmp_path, monkeypatch):
    folder = as_final_run(tiny_runs / "spread", tmp_path / "final")
    called = []
    monkeypatch.setattr(ablate, "view_ablation", lambda run, final: called.append((run, final)) or {
        "views": {"none": {"mean": 1.0}}, "reproduces_run": True})
    assert ablate.main(["--final", str(folder)]) == 0
    assert called == [(str(folder), True)] and (folder / ablate.ABLATION).is_file()


@pytest.fixture(scope="module")
def reproducible_run(tmp_path_factory):
    """A tiny run trained in the reproducible mode (its command line restarts itself pinned)."""
    folder = tmp_path_factory.mktemp("reproducible") / "spread"
    subprocess.run([sys.executable, "-m", "marl_render.baselines", "--env", "spread", "--reproducible",
                    "--out", str(folder), *TINY], check=True, capture_output=True, timeout=300)
    return folder


def test_a_reproducible_run_is_ablated_in_its_mode_and_replays_its_episodes(reproducible_run, tiny_runs, capsys):
    assert json.loads((reproducible_run / "result.json").read_text())["mode"] == "reproducible"
    with pytest.raises(SystemExit):  # from Python: torch chose its kernels already, no restart possible
        ablate.main([str(reproducible_run)])
    assert "need a process started with its environment" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        ablate.main([str(reproducible_run), str(tiny_runs / "spread")])
    assert "runs mix the reproducible mode and the default one" in capsys.readouterr().err
    with pytest.raises(ValueError, match="reproducible mode needs its environment set"):
        ablate.view_ablation(reproducible_run)
    assert not (reproducible_run / ablate.ABLATION).exists()
    subprocess.run([sys.executable, "-m", "marl_render.baselines.ablate", str(reproducible_run)], check=True,
                   capture_output=True, timeout=300)  # restarts itself pinned
    written = json.loads((reproducible_run / ablate.ABLATION).read_text())
    assert written["reproduces_run"] is True and set(written["views"]) == set(ablate.VIEWS)
    assert written["cpu"]


def test_greedy_vs_sampled_replays_the_greedy_score_and_draws_other_actions(tiny_runs, capsys):
    """tools/greedy_vs_sampled.py: its greedy score on the run's own worlds is the run's; sampling draws
    from the actor's distribution (with all mass on one action it is that action)."""
    spec = importlib.util.spec_from_file_location("greedy_vs_sampled", ROOT / "tools" / "greedy_vs_sampled.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    tool.main([str(tiny_runs / "spread"), str(tiny_runs / "spread-state"), "--episodes", "3"])
    lines = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()[-2:]]
    for line, folder in zip(lines, ("spread", "spread-state"), strict=True):  # a pixel run and a state run
        result = json.loads((tiny_runs / folder / "result.json").read_text())
        assert line["greedy"] == result["evaluation"]["policy"]["mean"] and set(line) >= {"sampled", "seed"}
    logits = torch.tensor([[0.0, -1e9, -1e9], [-1e9, -1e9, 0.0]])
    sampled = tool.SampledPolicy.choose(None, logits, torch.Generator().manual_seed(0))
    assert sampled.tolist() == [0, 2] and sampled.dtype == torch.int64
    assert tool.GreedyPolicy.choose(None, torch.tensor([[0.1, 0.5, 0.2]]), None).tolist() == [1]
    with pytest.raises(ValueError, match="sealed 'final' evaluation set"):
        tool.main([str(tiny_runs / "spread"), "--episodes", "3", "--seed", str(FINAL_SEED)])
