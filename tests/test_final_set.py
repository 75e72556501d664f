"""The sealed final evaluation set: its size from the committed runs, its guard, nothing scored on it yet."""
import json
import math
import statistics
import subprocess
from pathlib import Path

import pytest

from marl_render.baselines import ablate, final_runs, final_set, run
from marl_render.baselines.settings import EVALUATION_SETS
from marl_render.envs.evaluation import SEALED_SEEDS, evaluate, random_policy
from marl_render.envs.registry import list_envs

ROOT = Path(__file__).resolve().parents[1]
FINAL = EVALUATION_SETS["final"]


def test_needed_episodes_is_the_fewest_with_a_standard_error_under_the_target():
    assert final_set.needed_episodes(1.0, 1.0) == 401  # sd / sqrt(400) is exactly 5%: not under it
    assert final_set.needed_episodes(2.0, -4.0) == 101  # the range's sign does not matter
    assert final_set.needed_episodes(0.0, 3.0) == 1
    with pytest.raises(ValueError, match="value_range must not be 0"):
        final_set.needed_episodes(1.0, 0.0)


def test_per_task_takes_the_largest_sd_of_random_heuristic_and_every_learned_run(tmp_path):
    def result(env, policy):
        return {"env": env, "evaluation": {"random": {"mean": 0.0, "per_episode": [-1.0, 1.0]},
                                           "heuristic": {"mean": 10.0, "per_episode": [10.0, 10.0]},
                                           "policy": {"per_episode": policy}}}
    for folder, policy in (("spread/seed0", [0.0, 0.0]), ("spread-state/seed1", [0.0, 4.0])):
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "result.json").write_text(json.dumps(result("spread", policy)))
    tasks = final_set.per_task(tmp_path)
    assert tasks == {"spread": {"range": 10.0, "sd": statistics.stdev([0.0, 4.0]), "episodes": 33}}
    assert final_set.final_episodes(tasks) == 64  # 33 x 1.5, rounded up to 64


def test_the_committed_final_set_resolves_every_task_to_5_percent():
    """Its episode count, from the committed runs, gives every task a standard error under 5% of its
    random-to-heuristic range (with the margin: what final_set.py computes)."""
    tasks = final_set.per_task(ROOT / "docs" / "baselines")
    assert sorted(tasks) == sorted(list_envs())  # issue 41's five tasks too: each needs at most 39 episodes
    assert FINAL["episodes"] == final_set.final_episodes(tasks) == 256
    for task in tasks.values():
        assert task["sd"] / math.sqrt(FINAL["episodes"]) < 0.05 * abs(task["range"])
    assert FINAL["seed"] not in {s["seed"] for name, s in EVALUATION_SETS.items() if name != "final"}


def test_evaluate_refuses_the_sealed_seed_without_final_and_final_without_it():
    with pytest.raises(ValueError, match="seed 52813907 is the sealed 'final' evaluation set: it is scored only "
                                         "with final=True"):
        evaluate("spread", random_policy, episodes=1, seed=FINAL["seed"])
    with pytest.raises(ValueError, match=r"final=True applies to a sealed set's seed \[52813907\], got seed 7000000"):
        evaluate("spread", random_policy, episodes=1, seed=7_000_000, final=True)
    assert SEALED_SEEDS == {FINAL["seed"]: "final"}


@pytest.mark.parametrize("args, message", [
    (["--eval-set", "final"], "--eval-set final is sealed: it is scored once, by the final runs, with --final"),
    (["--eval-seed", str(FINAL["seed"])], "--eval-set final is sealed"),
    (["--final"], "--final applies to the sealed set (--eval-set final), got evaluation seed 1000"),
    (["--eval-set", "publication", "--final"], "got evaluation seed 7000000"),
])
def test_the_command_scores_the_final_set_only_with_final(args, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        run.parse_args(["--env", "spread", *args])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert run.parse_args(["--env", "spread", "--eval-set", "final", "--final"]).final is True


def test_only_the_final_runs_are_scored_on_the_final_set():
    """The sealed set scores the final runs alone: no committed JSON file outside docs/final/ names its
    seed or the set, and every one inside is a final run's result.json, its view ablation (ablation.json
    beside it, on its episodes) or the frozen tasks' best constant actions on the set (ablate.py)."""
    files = subprocess.run(["git", "ls-files", "*.json"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split()
    assert len(files) > 50
    for name in files:
        text = (ROOT / name).read_text(errors="replace")
        if name == f"{final_runs.ROOT}/{ablate.CONSTANT_ACTIONS}":
            constants = json.loads(text)
            assert set(constants) <= set(final_runs.FROZEN), name
            assert all(c["evaluation_set"] == "final" and c["seed"] == FINAL["seed"] for c in constants.values())
        elif name.startswith(final_runs.ROOT + "/") and name.endswith("/" + ablate.ABLATION):
            ablation, result = json.loads(text), json.loads((ROOT / name).with_name("result.json").read_text())
            assert ablation["evaluation_set"] == "final" and ablation["seed"] == FINAL["seed"], name
            assert ablation["views"]["none"]["per_episode"] == result["evaluation"]["policy"]["per_episode"], name
        elif name.startswith(final_runs.ROOT + "/"):
            result = json.loads(text)
            assert name.endswith("/result.json") and result["evaluation_set"] == "final", name
            assert result["mode"] == "reproducible" and result["seeds"]["evaluation"] == FINAL["seed"], name
        else:
            assert str(FINAL["seed"]) not in text and '"evaluation_set": "final"' not in text, name
