"""The baselines report (docs/baselines.md, the pictures, marl_eval.json) on synthetic result.json
files of the step-budget schema written here, the runs' folders, and the published commands."""
import json
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from marl_render.baselines import marl_eval, published, report, run, stats
from marl_render.baselines.settings import step_budget, task_hyperparameters
from marl_render.envs import list_envs

BUDGET = 100_000
CHECKPOINTS = (25_000, 50_000, 100_000)
RANDOM, HEURISTIC = [-3.0, -1.0], [6.0, 8.0]  # per-episode returns: means -2 and 7
# (task, obs) -> each seed's per-episode returns of the final greedy policy
POLICIES = {
    ("spread", "pixels"): [[4.0, 6.0], [1.0, 2.0], [5.0, 6.0]],  # means 5, 1.5, 5.5: every seed above random
    ("spread", "state"): [[6.0, 7.0], [6.0, 8.0], [5.0, 6.0]],
    ("commons", "pixels"): [[0.0, 2.0], [-4.0, -2.0], [3.0, 5.0]],  # seed 1 (-3) below random (-2)
}


def evaluation(returns: list) -> dict:
    return {"mean": float(np.mean(returns)), "std": float(np.std(returns)), "min": min(returns), "max": max(returns),
            "episodes": len(returns), "per_episode": returns}


def synthetic_result(env: str, obs: str, seed: int, returns: list) -> dict:
    """A result.json of the step-budget trainer's schema with made-up numbers."""
    steps = np.linspace(BUDGET / 10, BUDGET, 10).astype(int).tolist()
    return {
        "env": env, "obs": obs, "seeds": {"train": seed, "evaluation": 2000}, "evaluation_set": "publication",
        "budget": {"env_steps": BUDGET, "updates": None, "max_minutes": None}, "budget_minutes": None,
        "truncated": False, "env_steps": BUDGET, "updates": 10, "wall_clock_seconds": 60.0 + seed,
        "training_seconds": 50.0 + seed, "env_seconds_in_training": 20.0, "stage_seconds": {"env": 20.0},
        "curve": [{"env_steps": s, "seconds": 5.0 * (i + 1) + seed, "episode_return": None if i == 0 else i + seed}
                  for i, s in enumerate(steps)],
        "checkpoints": [{"env_steps": s, "updates": i, "seconds": s / 2000, "mean": i + 0.5 * seed, "std": 0.0,
                         "min": i + 0.5 * seed, "max": i + 0.5 * seed, "episodes": 2,
                         "per_episode": [i + 0.5 * seed] * 2} for i, s in enumerate(CHECKPOINTS)],
        "evaluation": {"policy": evaluation(returns), "random": evaluation(RANDOM), "heuristic": evaluation(HEURISTIC)},
        "hyperparameters": {**report.DEFAULTS, "worlds": 4}, "env_options": {}, "train_options": {"shaping": 0.5},
        "command": "python -m marl_render.baselines ...", "versions": {"torch": "2.13.0+cpu"},
    }


def write_runs(root, policies=POLICIES):
    for (env, obs), per_seed in policies.items():
        for seed, returns in enumerate(per_seed):
            path = published.run_folder(root, env, obs, seed) / "result.json"
            path.parent.mkdir(parents=True)
            path.write_text(json.dumps(synthetic_result(env, obs, seed, returns)))


# The best constant action on the runs' worlds: spread's 0.0 (below every seed), commons' 10.0 (above them).
CONSTANTS = {"spread": 0.0, "commons": 10.0}
# Spread seed 0's ablated returns (its own: 4.0, 6.0): zeros costs return on both episodes, shifted on one only.
ABLATED = {"zeros": [1.0, 2.0], "shifted": [4.0, 5.0]}


