"""The final runs (issue 38): each frozen published row's command in the reproducible mode, scored once on
the sealed final set; their settings frozen; the page written from their result.json files."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from marl_render.baselines import ablate, final_runs, published, run
from marl_render.baselines.settings import EVALUATION_SETS

FINAL_SEED = EVALUATION_SETS["final"]["seed"]

# Each frozen row's settings_digest() when its final runs began (stop 40; issue 41's five tasks: stop 49). A
# change fails here: the final runs already trained with the old settings must then be deleted (and the change
# said in the notes), or the change undone.
FROZEN_DIGESTS = {
    ("capture_flag", "pixels"): "d4142a15dc5c157a", ("capture_flag", "state"): "f4495fa766bbda6b",
    ("cartpole", "pixels"): "b2bed0db9b4690f9", ("cartpole", "state"): "70e4528b45243e13",
    ("commons", "pixels"): "2a4b55f429c27b12", ("commons", "state"): "424aabf8e83bf32f",
    ("forage", "pixels"): "8548369f924f1440", ("forage", "state"): "72f2d128fdf99212",
    ("push", "pixels"): "205fa125108f7626", ("push", "state"): "cadecfd9d37e44f7",
    ("rooms", "pixels"): "2065a746dfe8c7e6", ("rooms", "state"): "fee0dd42242ebb57",
    ("speaker_listener", "pixels"): "386cc9e7ad249009", ("speaker_listener", "state"): "d121d2d690698b22",
    ("spread", "pixels"): "13ad29113c1e8378", ("spread", "state"): "741bda26875c74df",
    ("tag", "pixels"): "d60eba11c3109a04", ("tag", "state"): "78d8a882907f62d9",
    ("clean_up", "pixels"): "f7b6e63f67e1d146", ("clean_up", "state"): "14c72ebd190c3e2f",
    ("cooking", "pixels"): "2c47bf5d4cc44e3c", ("cooking", "state"): "14c72ebd190c3e2f",
    ("coop_mining", "pixels"): "a3ddb490cacad6d8", ("coop_mining", "state"): "b33dc0baaa0ddbef",
    ("matrix", "pixels"): "8a2fa453ea398a0c", ("matrix", "state"): "c183236e090cf8dc",
    ("territory", "pixels"): "926e24770d17213d", ("territory", "state"): "5fc16f98129fb35c",
}


def test_the_frozen_rows_settings_are_those_their_final_runs_train_with():
    assert set(FROZEN_DIGESTS) == {(env, obs) for env in final_runs.FROZEN for obs in published.OBSERVATIONS}
    changed = {key: final_runs.settings_digest(*key) for key, digest in FROZEN_DIGESTS.items()
               if final_runs.settings_digest(*key) != digest}
    assert not changed, f"frozen rows changed: {changed}"


def test_a_final_command_is_the_published_one_in_the_reproducible_mode_on_the_sealed_set():
    commands = final_runs.commands()
    assert len(commands) == len(final_runs.FROZEN) * len(published.OBSERVATIONS) * len(published.SEEDS)
    for env in final_runs.FROZEN:
        for obs in published.OBSERVATIONS:
            entry = published.RUNS[env][obs]
            for seed in published.SEEDS:
                args = run.parse_args(final_runs.argv(env, obs, seed))  # as the learner reads it
                assert (args.env, args.obs, args.seed, args.env_steps) == (env, obs, seed, entry.env_steps)
                assert (args.eval_set, args.final, args.reproducible) == ("final", True, True)
                assert dict(args.env_option) == dict(entry.env_options)
                assert dict(args.train_option) == dict(entry.train_options)
                assert all(getattr(args, k) == v for k, v in entry.hyperparameters.items())
                assert args.out == f"docs/final/{published.folder(env, obs)}/seed{seed}"


def test_every_published_task_is_frozen_and_only_frozen_tasks_have_final_runs():
    assert set(final_runs.FROZEN) == set(published.RUNS)
    with pytest.raises(ValueError, match=r"env must be one of the frozen tasks \[.*\], got 'no_such_task'"):
        final_runs.argv("no_such_task", "pixels", 0)
    with pytest.raises(SystemExit):
        final_runs.main(["--tasks", "no_such_task"])


def _result(env: str, obs: str, mean: float, cpu: str = "AMD EPYC", seed: int = 0) -> dict:
    return {"env": env, "obs": obs, "machine": {"cpu": {"model": cpu}}, "evaluation_set": "final", "env_steps": 1024,
            "seeds": {"train": seed, "evaluation": FINAL_SEED},
            "evaluation": {"policy": {"mean": mean}, "random": {"mean": -14.0}, "heuristic": {"mean": -0.9}}}


def test_the_page_shows_the_runs_done_and_the_commands_left(tmp_path):
    for seed, mean in ((0, -6.0), (1, -8.0)):
        folder = published.run_folder(tmp_path, "speaker_listener", "pixels", seed)
        folder.mkdir(parents=True)
        (folder / "result.json").write_text(json.dumps(_result("speaker_listener", "pixels", mean, seed=seed)))
    published_root = tmp_path / "published"
    folder = published.run_folder(published_root, "speaker_listener", "pixels", 0)
    folder.mkdir(parents=True)
    (folder / "result.json").write_text(json.dumps(_result("speaker_listener", "pixels", -9.5)))
    page = final_runs.report(tmp_path, tmp_path / "final.md", published_root)
    assert page == (tmp_path / "final.md").read_text()
    row = next(line for line in page.splitlines() if line.startswith("| speaker_listener | pixels |"))
    assert "| 2 | -6 / -8 | -7 [-8, -6] | -14 | -0.9 | – | not run | not judged (no best constant action on its " \
           "worlds, no view ablation) | -9.5 (1 seed) | AMD EPYC |" in row
    total = len(final_runs.FROZEN) * len(published.OBSERVATIONS) * len(published.SEEDS)
    assert f"Final runs done: 2 of {total}; still to train ({total - 2})" in page
    assert f"--out {tmp_path}/speaker_listener/seed2" in page and f"{tmp_path}/speaker_listener/seed0" not in page


def _ablation(none: list, zeros: list, shifted: list) -> dict:
    return {"views": {view: {"mean": float(np.mean(returns)), "per_episode": returns}
                      for view, returns in (("none", none), ("zeros", zeros), ("shifted", shifted))}}


@pytest.mark.parametrize("shifted, verdict", [([-7.0, -8.0, -7.0, -8.0], "yes"),
                                              ([-5.0, -6.0, -5.0, -6.0], "no (view ablation costs no return)")])
def test_the_page_judges_each_row_by_the_constant_action_and_the_view_ablation(tmp_path, shifted, verdict):
    for seed, mean in ((0, -5.5), (1, -5.0), (2, -6.0)):
        folder = published.run_folder(tmp_path, "speaker_listener", "pixels", seed)
        folder.mkdir(parents=True)
        (folder / "result.json").write_text(json.dumps(_result("speaker_listener", "pixels", mean, seed=seed)))
        (folder / ablate.ABLATION).write_text(json.dumps(_ablation([-5.0, -6.0, -5.0, -6.0],
                                                                   [-9.0, -10.0, -9.0, -10.0], shifted)))
    (tmp_path / ablate.CONSTANT_ACTIONS).write_text(json.dumps(
        {"speaker_listener": {"action": 3, "mean": -12.0, "evaluation_set": "final", "seed": FINAL_SEED}}))
    page = final_runs.report(tmp_path, tmp_path / "final.md", tmp_path / "published")
    row = next(line for line in page.splitlines() if line.startswith("| speaker_listener | pixels |"))
    zeros_shifted = f"{-9.5:.3g} / {np.mean(shifted):.3g}"
    assert f"| -14 | -0.9 | -12.0 (action 3) | {zeros_shifted} | {verdict} | - |" in row


def test_the_committed_final_constant_actions_are_on_the_sealed_set_for_every_task_whose_runs_are_done():
    """Computed once per task, after its final runs (so at least every task with all runs done has one)."""
    root = Path(__file__).resolve().parents[1] / final_runs.ROOT
    constants = json.loads((root / ablate.CONSTANT_ACTIONS).read_text())
    done = {env for env in final_runs.FROZEN if not final_runs.missing(root, [env])}
    assert done <= set(constants) <= set(final_runs.FROZEN)
    assert all(c["evaluation_set"] == "final" and c["seed"] == FINAL_SEED and c["episodes"] == 256
               and c["mean"] == max(c["per_action"]) for c in constants.values())


def test_run_trains_only_the_missing_runs_of_the_tasks_asked_and_writes_the_page(tmp_path, monkeypatch):
    done = published.run_folder(tmp_path, "tag", "pixels", 0)
    done.mkdir(parents=True)
    (done / "result.json").write_text(json.dumps(_result("tag", "pixels", 10.0)))
    started = []
    monkeypatch.setattr(published, "run_quietly", lambda command: started.append(command[3:]) or 0)
    assert final_runs.main(["--run", "--tasks", "tag", "--root", str(tmp_path), "--page", str(tmp_path / "f.md")]) == 0
    assert started == final_runs.missing(tmp_path, ["tag"]) and len(started) == 5
    assert all("--reproducible" in a and a[a.index("--env") + 1] == "tag" for a in started)
    row = "| tag | pixels | 1 | 10 | 10 (1 seed) | -14 | -0.9 | – | not run | not judged (1 seed) | 10 [10, 10] " \
          "| AMD EPYC |"
    assert row in (tmp_path / "f.md").read_text()


def test_the_committed_page_is_its_runs(tmp_path, monkeypatch):
    """docs/final.md is what --report writes from docs/final/ (regenerated, not edited)."""
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)
    assert final_runs.report(final_runs.ROOT, tmp_path / "final.md") == (root / final_runs.PAGE).read_text()


@pytest.mark.parametrize("document", ["README.md", "docs/results.md"])
def test_the_docs_claims_about_the_final_runs_follow_the_page(document):
    """README and results.md: "N of 84 done; from the state X count as learned, and Y do not; from pixels X'
    count as learned, and Y' do not", read against docs/final.md's table (the rows whose three seeds are done)."""
    root = Path(__file__).resolve().parents[1]
    text = " ".join((root / document).read_text().split())
    page = (root / final_runs.PAGE).read_text()
    rows = [[cell.strip() for cell in line.split("|")[1:-1]] for line in page.splitlines()
            if line.startswith("| ") and not line.startswith("| task ")]
    verdict = {(row[0], row[1]): row[9] for row in rows if row[2] == str(len(published.SEEDS))}
    done = sum(int(row[2]) for row in rows)
    total = len(final_runs.FROZEN) * len(published.OBSERVATIONS) * len(published.SEEDS)
    assert f"{done} of {total} done" in text and f"Final runs done: {done} of {total}" in page
    for obs, words in (("state", "from the state"), ("pixels", "from pixels")):
        claim = re.search(words + r" ([a-z_, and]+) count as learned(?:, and ([a-z_, and]+) do not)?", text)
        assert claim, f"{document} names the {obs} rows that count as learned and those that do not"
        named = [set(re.split(r", and |, | and ", group)) if group else set() for group in claim.groups()]
        assert named[0] == {env for (env, o), v in verdict.items() if o == obs and v == "yes"}, (document, obs)
        assert named[1] == {env for (env, o), v in verdict.items() if o == obs and v.startswith("no")}, (document, obs)
