"""Round 5's independent adversarial pass (docs/reliability/round5-recheck.md): each test pins one
defect the pass found, on the held-out, bot, level, sight, Elo, evaluation, generalisation and
trainer surfaces. Cheap: one- or two-world envs at 8 px, or no env at all."""
from __future__ import annotations

import copy
import json
import math
import os

import numpy as np
import pytest
import torch

from marl_render import bots, heldout
from marl_render import generalise as generalisation
from marl_render.baselines import report
from marl_render.baselines import run as trainer
from marl_render.bots import make_bot, register_bot, wander
from marl_render.elo import elo_ratings
from marl_render.envs import evaluation as references
from marl_render.envs import make_env, sight
from marl_render.envs.levels import PrioritisedLevelReplay
from marl_render.heldout import HELDOUT, HeldOutScenario, register_heldout

RUN = os.path.join(os.path.dirname(__file__), "..", "docs", "baselines", "forage", "seed0")


# ---------------------------------------------------------------------- generalise
def test_generalise_refuses_the_same_run_twice_before_any_work():
    # "run" and "run/" were two entries of the summary: one seed counted twice.
    for runs in ([RUN, RUN], [RUN, RUN + "/"]):
        with pytest.raises(ValueError, match="runs must name each run folder once"):
            generalisation.generalise(runs, episodes=2, max_steps=1)


def test_generalise_refuses_a_seed_the_envs_do_not_take():
    with pytest.raises((ValueError, TypeError), match=r"seed must be an int in \[0, 2\*\*63\)"):
        generalisation.generalise(RUN, episodes=2, max_steps=1, seed=2 ** 64)