def write_baselines(results, ablated=ABLATED):
    """constant_actions.json for CONSTANTS and spread pixels seed 0's ablation.json."""
    constants = {env: {"evaluation_set": "publication", "seed": 2000, "env_options": {}, **evaluation([mean, mean]),
                       "action": 3, "per_action": [mean - 1, mean - 1, mean - 1, mean]}
                 for env, mean in CONSTANTS.items()}
    (results / "constant_actions.json").write_text(json.dumps(constants))
    views = {"none": evaluation(POLICIES[("spread", "pixels")][0]), **{v: evaluation(r) for v, r in ablated.items()}}
    (results / "spread" / "seed0" / "ablation.json").write_text(json.dumps(
        {"run": "x", "env": "spread", "evaluation_set": "publication", "seed": 2000, "episodes": 2, "views": views,
         "reproduces_run": True}))


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    results = root / "docs" / "baselines"
    write_runs(results)
    readme = root / "README.md"
    readme.write_text(f"intro\n{report.START}\nold table\n{report.END}\nrest\n")
    write_baselines(results)
    out = root / "docs" / "baselines.md"
    assert report.main(["--results", str(results), "--out", str(out), "--readme", str(readme)]) == 0
    rows = {line.split("|")[1].strip(): line.split("|")[2:-1] for line in out.read_text().splitlines()
            if line.startswith("| ") and not line.startswith("| seed") and not line.startswith("| env steps")}
    return {"results": results, "text": out.read_text(), "rows": rows, "readme": readme.read_text()}


def test_rows_show_the_mean_its_interval_and_every_seed(written):
    rows = written["rows"]
    assert set(list_envs()) <= set(rows)
    (random, heuristic, pixels, state, above, normalised, scored_on, pixel_cost, state_cost, constant,
     learned) = rows["spread"]
    assert (random.strip(), heuristic.strip()) == ("-2.00", "7.00")
    # 3 seeds: the interval of the mean is exactly [lowest, highest] seed
    assert pixels.strip() == "4.00 [1.50, 5.50]; seeds 0/1/2: 5.00 / 1.50 / 5.50"
    assert state.strip() == "6.33 [5.50, 7.00]; seeds 0/1/2: 6.50 / 7.00 / 5.50"
    assert above.strip() == "yes; yes"
    seed_scores = (np.array([5.0, 1.5, 5.5]) + 2) / 9 * 100
    assert normalised.strip() == (f"{seed_scores.mean():.0f}% [{seed_scores.min():.0f}%, {seed_scores.max():.0f}%]; "
                                  "seeds 0/1/2: " + " / ".join(f"{v:.0f}%" for v in seed_scores))
    assert scored_on.strip() == "publication (seed 2000)"
    assert pixel_cost.strip() == "100,000 steps; 1.0 min (1.0-1.0)"
    commons = rows["commons"]
    assert commons[3].strip() == "–" and commons[4].strip() == "no; –"  # seed 1 below random; no state runs
    assert [cell.strip() for cell in rows["cartpole"]] == ["–"] * 4 + ["–; –"] + ["–"] * 5 + ["–; –"]
    assert constant.strip() == "0.00 (action 3)"
    # shifted views cost seed 0 a return of 0.5 on average, with a paired interval that reaches below 0
    assert learned.strip() == "no (view ablation costs no return); yes"
    assert rows["commons"][-2:] == [" 10.0 (action 3) ",
                                    " no (not above random, not above the best constant action); – "]


def test_document_says_final_policy_and_lists_commands_and_checkpoints(written):
    text = written["text"]
    assert "**Rows are the final policy only**" in text and "none is ever picked for a row" in text
    assert ("python -m marl_render.baselines --env spread --seed 1 --env-steps 100000 --eval-set publication "
            "--episodes 2 --worlds 4") in text
    assert "--train-option shaping=0.5 --out docs/baselines/spread/seed1" in text
    assert "--obs state --seed 2" in text and "--out docs/baselines/spread-state/seed2" in text
    section = text.split("### spread from pixels")[1].split("###")[0]
    assert "| env steps | seed 0 | seed 1 | seed 2 |" in section
    for i, step in enumerate(CHECKPOINTS):  # checkpoint i of seed k returned i + k / 2
        assert f"| {step:,} | {i:.2f} | {i + 0.5:.2f} | {i + 1:.2f} |" in section
    assert "Learned minus random, mean over seeds: 6.00 [3.50, 7.50] (above random)." in section
    assert "| 1 | 1.50 ± 0.50 (2) | -2.00 ± 1.00 | 7.00 ± 1.00 | publication (seed 2000) | 100,000 |" in section


