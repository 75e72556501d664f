"""The social outcomes of the published mixed-motive rows (marl_render/baselines/social.py): read from a run's
result.json, or replayed from its kept actor into social.json, and shown in docs/results.md and on the cards."""
import json
import shutil
from pathlib import Path

import pytest

from marl_render.baselines import run, social
from marl_render.baselines.published import ROOT, RUNS, SEEDS, run_folder

ROOT_DIR = Path(__file__).resolve().parent.parent
# One update of 2 worlds x 4 decisions, no checkpoint, two evaluation episodes of 10 steps.
TINY = ["--env-steps", "8", "--worlds", "2", "--resolution", "12", "--rollout", "4", "--episodes", "2",
        "--checkpoint-every", "0", "--env-option", "max_steps=10"]


@pytest.fixture(scope="module")
def tiny_commons(tmp_path_factory):
    """A tiny commons run from pixels (a mixed-motive task): its folder."""
    out = tmp_path_factory.mktemp("social") / "commons"
    assert run.main(["--env", "commons", "--out", str(out), *TINY]) == 0
    return out


def test_a_mixed_motive_run_records_its_outcomes_and_a_replay_of_its_actor_gives_them_again(tiny_commons, tmp_path):
    recorded = social.run_outcomes(tiny_commons)
    assert set(recorded) == {"policy", "random", "heuristic"}
    assert all(set(outcomes) == set(social.OUTCOMES) for outcomes in recorded.values())
    result = json.loads((tiny_commons / "result.json").read_text())
    assert recorded["policy"]["efficiency"] == result["evaluation"]["policy"]["efficiency_mean"]
    measured = social.measure(tiny_commons)
    assert measured["reproduces_run"] is True and measured["episodes"] == 2
    assert measured["outcomes"] == recorded  # the same worlds, policies and options: the same outcomes
    assert measured["return"]["policy"] == result["evaluation"]["policy"]["mean"]

    # A run from before the metrics: its result.json lacks them, and its social.json stands in.
    old = tmp_path / "old"
    shutil.copytree(tiny_commons, old)
    for name in ("policy", "random", "heuristic"):
        for key in social.OUTCOMES:
            del result["evaluation"][name][f"{key}_mean"]
    (old / "result.json").write_text(json.dumps(result))
    assert social.run_outcomes(old) is None
    (old / social.SOCIAL).write_text(json.dumps(measured))
    assert social.run_outcomes(old) == recorded


def test_measure_refuses_a_task_without_outcomes_and_a_run_without_its_actor(tiny_commons, tmp_path):
    no_actor = tmp_path / "no_actor"
    shutil.copytree(tiny_commons, no_actor)
    (no_actor / "actor.pt").unlink()
    with pytest.raises(ValueError, match=r"no_actor kept no actor\.pt"):
        social.measure(no_actor)
    spread = tmp_path / "spread"
    shutil.copytree(tiny_commons, spread)
    result = json.loads((spread / "result.json").read_text())
    (spread / "result.json").write_text(json.dumps({**result, "env": "spread"}))
    with pytest.raises(ValueError, match="spread is not a mixed-motive task"):
        social.measure(spread)
    assert social.run_outcomes(tmp_path / "nothing") is None


def test_a_task_without_runs_or_kept_actors_says_so_in_every_cell(tmp_path):
    rows = social.task_rows("clean_up", tmp_path)
    assert [row[0] for row in rows] == ["random", "heuristic", "MAPPO"]
    assert all(cell == "no trained runs yet" for row in rows for cell in row[2:])
    folder = run_folder(tmp_path, "commons", "state", 0)  # a run, but no outcomes and no actor
    folder.mkdir(parents=True)
    (folder / "result.json").write_text(json.dumps({"evaluation": {"policy": {"mean": 1.0}}}))
    rows = social.task_rows("commons", tmp_path)
    assert all(cell.startswith("no kept actor to replay") for row in rows for cell in row[2:])


def test_update_page_writes_between_the_markers_and_nowhere_else(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(f"before\n{social.START}\nold\n{social.END}\nafter\n")
    assert social.update_page(page, tmp_path)
    text = page.read_text()
    assert text.startswith(f"before\n{social.START}\n| task | policy | seeds |")
    assert text.endswith(f"{social.END}\nafter\n")
    assert "old" not in text and text.count("| clean_up | random |") == 1
    bare = tmp_path / "bare.md"
    bare.write_text("no markers\n")
    assert not social.update_page(bare, tmp_path) and bare.read_text() == "no markers\n"


def test_the_committed_outcomes_are_the_ones_shown_and_every_kept_actor_was_replayed():
    """docs/results.md's table is social.table() of the committed runs; each kept actor of a mixed-motive row
    has outcomes (its result.json's or a social.json whose replay gave the run's returns episode for episode)."""
    root = ROOT_DIR / ROOT
    results = (ROOT_DIR / "docs" / "results.md").read_text()
    assert f"{social.START}\n{social.table(root)}\n{social.END}" in results
    assert set(social.mixed_motive_tasks()) == {"capture_flag", "clean_up", "commons", "coop_mining", "matrix",
                                               "territory"}
    for env in social.mixed_motive_tasks():
        for obs in RUNS[env]:
            for seed in SEEDS:
                folder = run_folder(root, env, obs, seed)
                if (folder / "actor.pt").is_file():
                    assert social.run_outcomes(folder) is not None, folder
                if (folder / social.SOCIAL).is_file():
                    assert json.loads((folder / social.SOCIAL).read_text())["reproduces_run"] is True, folder
