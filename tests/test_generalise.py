"""The generalisation workflow of a saved run: one policy protocol for every evaluation, load_policy's
training condition, ``marl_render.generalise`` (train / test levels / held-out looks beside random and
the heuristic), the evaluate CLI's --levels and --appearance."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
import torch

from marl_render import evaluate as heldout_evaluation
from marl_render import generalise as generalisation
from marl_render.baselines.networks import Actor
from marl_render.envs import evaluation
from marl_render.policies import CallablePolicy, RandomPolicy, as_policy, heuristic_policy, load_policy


def saved_run(folder: Path, *, seed: int = 0, levels=5, appearance="train") -> str:
    """A forage run folder as python -m marl_render.baselines --levels 5 --appearance train writes it."""
    folder.mkdir(parents=True)
    hp = {"resolution": 16, "grayscale": False, "frames": 1, "action_repeat": 1, "hidden": 8, "encoder": "conv",
          "precision": "float32"}
    torch.manual_seed(seed)
    torch.save(Actor("pixels", (16, 16, 3), 3, 5, 8).state_dict(), folder / "actor.pt")
    result = {"env": "forage", "obs": "pixels", "hyperparameters": hp, "seeds": {"train": seed},
              "env_options": {} if appearance is None else {"appearance": appearance},
              "train_options": {} if levels is None else {"levels": levels}}
    (folder / "result.json").write_text(json.dumps(result))
    return str(folder)


SHORT = dict(episodes=2, seed=3, resolution=8, max_steps=12)


def test_every_evaluation_takes_objects_with_act_and_functions_alike(tmp_path):
    # envs.evaluation.evaluate took functions only: load_policy's object raised "not callable".
    function = evaluation.evaluate("forage", evaluation.heuristic_policy, **SHORT)
    as_object = evaluation.evaluate("forage", heuristic_policy(), **SHORT)
    assert as_object["per_episode"] == function["per_episode"]
    assert evaluation.evaluate("forage", RandomPolicy(1), **SHORT)["episodes"] == 2
    run = saved_run(tmp_path / "run")
    loaded = evaluation.evaluate("forage", load_policy(run), **{**SHORT, "resolution": 16})
    assert len(loaded["per_episode"]) == 2 and all(math.isfinite(v) for v in loaded["per_episode"])
    # ... and marl_render.evaluate's took objects only: a function was taken for a spec string.
    rows = {label: heldout_evaluation.evaluate(policy, ["forage/two_with_lazy"], episodes=2, max_steps=12)[0]
            for label, policy in (("name", "heuristic"), ("function", evaluation.heuristic_policy))}
    assert rows["function"]["focal_return_mean"] == rows["name"]["focal_return_mean"]
    assert rows["function"]["policy"] == "heuristic_policy"
    random_rows = heldout_evaluation.evaluate(evaluation.random_policy, ["forage/two_with_lazy"], episodes=2,
                                              max_steps=12)
    assert math.isfinite(random_rows[0]["focal_return_mean"])


def test_as_policy_is_the_one_adapter():
    policy = heuristic_policy()
    assert as_policy(policy) is policy
    wrapped = as_policy(evaluation.random_policy, torch.Generator().manual_seed(4))
    assert isinstance(wrapped, CallablePolicy) and wrapped.name == "random_policy"
    with pytest.raises(TypeError, match=r"policy must be an object with act.*got .random."):
        as_policy("random")
    with pytest.raises(TypeError, match="policy must be an object with act"):
        evaluation.evaluate("forage", 3, **SHORT)


def test_load_policy_keeps_the_levels_and_looks_it_trained_with(tmp_path):
    policy = load_policy(saved_run(tmp_path / "run", levels=200, appearance="train"))
    assert policy.env_kwargs == {"resolution": 16, "grayscale": False, "levels": 200, "appearance": "train"}
    plain = load_policy(saved_run(tmp_path / "plain", levels=None, appearance=None))
    assert plain.env_kwargs == {"resolution": 16, "grayscale": False}


def test_generalise_scores_train_test_and_held_out_looks_beside_random_and_the_heuristic(tmp_path):
    runs = [saved_run(tmp_path / f"seed{seed}", seed=seed) for seed in (0, 1)]
    result = generalisation.generalise(runs, episodes=2, seed=3, max_steps=12)
    assert [entry["run"] for entry in result["runs"]] == runs
    first = result["runs"][0]["sets"]
    assert list(first) == ["training levels", "test levels", "test levels, held-out looks"]
    assert [(c["levels"], c["appearance"]) for c in first.values()] == [(5, "train"), ("published", "train"),
                                                                         ("published", "heldout")]
    same = dict(episodes=2, seed=3, resolution=16, grayscale=False, max_steps=12)
    for name, levels, looks in (("training levels", 5, "train"), ("test levels, held-out looks", "published",
                                                                   "heldout")):
        alone = evaluation.evaluate("forage", load_policy(runs[0]), levels=levels, appearance=looks, **same)
        assert first[name]["per_episode"] == alone["per_episode"]
        assert first[name]["return"]["mean"] == pytest.approx(alone["mean"])
        assert first[name]["random"] == evaluation.evaluate("forage", evaluation.random_policy, levels=levels,
                                                            **same)["mean"]
        assert first[name]["heuristic"] == evaluation.evaluate("forage", evaluation.heuristic_policy,
                                                               levels=levels, **same)["mean"]
    for cell in first.values():
        assert cell["return"]["low"] <= cell["return"]["mean"] <= cell["return"]["high"]
        assert cell["gap"] == pytest.approx(first["training levels"]["return"]["mean"] - cell["return"]["mean"])
    summary = result["summary"]["forage"]
    assert summary["runs"] == 2
    returns = [entry["sets"]["test levels"]["return"]["mean"] for entry in result["runs"]]
    assert summary["sets"]["test levels"]["return"]["mean"] == pytest.approx(sum(returns) / 2)
    assert "| test levels, held-out looks |" in generalisation.table(result)


def test_generalise_command_prints_the_table_and_writes_strict_json(tmp_path, capsys):
    run = saved_run(tmp_path / "run")
    assert generalisation.main([run, "--episodes", "2", "--max-steps", "6", "--out", str(tmp_path / "out" / "g")]) == 0
    printed = capsys.readouterr().out
    assert "## forage" in printed and "| training levels |" in printed and "Across 1 run(s)" in printed
    text = (tmp_path / "out" / "g.json").read_text()
    loaded = json.loads(text, parse_constant=lambda token: pytest.fail(f"bare {token} in the JSON"))
    assert loaded["runs"][0]["sets"]["test levels"]["levels"] == "published"
    assert (tmp_path / "out" / "g.md").read_text().strip() == printed.strip()
    for argv, message in (([str(tmp_path)], "RUN must be a run folder"), ([run, "--episodes", "1"], "--episodes"),
                          ([run, "--out", str(tmp_path)], "--out must be a file prefix")):
        with pytest.raises(SystemExit):
            generalisation.main(argv)
        assert message in capsys.readouterr().err


def test_evaluate_cli_takes_levels_and_appearance(tmp_path, capsys):
    argv = ["--policy", "heuristic", "--scenario", "forage/two_with_lazy", "--episodes", "2", "--max-steps", "8"]
    assert heldout_evaluation.main([*argv, "--levels", "published", "--appearance", "heldout"]) == 0
    row = json.loads(capsys.readouterr().out)[0]
    direct = heldout_evaluation.scenario_returns("heuristic", "forage/two_with_lazy", episodes=2, max_steps=8,
                                                 levels="published", appearance="heldout")
    assert row["focal_return_mean"] == pytest.approx(float(direct["focal"].mean()))
    with pytest.raises(SystemExit):
        heldout_evaluation.main([*argv, "--levels", "0"])
    assert "--levels" in capsys.readouterr().err


def test_the_held_out_pages_mean_gap_is_normalised_per_scenario():
    # Raw gaps of 10 (scale 100) and 0.1 (scale 1) averaged to 5.05; normalised they are 0.1 each.
    rows = [{"generalisation_gap": 10.0, "random_return": 0.0, "heuristic_return": 100.0},
            {"generalisation_gap": 0.1, "random_return": -1.0, "heuristic_return": 0.0},
            {"generalisation_gap": 3.0, "random_return": 2.0, "heuristic_return": 2.0}]  # no scale: left out
    assert heldout_evaluation.normalised_gaps(rows) == pytest.approx([0.1, 0.1])
    line = heldout_evaluation.mean_gap_lines(rows)[-1]
    assert line.startswith("Mean generalisation gap over 2 scenarios, each normalised by its heuristic - random: 0.10")
    assert "1 scenario(s) without a scale" in line
    page = heldout_evaluation.heldout_page({"p": [{**rows[0], "scenario": "s", "tags": "visitor",
                                                   "focal_return_mean": 1.0, "focal_return_std": 0.0,
                                                   "background_return_mean": 0.0, "normalised_score": 0.5,
                                                   "bots_sampled": {}}]}, "cmd", "note")
    assert "Mean generalisation gap over 1 scenarios, each normalised by its heuristic - random: 0.10." in page


DOCS = Path(__file__).resolve().parent.parent / "docs"


def test_the_generalisation_page_shows_the_commands_real_output(tmp_path):
    from marl_render.baselines import generalisation as study

    page = (DOCS / "generalisation.md").read_text()
    assert study.report(str(DOCS / "generalisation"), str(tmp_path / "page.md")) == page  # regenerated, not edited
    example = (DOCS / "generalisation" / "example.md").read_text()
    assert "**tiny run**" in page and "python -m marl_render.generalise out/gen_example/seed0" in page
    # the example is the command's own table: its runs and sets, as table() writes them
    for run in ("out/gen_example/seed0", "out/gen_example/seed1"):
        for name in generalisation.SETS:
            assert f"| {run} | {name} |" in example
    assert "Across 2 run(s)" in example and "Held-out scenarios of out/gen_example/seed1:" in example


def test_interactive_play_is_linked_from_the_readme_and_the_docs_index(capsys):
    readme = (DOCS.parent / "README.md").read_text()
    index = (DOCS / "index.md").read_text()
    assert "[play a task](docs/play.md)" in readme
    assert ":link: play" in index and "\nplay\n" in index  # a card and the toctree
    page = (DOCS / "play.md").read_text()
    from marl_render import play

    with pytest.raises(SystemExit) as exit:
        play.main(["--help"])
    assert exit.value.code == 0
    shown = capsys.readouterr().out
    for option in sorted(set(re.findall(r"(--[a-z]+)", page))):  # every option the page names is one of play's
        assert re.search(rf"{option}\b", shown), option


def test_generalise_takes_a_run_of_a_module_class_task_and_names_what_it_cannot_do(tmp_path, capsys, monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent))
    folder = tmp_path / "duel"
    folder.mkdir()
    torch.save(Actor("state", (8,), 2, 5, 8).state_dict(), folder / "actor.pt")
    hp = {"resolution": 8, "grayscale": False, "frames": 1, "action_repeat": 1, "hidden": 8, "encoder": "conv",
          "precision": "float32"}
    (folder / "result.json").write_text(json.dumps({"env": "selfplay_user_task:BeaconDuel", "obs": "state",
                                                    "hyperparameters": hp}))
    # registered from the run's own env name (no --import), then refused by name: the task has no levels
    with pytest.raises(SystemExit):
        generalisation.main([str(folder), "--episodes", "2"])
    err = capsys.readouterr().err
    assert "task 'selfplay_user_task:BeaconDuel' draws its resets with spawn(generator), so it has no levels" in err