def test_aggregate_across_tasks_matches_stats(written):
    normalised = {env: (np.array([np.mean(r) for r in POLICIES[(env, "pixels")]]) + 2) / 9
                  for env in ("commons", "spread")}
    matrix = np.stack([normalised["commons"], normalised["spread"]], axis=1)  # tasks in list_envs() order
    iqm = stats.stratified_bootstrap(matrix, stats.iqm)
    assert (f"from pixels, 3 seeds x 2 tasks (commons, spread): IQM {iqm.point:.2f} [{iqm.low:.2f}, {iqm.high:.2f}]"
            in written["text"])
    assert "from state, 3 seeds x 1 tasks (spread)" in written["text"]
    assert "![normalised scores across tasks](baselines/aggregate.png)" in written["text"]


@pytest.mark.parametrize("picture", ["spread/curves.png", "spread-state/curves.png", "commons/curves.png",
                                     "aggregate.png"])
def test_pictures_are_drawn(written, picture):
    with Image.open(written["results"] / picture) as image:
        pixels = np.asarray(image.convert("L"))
    assert pixels.shape[0] >= 380 and pixels.shape[1] >= 1000
    assert pixels.min() < 100 < pixels.max()  # lines drawn on a light background


def test_readme_table_is_rewritten_short(written):
    readme = written["readme"]
    assert readme.startswith("intro\n") and readme.endswith("\nrest\n") and "old table" not in readme
    row = next(line for line in readme.splitlines() if line.startswith("| spread |"))
    assert row == ("| spread | -2.00 | 7.00 | 4.00 [1.50, 5.50] | 6.33 [5.50, 7.00] | yes; yes | 0.00 (action 3) "
                   "| no (view ablation costs no return); yes |")


def test_marl_eval_layout(written):
    data = json.loads((written["results"] / "marl_eval.json").read_text())
    assert list(data) == ["marl_render"] and set(data["marl_render"]) == {"spread", "commons"}
    assert set(data["marl_render"]["spread"]) == {"mappo_pixels", "mappo_state"}
    runs = data["marl_render"]["spread"]["mappo_pixels"]
    assert list(runs) == ["seed_0", "seed_1", "seed_2"]
    seed1 = runs["seed_1"]
    # the checkpoint at the budget's end (100,000) is the final policy: absolute_metrics holds it
    assert list(seed1) == ["step_0", "step_1", "absolute_metrics"]
    assert [seed1[f"step_{i}"] for i in range(2)] == [{"step_count": s, "return": [i + 0.5] * 2}
                                                      for i, s in enumerate(CHECKPOINTS[:2])]
    assert seed1["absolute_metrics"] == {"return": POLICIES[("spread", "pixels")][1]}
    # commons has no state runs: marl-eval's tools would refuse the file, and the report says so
    problems = marl_eval.problems(data)
    assert problems == ["marl_render: tasks differ in algorithms (commons: mappo_pixels; spread: mappo_pixels, "
                        "mappo_state)"]
    assert problems[0] in written["text"]


def test_marl_eval_same_shape_everywhere_has_no_problems(tmp_path):
    write_runs(tmp_path, {key: value for key, value in POLICIES.items() if key[1] == "pixels"})
    data = marl_eval.layout(report.load_results(tmp_path))
    assert marl_eval.problems(data) == []
    del data["marl_render"]["spread"]["mappo_pixels"]["seed_2"]["step_1"]
    assert marl_eval.problems(data) == ["marl_render: runs or steps differ (seed_0, seed_1, seed_2 with 2 steps: "
                                        "commons/mappo_pixels; seed_0, seed_1, seed_2 with 1/2 steps: "
                                        "spread/mappo_pixels)"]


def test_marl_eval_steps_leave_out_the_checkpoint_at_the_budgets_end():
    """Whether a checkpoint lands on the last update depends on how the budget divides into updates:
    the exported steps are the same either way (that checkpoint is the final policy's)."""
    result = synthetic_result("spread", "pixels", 0, [1.0, 2.0])
    before_end = marl_eval.run_entry(result)
    result["checkpoints"] = result["checkpoints"][:2]  # none at the budget's end
    assert marl_eval.run_entry(result) == before_end
    assert [before_end[k]["step_count"] for k in ("step_0", "step_1")] == list(CHECKPOINTS[:2])
    result["checkpoints"] = []  # a run from before the checkpoints: its final evaluation is its one step
    assert marl_eval.run_entry(result)["step_0"] == {"step_count": BUDGET, "return": [1.0, 2.0]}