def test_generalise_command_refuses_an_out_under_a_file_before_any_work(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")

    def played(*args, **kwargs):
        raise AssertionError("the runs were scored before --out was checked")

    monkeypatch.setattr(generalisation, "generalise", played)
    with pytest.raises(SystemExit) as stop:
        generalisation.main([RUN, "--episodes", "2", "--out", str(blocker / "table")])
    assert stop.value.code == 2 and "--out" in capsys.readouterr().err


# ---------------------------------------------------------------------- python -m marl_render.envs.evaluation
@pytest.mark.parametrize("argv, named", [
    (["--env", "forage", "--episodes", "2", "--levels", "nope"], "--levels"),
    (["--env", "forage", "--episodes", "2", "--levels", "0"], "--levels"),
    (["--env", "forage", "--episodes", "2", "--seed", "-1"], "--seed"),
    (["--env", "forage", "--episodes", "2", "--seed", str(2 ** 64)], "--seed"),
    (["--env", "nope"], "nope"),
    (["--env", "forage", "--episodes", "1000000000"], "num_worlds"),
])
def test_reference_returns_command_gives_one_error_line(argv, named, capsys):
    with pytest.raises(SystemExit) as stop:
        references.main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and named in err and "Traceback" not in err


def test_reference_evaluation_refuses_a_seed_beyond_the_envs():
    with pytest.raises(ValueError, match=r"seed must be None or an int in \[0, 2\*\*63\), got 18446744073709551616"):
        references.evaluate("forage", references.random_policy, episodes=2, seed=2 ** 64, resolution=8)


# ---------------------------------------------------------------------- focal envs and bots
def test_a_focal_env_takes_the_numpy_integer_seeds_its_core_takes():
    with make_env("forage", heldout="forage/one_among_noisy", num_worlds=2, resolution=8) as env:
        env.reset(seed=4)
        plain = env.get_state()
        env.reset(seed=np.int64(4))  # TypeError("an integer is required") from the bots' re-seeding before
        numpy = env.get_state()
    assert plain.keys() == numpy.keys()
    for key in plain:
        if isinstance(plain[key], torch.Tensor):
            assert torch.equal(plain[key], numpy[key]), key
    assert all(torch.equal(a, b) for a, b in zip(plain["bot_rngs"], numpy["bot_rngs"], strict=True) if a is not None)


@pytest.mark.parametrize("seed, error", [(-1, ValueError), (2 ** 64, ValueError), (1.5, TypeError), (True, TypeError)])
def test_make_bot_refuses_a_seed_the_envs_do_not_take(seed, error):
    with pytest.raises(error, match=r"seed must be None or an int in \[0, 2\*\*63\)"):
        make_bot("forage", "noisy0.5", seed=seed)


def test_register_bot_refuses_a_non_bool_overwrite_and_a_non_str_description(registries):
    register_bot("forage", "circler", wander)
    before = copy.deepcopy(bots._REGISTERED)
    with pytest.raises(TypeError, match="overwrite must be a bool, got"):
        register_bot("forage", "circler", wander, overwrite="no")  # a truthy "no" replaced the bot
    with pytest.raises(TypeError, match="description of bot 'other' must be a str"):
        register_bot("forage", "other", wander, description=5)
    assert copy.deepcopy(bots._REGISTERED) == before and bots.populations("forage")["test"][-1] == "circler"


def _scenario(**changes) -> HeldOutScenario:
    fields = dict(name="forage/mine", task="forage", description="one focal forager with two wanderers",
                  num_agents=3, focal=("agent_0",), bots_by_role={"agents": ("wanderer",)})
    return HeldOutScenario(**{**fields, **changes})


@pytest.mark.parametrize("changes, message", [
    ({"name": "tag"}, "must not be 'all' or a task's name"),
    ({"name": "all"}, "must not be 'all' or a task's name"),
    ({"params": {"num_agents": 4}}, "other than num_agents"),  # silently made a 4-agent scenario declared as 3
    ({"params": [1]}, "params must be a dict"),
    ({"bots_by_role": {"agents": ()}}, "at least one name per team"),
    ({"bots_by_role": [("agents", ("wanderer",))]}, "bots_by_role must be a dict"),
    ({"focal": ("agent_0", "agent_1", "agent_2")}, "does not make a focal-only env"),
    ({"description": 5}, "description must be a str"),
])
def test_register_heldout_refuses_a_scenario_that_cannot_play_before_registering_it(registries, changes, message):
    names = list(heldout.HELDOUT)
    with pytest.raises((ValueError, TypeError), match=message):
        register_heldout(_scenario(**changes))
    assert list(heldout.HELDOUT) == names


def test_register_heldout_keeps_its_own_copy_and_a_bool_overwrite(registries):
    mine = _scenario(bots_by_role={"agents": ["wanderer"]})
    register_heldout(mine)
    mine.bots_by_role["agents"].append("heuristic")  # a train bot, slipped in after the check
    assert HELDOUT["forage/mine"].bots_by_role == {"agents": ("wanderer",)}
    with pytest.raises(TypeError, match="overwrite must be a bool"):
        register_heldout(_scenario(description="changed"), overwrite="no")
    assert HELDOUT["forage/mine"].description == "one focal forager with two wanderers"


# ---------------------------------------------------------------------- Elo
@pytest.mark.parametrize("wins, smoothing", [
    ([[0, 1e308], [1e308, 0]], 0.1),
    ([[0, 1e308, 1e308], [1, 0, 1], [1, 1, 0]], 0.1),
    ([[0, 3], [1, 0]], 1e308),
])
def test_elo_refuses_counts_whose_sums_overflow(wins, smoothing):
    with pytest.raises(ValueError, match="must give finite game counts"):  # [nan, nan] before
        elo_ratings(np.array(wins, dtype=np.float64), smoothing=smoothing)


def test_elo_takes_a_tensor_that_requires_grad_and_refuses_complex_and_text():
    wins = torch.tensor([[0.0, 3.0], [1.0, 0.0]], requires_grad=True)
    assert np.array_equal(elo_ratings(wins), elo_ratings(np.array([[0.0, 3.0], [1.0, 0.0]])))
    with pytest.raises(TypeError, match="wins must hold real counts"):  # the imaginary part was dropped
        elo_ratings(np.array([[0, 1j], [1, 0]]))
    with pytest.raises(TypeError, match="draws must hold real counts"):
        elo_ratings([[0, 1], [1, 0]], [["a", "b"], ["c", "d"]])


# ---------------------------------------------------------------------- sight
EYE, YAW, TARGET = torch.zeros(1, 1, 2), torch.zeros(1, 1), torch.tensor([[[0.0, 1.0]]])


@pytest.mark.parametrize("changes, message", [
    ({"fov": math.nan}, "fov must be a number > 0"),
    ({"fov": -1.0}, "fov must be a number > 0"),
    ({"fov": "wide"}, "fov must be a number > 0"),
    ({"half_extent": (-2.0, -2.0)}, "half_extent must be"),
    ({"half_extent": (math.nan, 2.0)}, "half_extent must be"),
    ({"eye": torch.full((1, 1, 2), math.nan)}, "eye, yaw and targets must be finite"),
    ({"yaw": torch.full((1, 1), math.nan)}, "eye, yaw and targets must be finite"),
    ({"targets": torch.full((1, 1, 2), math.nan)}, "eye, yaw and targets must be finite"),
])
def test_line_of_sight_refuses_what_would_see_nothing_silently(changes, message):
    arguments = {"eye": EYE, "yaw": YAW, "targets": TARGET, "fov": 1.0, "reach": 5.0, "half_extent": (2.0, 2.0),
                 **changes}
    assert bool(sight.line_of_sight(EYE, YAW, TARGET, fov=1.0, reach=5.0, half_extent=(2.0, 2.0)).all())
    with pytest.raises(ValueError, match=message):  # False (not seen) before
        sight.line_of_sight(arguments.pop("eye"), arguments.pop("yaw"), arguments.pop("targets"), **arguments)


def test_lidar_refuses_a_nan_circle_centre_and_a_bad_half_extent():
    present = torch.ones(1, 1, dtype=torch.bool)
    nan_circle = sight.Circles(torch.full((1, 1, 2), math.nan), torch.ones(1, 1), present)
    with pytest.raises(ValueError, match="circles.center must be finite"):  # read 1 (nothing in reach) before
        sight.lidar(EYE, YAW, rays=4, reach=1.0, half_extent=(2.0, 2.0), circles=nan_circle)
    absent = sight.Circles(torch.full((1, 1, 2), math.nan), torch.ones(1, 1), ~present)
    assert sight.lidar(EYE, YAW, rays=4, reach=1.0, half_extent=(2.0, 2.0), circles=absent).tolist() == [[[1.0] * 4]]
    for half_extent in ((-2.0, -2.0), (math.nan, 2.0), "wide"):  # 0 or NaN readings before
        with pytest.raises(ValueError, match="half_extent must be"):
            sight.lidar(EYE, YAW, rays=4, reach=1.0, half_extent=half_extent)


@pytest.mark.parametrize("arguments, name", [((math.nan,), "fov_y"), ((-1.0,), "fov_y"), ((4.0,), "fov_y"),
                                             ((1.0, 0.0), "aspect"), ((1.0, 1.0, math.inf), "pitch")])
def test_horizontal_fov_refuses_what_has_no_field_of_view(arguments, name):
    with pytest.raises(ValueError, match=f"{name} must be"):
        sight.horizontal_fov(*arguments)


# ---------------------------------------------------------------------- levels
def test_prioritised_replay_keeps_no_graph_and_the_last_score_of_a_level_given_twice():
    replay = PrioritisedLevelReplay(range(4))
    replay.update(torch.tensor([0, 2, 0]), torch.tensor([1.0, 5.0, 3.0], requires_grad=True))
    assert not replay.scores.requires_grad  # a value loss's graph was kept in the sampler's state
    assert replay.scores.tolist() == [3.0, 0.0, 5.0, 0.0] and replay.seen.tolist() == [True, False, True, False]


# ---------------------------------------------------------------------- trainer
@pytest.mark.parametrize("argv", [["--seeds", "0", "-1"], ["--seeds", "0", str(2 ** 64)], ["--seed", "-3"]])
def test_trainer_refuses_every_seed_out_of_range_before_training(argv, capsys):
    with pytest.raises(SystemExit) as stop:  # seed 0 trained in full before seed -1 failed
        trainer.parse_args(["--env", "forage", "--updates", "1", *argv])
    assert stop.value.code == 2 and r"must be an int in [0, 2**63)" in capsys.readouterr().err


def test_each_seeds_command_drops_the_seeds_option_in_its_equals_form():
    command = trainer.seed_command(["--env", "forage", "--seeds=3", "--out=o"], 3, "o/seed3", None)
    assert command == ["--env", "forage", "--seed", "3", "--out", "o/seed3"]  # kept --seeds=3: refused on a rerun


# ---------------------------------------------------------------------- python -m marl_render.baselines.report
def test_report_refuses_a_field_of_the_wrong_type_in_one_line_and_writes_nothing(tmp_path, capsys):
    run = tmp_path / "results" / "forage" / "seed0"
    run.mkdir(parents=True)
    result = json.loads(open(os.path.join(RUN, "result.json")).read())
    result["hyperparameters"] = None  # a traceback, after marl_eval.json was rewritten, before
    (run / "result.json").write_text(json.dumps(result))
    with pytest.raises(SystemExit) as stop:
        report.main(["--results", str(tmp_path / "results"), "--out", str(tmp_path / "b.md"), "--readme", ""])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "holds a field of the wrong type" in err and "Traceback" not in err
    assert not (tmp_path / "results" / "marl_eval.json").exists() and not (tmp_path / "b.md").exists()


def test_trainer_refuses_an_empty_tensorboard_folder(capsys):
    with pytest.raises(SystemExit) as stop:  # SummaryWriter("") logs to its own runs/DATE_HOST instead
        trainer.parse_args(["--env", "forage", "--updates", "1", "--tensorboard", ""])
    assert stop.value.code == 2 and "--tensorboard must be a folder" in capsys.readouterr().err


# ---------------------------------------------------------------------- the env's counters
@pytest.mark.parametrize("heldout_name", [None, "forage/one_among_noisy"])
def test_step_count_and_alive_are_the_callers_copies(heldout_name):
    # The core handed out its own tensors: writing into them changed get_state() (MultiProcessEnv copied).
    kwargs = {"heldout": heldout_name} if heldout_name else {}
    with make_env("forage", num_worlds=2, resolution=8, **kwargs) as env:
        env.reset()
        env.step(env.heuristic_actions())
        before = env.get_state()
        env.step_count.add_(5)
        env.alive.zero_()
        after = env.get_state()
        assert torch.equal(before["step_count"], after["step_count"]) and torch.equal(before["alive"], after["alive"])
        assert env.step_count.tolist() == [1, 1] and bool(env.alive.all())


@pytest.mark.parametrize("origin, direction", [
    (torch.full((1, 1, 2), math.nan), torch.tensor([[[1.0, 0.0]]])),  # NaN before
    (torch.zeros(1, 1, 2), torch.zeros(1, 1, 2)),  # inf before
    (torch.zeros(1, 1, 2), torch.tensor([[[2.0, 0.0]]])),  # half the distance before
])
def test_first_hit_refuses_a_bad_origin_or_a_direction_that_is_not_a_unit_vector(origin, direction):
    assert first_hit_distance(torch.zeros(1, 1, 2), torch.tensor([[[1.0, 0.0]]])) == 2.0
    with pytest.raises(ValueError, match="origin must be finite and direction a unit vector"):
        first_hit_distance(origin, direction)


def first_hit_distance(origin, direction) -> float:
    return float(sight.first_hit(origin, direction, half_extent=(2.0, 2.0)))


@pytest.mark.parametrize("heldout_name", [None, "spread/two_with_nearest"])
def test_writing_into_env_sim_changes_nothing(heldout_name):
    """env.sim is the caller's copy (as alive, step_count and every output): writing into it changes
    neither the env's state nor its next step, on the core and on a focal env alike."""
    options = {} if heldout_name is None else {"heldout": heldout_name}
    with make_env("spread", num_worlds=2, resolution=8, **options) as env, \
            make_env("spread", num_worlds=2, resolution=8, **options) as twin:
        env.reset(seed=3)
        twin.reset(seed=3)
        sim = env.sim
        sim.pos.add_(0.5)
        sim.vel.fill_(9.0)
        assert all(torch.equal(a, b) for a, b in zip(env.get_state().values(), twin.get_state().values(),
                                                      strict=True) if isinstance(a, torch.Tensor))
        actions = torch.zeros(env.num_worlds, env.num_agents, dtype=torch.int64)
        stepped, reference = env.step(actions), twin.step(actions)
        assert torch.equal(stepped[1], reference[1]) and torch.equal(stepped[0]["pixels"], reference[0]["pixels"])
        assert not torch.equal(env.sim.pos, sim.pos)