@pytest.mark.parametrize("ablated, constant, expected", [
    # both views cost return on every episode (of the one ablated seed)
    ({"zeros": [1.0, 2.0], "shifted": [1.0, 3.5]}, 0.0, "yes (view ablation of seed 0 only)"),
    ({"zeros": [1.0, 2.0], "shifted": [4.0, 6.0]}, 0.0, "no (view ablation costs no return)"),  # shifted: nothing
    ({"zeros": [1.0, 2.0], "shifted": [1.0, 3.5]}, 5.0, "no (not above the best constant action)"),  # seed 1 1.5
    (None, 0.0, "not judged (no view ablation)"),
    ({"zeros": [1.0, 2.0], "shifted": [1.0, 3.5]}, None, "not judged (no best constant action on its worlds)"),
])
def test_a_row_counts_as_learned_only_above_random_the_constant_action_and_with_its_view(tmp_path, ablated, constant,
                                                                                        expected):
    write_runs(tmp_path, {("spread", "pixels"): POLICIES[("spread", "pixels")]})
    if ablated is not None:
        write_baselines(tmp_path, ablated)
    runs = report.load_results(tmp_path)
    constants = None if constant is None else {"evaluation_set": "publication", "seed": 2000, "mean": constant}
    assert report.learned_verdict(runs["spread"]["pixels"], constants) == expected
    # the same constant scored on other worlds than the runs' judges nothing
    assert report.above_constant(runs["spread"]["pixels"], {"evaluation_set": "development", "seed": 1000,
                                                            "mean": -100.0}) is None


def test_the_view_ablation_and_the_constant_action_are_written_under_the_task(written):
    section = written["text"].split("### spread from pixels")[1].split("###")[0]
    assert "- Best constant action on the publication worlds: action 3, 0.00 (each action, by index: -1.00, -1.00, " \
           "-1.00, 0.00)." in section
    # zeros: drops 3 and 4 (mean 3.5, std 0.71 over 2 episodes); shifted: drops 0 and 1
    half = 1.96 * np.std([3.0, 4.0], ddof=1) / np.sqrt(2)
    assert (f"- View ablation of seed 0 (2 episodes of its evaluation worlds): as trained 5.00; zeros 1.50 (drop "
            f"3.50 [{3.5 - half:.2f}, {3.5 + half:.2f}]); shifted 4.50 (drop 0.50 [") in section


def test_older_flat_runs_are_read_only_where_no_seed_folders_exist(tmp_path):
    write_runs(tmp_path, {("spread", "pixels"): POLICIES[("spread", "pixels")]})
    old = synthetic_result("spread", "pixels", 0, [-100.0, -100.0])  # replaced by the seed folders
    older = {k: v for k, v in synthetic_result("tag", "state", 0, [1.0, 3.0]).items()
             if k not in ("evaluation_set", "budget", "checkpoints", "truncated")}
    for name, result in (("spread", old), ("tag-state", {**older, "budget_minutes": 5.0})):
        (tmp_path / name).mkdir(exist_ok=True)
        (tmp_path / name / "result.json").write_text(json.dumps(result))
    runs = report.load_results(tmp_path)
    assert [r["evaluation"]["policy"]["mean"] for r in runs["spread"]["pixels"]] == [5.0, 1.5, 5.5]
    tag = runs["tag"]["state"]
    assert len(tag) == 1 and tag[0]["evaluation_set"] == "development"
    row = next(line for line in report.table(runs).splitlines() if line.startswith("| tag |"))
    assert "| 2.00 (seed 0 only) | –; not judged (1 seed) |" in row
    assert "| development (seed 2000) | – | 5 min wall-clock budget: 100,000 steps; 1.0 min |" in row
    assert "--budget-minutes 5 --eval-seed 2000" in report.reproducing_command(tag[0])


def test_update_budgets_truncated_runs_and_other_seeds_are_said(tmp_path):
    write_runs(tmp_path, {("tag", "pixels"): [[1.0], [2.0]]})
    path = tmp_path / "tag" / "seed1" / "result.json"
    result = json.loads(path.read_text())
    result.update(budget={"env_steps": None, "updates": 40, "max_minutes": 2.0}, truncated=True,
                  evaluation_set="seed 5", seeds={"train": 1, "evaluation": 5})
    del result["hyperparameters"]["init"]  # a run from before init was recorded: torch's draws
    path.write_text(json.dumps(result))
    runs = report.load_results(tmp_path)
    assert report.cost_cell(runs["tag"]["pixels"]) == ("100,000 steps / 40 updates; 1.0 min (1.0-1.0); 1 of 2 "
                                                       "truncated by --max-minutes")
    assert report.scored_on(runs["tag"]) == "publication (seed 2000), seed 5"
    assert "--seed 1 --updates 40 --max-minutes 2 --eval-seed 5 --episodes 1" in report.reproducing_command(
        runs["tag"]["pixels"][1])
    assert "--init torch" in report.reproducing_command(runs["tag"]["pixels"][1])
    assert "--init orthogonal" in report.reproducing_command(runs["tag"]["pixels"][0])
    assert "| seed 5 | 100,000 (truncated) |" in "\n".join(report.seeds_table(runs["tag"]["pixels"]))


@pytest.mark.parametrize("content, message", [
    ('{"env": "spread", "obs": "pix', "not a readable result.json"),
    (json.dumps({"env": "spread", "obs": "pixels", "seeds": {"train": 0}, "env_steps": 5}),
     "result.json has no evaluation.policy.mean"),
    (json.dumps({**synthetic_result("spread", "pixels", 0, [1.0]), "obs": "rgb"}), "obs must be one of"),
    (json.dumps({**synthetic_result("spread", "pixels", 0, [1.0]), "seeds": {"train": "0"}}),
     "seeds.train must be an int, got '0'"),
    ("[1, 2]", "result.json has no env"),
])
def test_bad_result_files_are_named(tmp_path, content, message):
    path = tmp_path / "spread" / "seed0" / "result.json"
    path.parent.mkdir(parents=True)
    path.write_text(content)
    with pytest.raises(ValueError, match=message) as error:
        report.load_results(tmp_path)
    assert str(path) in str(error.value)


def test_bad_policy_mean_is_named(tmp_path):
    result = synthetic_result("spread", "pixels", 0, [1.0])
    result["evaluation"]["policy"]["mean"] = float("nan")
    (tmp_path / "spread" / "seed0").mkdir(parents=True)
    (tmp_path / "spread" / "seed0" / "result.json").write_text(json.dumps(result))
    with pytest.raises(ValueError, match="evaluation.policy.mean must be a finite number, got nan"):
        report.load_results(tmp_path)


def test_two_runs_of_one_seed_are_refused(tmp_path):
    write_runs(tmp_path, {("spread", "pixels"): [[1.0]]})
    copy = tmp_path / "spread" / "seed7" / "result.json"  # a seed-0 run in another seed's folder
    copy.parent.mkdir()
    copy.write_text((tmp_path / "spread" / "seed0" / "result.json").read_text())
    with pytest.raises(ValueError, match="two runs of spread from pixels with training seed 0"):
        report.load_results(tmp_path)


def report_error(argv, capsys) -> str:
    """report.main's exit on bad input: status 2 and one error line, no traceback."""
    with pytest.raises(SystemExit) as exit_:
        report.main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len([line for line in err.splitlines() if "error:" in line]) == 1
    return err


def test_readme_without_markers_is_refused_before_writing(tmp_path, capsys):
    write_runs(tmp_path / "runs", {("spread", "pixels"): [[1.0]]})
    readme, out = tmp_path / "README.md", tmp_path / "baselines.md"
    readme.write_text("no markers\n")
    assert "markers" in report_error(["--results", str(tmp_path / "runs"), "--out", str(out), "--readme", str(readme)],
                                     capsys)
    assert readme.read_text() == "no markers\n" and not out.exists()
    assert not (tmp_path / "runs" / "marl_eval.json").exists()
    assert "--results must be a folder of runs" in report_error(
        ["--results", str(tmp_path / "nothing"), "--out", str(out), "--readme", ""], capsys)


def test_the_report_cli_names_a_broken_run_in_one_line(tmp_path, capsys):
    write_runs(tmp_path / "runs", {("spread", "pixels"): [[1.0]]})
    argv = ["--results", str(tmp_path / "runs"), "--out", str(tmp_path / "baselines.md"), "--readme", ""]
    run_file = tmp_path / "runs" / "spread" / "seed0" / "result.json"
    copy = tmp_path / "runs" / "spread" / "seed7" / "result.json"  # a seed-0 run in another seed's folder
    copy.parent.mkdir()
    copy.write_text(run_file.read_text())
    assert "two runs of spread from pixels with training seed 0" in report_error(argv, capsys)
    copy.write_text(run_file.read_text()[:40])  # truncated
    assert f"{copy}: not a readable result.json" in report_error(argv, capsys)
    assert not (tmp_path / "baselines.md").exists()


def test_published_commands_cover_every_task_and_seed():
    published.check_complete()
    commands = published.commands()
    tasks = published.published_tasks()
    assert sorted(tasks + list(published.PENDING)) == sorted(list_envs()) and len(tasks) >= 9
    assert set(published.RUNS) == set(list_envs())  # the pending tasks' commands too: `--run` trains them
    assert len(commands) == len(published.RUNS) * 2 * len(published.SEEDS) and len(published.SEEDS) >= 3
    for env in published.RUNS:
        for obs in published.OBSERVATIONS:
            entry = published.RUNS[env][obs]
            for seed in published.SEEDS:
                argv = published.run_argv(env, obs, seed)
                line = " ".join(argv)
                assert f"--seed {seed} --env-steps {entry.env_steps} --eval-set publication" in line
                assert line.endswith(f"--out docs/baselines/{published.folder(env, obs)}/seed{seed}")
                assert entry.env_steps == step_budget(env, obs)  # one table of budgets: the learner's
                args = run.parse_args(argv)  # the whole command, as the learner reads it
                assert (args.env, args.obs, args.seed) == (env, obs, seed)
                assert (args.env_steps, args.updates, args.eval_set) == (entry.env_steps, None, "publication")
                assert dict(args.env_option) == dict(entry.env_options)
                assert dict(args.train_option) == dict(entry.train_options)
                assert all(getattr(args, k) == v for k, v in entry.hyperparameters.items())


def test_a_commands_switches_are_written_either_way_and_read_back():
    """A False switch is written as --no-X: left out, the learner would take the task's default (overlap
    is on by default, so a run without it could not be reproduced from its shown command)."""
    for overlap, grayscale in ((True, True), (False, False), (False, True)):
        argv = published.learner_argv("spread", "pixels", 3, budget=["--env-steps", "1024"], evaluation=[],
                                      hyperparameters={"overlap": overlap, "grayscale": grayscale, "init": "torch"},
                                      env_options={}, train_options={}, out="runs/x")
        assert ("--overlap" in argv, "--no-overlap" in argv) == (overlap, not overlap)
        args = run.parse_args(argv)
        assert (args.overlap, args.grayscale, args.init, args.seed) == (overlap, grayscale, "torch", 3)


def test_every_published_command_trains_with_its_rows_published_init():
    """A row's seeds differ in the seed alone: each entry's init is that of the row's published runs
    (result.json; runs from before the init option had torch's default), so `make baselines` trains
    seeds 1 and 2 as seed 0 was."""
    root = Path(__file__).resolve().parents[1] / published.ROOT
    checked = 0
    for env in published.RUNS:
        for obs in published.OBSERVATIONS:
            for seed in published.SEEDS:
                path = published.run_folder(root, env, obs, seed) / "result.json"
                if not path.exists():
                    continue
                trained = json.loads(path.read_text())["hyperparameters"].get("init", "torch")
                args = run.parse_args(published.run_argv(env, obs, seed))
                assert (args.init or task_hyperparameters(env).init) == trained, (env, obs, seed)
                checked += 1
    trained = len(published.published_tasks()) * len(published.OBSERVATIONS) * len(published.SEEDS)
    assert checked == trained  # every published run (the pending tasks' are not trained yet)


def test_every_published_row_is_three_step_budget_seeds_on_the_publication_worlds():
    """Issue 29's rule, on the committed runs: every task, from pixels and from the state, has the
    published seeds, each stopped by its step budget and scored on the publication worlds, and every
    command docs/baselines.md shows for a run stops on a step budget."""
    root = Path(__file__).resolve().parents[1]
    runs = report.load_results(root / published.ROOT)
    assert not set(runs) & set(published.PENDING), "a pending task has runs: take it out of published.PENDING"
    for env in published.published_tasks():
        for obs in published.OBSERVATIONS:
            results = runs[env][obs]
            assert [r["seeds"]["train"] for r in results] == list(published.SEEDS), (env, obs)
            for r in results:
                where = (env, obs, r["seeds"]["train"])
                assert r["layout"] == "seeds" and r["evaluation_set"] == "publication", where
                assert r["budget_minutes"] is None and not r["truncated"], where
                assert r["env_steps"] == step_budget(env, obs), where
    page = (root / "docs" / "baselines.md").read_text()
    shown = [line for line in page.splitlines() if line.startswith("python -m marl_render.baselines ")]
    runs_section = page.split("\n## Runs\n")[1].split("\n## Findings\n")[0]
    outs = [line.split(" --out ")[1] for line in runs_section.splitlines() if line in shown]
    assert sorted(outs) == sorted(f"docs/baselines/{published.folder(env, obs)}/seed{seed}"
                                  for env in published.published_tasks()
                                  for obs in published.OBSERVATIONS for seed in published.SEEDS)
    for line in shown:  # the runs' and the findings' commands
        assert " --env-steps " in line and "--budget-minutes" not in line, line


def test_the_readmes_claims_about_the_baselines_follow_the_table():
    """README: "every published task's policy beats random (those tasks) ... from pixels and from the
    state", the tasks still pending, and the pixels' IQM across tasks, read against docs/results.md's
    table and docs/baselines.md's aggregate."""
    root = Path(__file__).resolve().parents[1]
    readme = " ".join((root / "README.md").read_text().split())
    table = (root / "docs" / "results.md").read_text().split(report.START)[1].split(report.END)[0]
    verdicts = {line.split("|")[1].strip(): line.split("|")[6].strip() for line in table.splitlines()[3:]
                if line.startswith("| ")}
    assert sorted(verdicts) == sorted(list_envs())  # every task has a row, a pending one too
    assert {env for env, v in verdicts.items() if v == "pending; pending"} == set(published.PENDING)
    shown = {env: v for env, v in verdicts.items() if env not in published.PENDING}
    claim = re.search(r"every published task's policy beats random \(([a-z_, ]+)\), from pixels and from the state",
                      readme)
    assert bool(claim) == (set(shown.values()) == {"yes; yes"}), shown  # the claim iff the table shows it
    assert claim is None or claim.group(1).split(", ") == sorted(shown)
    pending = re.search(r"no trained runs yet for ([a-z_, and]+) \(pending\)", readme)
    assert (pending is not None) == bool(published.PENDING)
    assert pending is None or set(re.split(r", | and ", pending.group(1))) == set(published.PENDING)
    iqm = re.search(rf"from pixels, 3 seeds x {len(list_envs())} tasks \([^)]*\): IQM ([-\d.]+ \[[-\d.]+, [-\d.]+\])",
                    (root / "docs" / "baselines.md").read_text())
    assert iqm and f"(random 0, heuristic 1, IQM) {iqm.group(1)} from pixels" in readme


def test_published_entries_are_checked_and_read_only():
    with pytest.raises(ValueError, match="env_steps must be an int >= 1, got 0"):
        published.Published(0)
    with pytest.raises(TypeError):
        published.RUNS["push"]["pixels"].train_options["shaping"] = 2.0
    assert published.RUNS["push"]["pixels"].train_options["shaping"] == 1.0


def test_published_main_lists_and_runs_what_is_missing(tmp_path, monkeypatch, capsys):
    assert published.main(["--root", "runs"]) == 0
    assert capsys.readouterr().out.splitlines() == published.commands("runs")
    kept = published.run_folder(tmp_path, "spread", "state", 1)
    kept.mkdir(parents=True)
    (kept / "result.json").write_text("{}")
    calls = []

    def fake_run(argv, **kwargs):
        calls.append(argv)
        return published.subprocess.CompletedProcess(argv, 0)
    monkeypatch.setattr(published.subprocess, "run", fake_run)
    assert published.main(["--run", "--root", str(tmp_path)]) == 0
    learner = [argv[3:] for argv in calls if argv[2] == "marl_render.baselines"]
    expected = [published.run_argv(env, obs, seed, tmp_path) for seed in published.SEEDS
                for obs in published.OBSERVATIONS for env in published.RUNS
                if (env, obs, seed) != ("spread", "state", 1)]
    assert learner == expected  # seed by seed: a batch cut short leaves whole seeds of every task
    assert calls[-1][2:] == ["marl_render.baselines.report", "--results", str(tmp_path)]
    assert (published.run_folder(tmp_path, "tag", "pixels", 2) / "train.log").is_file()


def test_published_run_reports_failed_runs_and_skips_the_report(tmp_path, monkeypatch, capsys):
    calls = []

    def failing_run(argv, **kwargs):
        calls.append(argv)
        return published.subprocess.CompletedProcess(argv, 3 if "cartpole" in argv else 0)
    monkeypatch.setattr(published.subprocess, "run", failing_run)
    assert published.main(["--run", "--jobs", "2", "--root", str(tmp_path)]) == 1
    assert not any(argv[2] == "marl_render.baselines.report" for argv in calls)
    assert len(calls) == len(published.RUNS) * len(published.OBSERVATIONS) * len(published.SEEDS)
    captured = capsys.readouterr()
    assert captured.err.count("--env cartpole") == len(published.OBSERVATIONS) * len(published.SEEDS)
    progress = captured.out.splitlines()  # two runs' threads: still one whole line per event
    assert len(progress) == 2 * len(calls)
    assert all(re.fullmatch(r"(started|finished|FAILED \(3\)) \S+/seed\d", line) for line in progress), progress


def test_published_jobs_below_one_is_refused(capsys):
    with pytest.raises(SystemExit):
        published.main(["--run", "--jobs", "0"])
    assert "--jobs must be >= 1, got 0" in capsys.readouterr().err


def test_a_run_whose_checkpoint_was_nan_is_read_from_its_null_and_written_as_null(tmp_path):
    write_runs(tmp_path / "runs", {("spread", "pixels"): [[1.0]]})
    path = tmp_path / "runs" / "spread" / "seed0" / "result.json"
    result = json.loads(path.read_text())
    result["checkpoints"][0].update(mean=None, std=None, per_episode=[None, 1.0])  # as the trainer writes a NaN
    path.write_text(json.dumps(result))
    assert report.main(["--results", str(tmp_path / "runs"), "--out", str(tmp_path / "baselines.md"),
                        "--readme", ""]) == 0
    layout = json.loads((tmp_path / "runs" / "marl_eval.json").read_text(), parse_constant=pytest.fail)
    assert layout["marl_render"]["spread"]["mappo_pixels"]["seed_0"]["step_0"]["return"] == [None, 1.0]


def test_a_published_rows_command_pins_what_its_entry_pins_that_the_run_did_not_record():
    """commons' runs were trained with the fixed episode end, before mixed-motive tasks ended at random by
    default: their result.json names no episode_end, their published entry pins it, and the command that
    reproduces a run passes it (a rerun without it would train another task)."""
    runs = report.load_results(Path(__file__).resolve().parents[1] / published.ROOT)
    for env in ("commons", "capture_flag"):
        for row in [*runs[env]["pixels"], *runs[env]["state"]]:
            assert "episode_end" not in row.get("env_options", {})
            assert "--env-option episode_end=False" in report.reproducing_command(row)
    assert "episode_end" not in report.reproducing_command(runs["spread"]["pixels"][0])
