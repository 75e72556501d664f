"""Reliability round 4 (issue 24), items 7-10: the cases that fed the renderer or a loop what it could
not take before their fixes (integer fields out of range, NaN positions, a step half done, two
threads at once, ``--block-seconds nan``), so that a regression could crash the process or hang it.
tests/test_reliability_author_traps.py runs each test here in a child process under a timeout; to run
them directly: ``python -m pytest tests/isolated_crash_cases.py``."""
from __future__ import annotations

import dataclasses
import math
import re
import threading

import pytest
import torch

from marl_render.bench import __main__ as bench_main
from marl_render.envs import make_env
from probe_task import ENVS, LOOKS, RES, Probe, W, assert_same, probe

pytestmark = pytest.mark.usefixtures("single_torch_thread")
ITEMS: dict[int, list[str]] = {}  # the item -> its tests here (each item runs in a child process of its own)


def item(number: int):
    """Registers the test under the issue's item `number`."""
    def register(test):
        ITEMS.setdefault(number, []).append(test.__name__)
        return test
    return register


# ---------------------------------------------------------------------- 7. every state field has its range
BAD_FIELDS = [  # (task, field, index, value, words)
    ("rooms", "home", (0,), 9, r"state\['home'\] must be within \[0, 8\]"),
    ("rooms", "home", (0,), -1, r"state\['home'\] must be within \[0, 8\]"),
    ("rooms", "door", (0, 0), 5.0, r"state\['door'\] must be within \[-0\.5, 0\.5\]"),
    ("rooms", "goal", (0, 0, 0), 3.5, r"state\['goal'\] must be within"),
    ("speaker_listener", "goal", (0,), 5, r"state\['goal'\] must be within \[0, 2\]"),
    ("speaker_listener", "lamp", (0,), -5, r"state\['lamp'\] must be within \[-1, 2\]"),
    ("speaker_listener", "targets", (0, 0, 0), 9.0, r"state\['targets'\] must be within"),
    ("commons", "timeout", (0, 0), -5, r"state\['timeout'\] must be within \[0, 25\]"),
    ("commons", "timeout", (0, 0), 26, r"state\['timeout'\] must be within \[0, 25\]"),
    ("commons", "steps", (0,), -1, r"state\['steps'\] must be within"),
    ("commons", "depleted_at", (0,), -2, r"state\['depleted_at'\] must be within"),
    ("commons", "depleted_at", (0,), 5, r"state\['depleted_at'\] must be -1 .* or a step in \[1, state\['steps'\]\]"),
    ("commons", "shown", (0, 0), False, r"state\['shown'\] must be True exactly for the agents in play"),
    ("capture_flag", "carrier", (0, 0), 99, r"state\['carrier'\] must be within \[\[-1, -1\], \[15, 7\]\]"),
    ("capture_flag", "carrier", (0, 1), 9, r"state\['carrier'\] must be within \[\[-1, -1\], \[15, 7\]\]"),
    ("capture_flag", "carrier", (0, 0), 3, r"red's flag\) must be -1 or a blue agent in \[8, 15\]"),
    ("capture_flag", "captures", (0, 0), -1, r"state\['captures'\] must be within"),
    ("forage", "item_timer", (0, 0), 11, r"state\['item_timer'\] must be within \[0, 10\]"),
    ("forage", "team_score", (0,), -1.0, r"state\['team_score'\] must be within"),
    ("tag", "obstacle_center", (0, 0, 0), 2.0, r"state\['obstacle_center'\] must be within"),
    ("cartpole", "qstate", (0, 0), 1.9, r"state\['qstate'\] must be within \[\[-1\.8, "),
    ("cartpole", "last_control", (0,), 1.5, r"state\['last_control'\] must be within \[-1, 1\]"),
]


@item(7)
@pytest.mark.parametrize("name, field, index, value, words", BAD_FIELDS,
                         ids=[f"{c[0]}-{c[1]}={c[3]}" for c in BAD_FIELDS])
def test_a_state_field_out_of_its_range_is_refused_and_changes_nothing(name, field, index, value, words):
    with make_env(name, num_worlds=W, resolution=RES, seed=0) as env, make_env(name, num_worlds=W, resolution=RES,
                                                                               seed=0) as twin:
        env.reset(), twin.reset()
        state = env.get_state()
        state[field][index] = value
        with pytest.raises(ValueError, match=words):
            env.set_state(state)
        assert_same(env.get_state(), twin.get_state())
        actions = env.random_actions(torch.Generator().manual_seed(0))
        assert_same(env.step(actions), twin.step(actions))  # the env steps on as if never asked


@item(7)
@pytest.mark.parametrize("change, error, words", [
    (lambda state: state.update(appearance_ids=state["appearance_ids"].float()), ValueError,
     r"state\['appearance_ids'\] must have dtype torch\.int64, got torch\.float32"),
    (lambda state: state.update(appearance_ids=state["appearance_ids"][:1]), ValueError,
     r"state\['appearance_ids'\] must have shape \[2\], got \[1\]"),
    (lambda state: state.update(appearance_ids=state["appearance_ids"].tolist()), TypeError,
     r"state\['appearance_ids'\] must be a torch\.Tensor, got \["),
    (lambda state: state.pop("appearance_ids"), ValueError, r"got missing \['appearance_ids'\]"),
])
def test_appearance_ids_are_checked_by_set_state_and_a_refusal_changes_nothing(change, error, words):
    with probe(**LOOKS) as env, probe(**LOOKS) as twin, probe(**{**LOOKS, "seed": 1}) as other:
        env.reset(), twin.reset(), other.reset()
        state = other.get_state()
        change(state)
        with pytest.raises(error, match=words):
            env.set_state(state)
        assert_same(env.get_state(), twin.get_state())
        actions = torch.zeros(W, 2, dtype=torch.long)
        assert_same(env.step(actions), twin.step(actions))
        env.set_state(other.get_state())  # any int64 is an id: the looks follow the state
        assert_same(env.step(actions), other.step(actions))


@item(7)
def test_appearance_ids_are_refused_by_an_env_without_appearance():
    with probe(**LOOKS) as looks, probe() as plain:
        looks.reset(), plain.reset()
        state = {**plain.get_state(), "appearance_ids": looks.get_state()["appearance_ids"]}
        with pytest.raises(ValueError, match=r"got missing \[\] and unknown \['appearance_ids'\]"):
            plain.set_state(state)


@item(7)
@pytest.mark.parametrize("name", ENVS)
def test_every_field_with_a_meaning_has_a_range(name):
    """Every state field that is not a bool has bounds in set_state (integers included)."""
    env = make_env(name, num_worlds=W, resolution=RES)
    bounds = env.scenario.state_bounds()
    unbounded = [field.name for field in dataclasses.fields(env.sim)
                 if getattr(env.sim, field.name).dtype != torch.bool and field.name not in bounds]
    env.close()
    assert unbounded == []


# ---------------------------------------------------------------------- 8. a step commits when every hook succeeded
FAILURES = [  # (hook, the call that raises, autoreset, the step it happens in: 0 is reset())
    ("rules", 1, False, 1), ("observation", 2, False, 1), ("action_mask", 2, False, 1), ("instances", 2, False, 1),
    ("frozen", 2, False, 2), ("spawn", 2, "next_step", 4), ("spawn", 2, "same_step", 3),
    ("action_mask", 5, "same_step", 3), ("spawn", 1, False, 0), ("observation", 1, False, 0),
    ("lidar", 2, False, 1), ("lidar", 5, "same_step", 3), ("lidar", 5, "next_step", 4),
]


@item(8)
@pytest.mark.parametrize("hook, call, autoreset, failing_step, options", [
    (*case, options) for options in ({}, LOOKS) for case in FAILURES if case[0] != "lidar" or options])
def test_a_hook_that_raises_leaves_the_env_as_it_was(hook, call, autoreset, failing_step, options):
    """The state, counters, generator, the worlds' appearance ids and looks (the frames that follow)."""
    env = probe(state_obs=True, autoreset=autoreset, **options)
    twin = probe(state_obs=True, autoreset=autoreset, **options)
    env.scenario.fail = (hook, call)
    generator = torch.Generator().manual_seed(0)
    try:
        if failing_step == 0:
            with pytest.raises(RuntimeError, match=f"{hook} failed on purpose"):
                env.reset()
            with pytest.raises(RuntimeError, match=r"call reset\(\) before"):
                env.step(torch.zeros(W, 2, dtype=torch.long))
        assert_same(env.reset(), twin.reset())
        for step in range(1, 7):
            actions = env.random_actions(generator)
            if step == failing_step:
                before = env.get_state()
                with pytest.raises(RuntimeError, match=f"{hook} failed on purpose"):
                    env.step(actions)
                assert_same(env.get_state(), before)  # the RNG, step counts, appearance ids and simulation
            assert_same(env.step(actions), twin.step(actions), f"step {step}")  # the frames too
        assert env.scenario.calls[hook] >= call  # the failure happened where the case says
    finally:
        env.close(), twin.close()


@item(8)
@pytest.mark.parametrize("call", ["reset", "reset_worlds", "set_state"])
def test_a_failed_reset_or_set_state_keeps_the_worlds_looks(call):
    """The new worlds' looks were drawn (and handed to the renderer) before the call failed."""
    env, twin, other = probe(**LOOKS), probe(**LOOKS), probe(**{**LOOKS, "seed": 1})
    actions = torch.zeros(W, 2, dtype=torch.long)
    try:
        env.reset(), twin.reset(), other.reset()
        env.step(actions), twin.step(actions)
        loaded = other.get_state()
        assert not torch.equal(loaded["appearance_ids"], env.appearance_ids)
        before = env.get_state()
        env.scenario.fail = ("instances", env.scenario.calls["instances"] + 1)
        with pytest.raises(RuntimeError, match="instances failed on purpose"):
            {"reset": lambda: env.reset(seed=5), "reset_worlds": lambda: env.reset_worlds(torch.tensor([True, False])),
             "set_state": lambda: env.set_state(loaded)}[call]()
        assert_same(env.get_state(), before)
        assert env.seed == twin.seed == 0
        for _ in range(2):
            assert_same(env.step(actions), twin.step(actions))  # the frames show the committed looks
    finally:
        env.close(), twin.close(), other.close()


@item(8)
def test_an_env_used_under_inference_mode_works_outside_it_and_stays_atomic():
    """An env built or reset under torch.inference_mode() failed every later call outside it (the
    renderer's buffers were inference tensors, which nothing may write into outside it)."""
    with torch.inference_mode():
        env = probe(state_obs=True)
    twin = probe(state_obs=True)
    env.scenario.fail = ("action_mask", 3)
    actions = torch.zeros(W, 2, dtype=torch.long)
    with torch.inference_mode():
        assert_same(env.reset(), twin.reset())
        assert_same(env.step(actions), twin.step(actions))
        with pytest.raises(RuntimeError, match="action_mask failed on purpose"):
            env.step(actions)
        assert_same(env.step(actions), twin.step(actions))
    assert_same(env.step(actions), twin.step(actions))  # and outside it again
    env.close(), twin.close()


class InPlace(Probe):
    """Breaks the contract: writes into the state it is given, then fails."""

    def rules(self, before, moved, actions, alive, generator):
        before.seen.add_(1.0)
        raise RuntimeError("rules failed after writing")


@item(8)
def test_a_hook_that_wrote_into_the_state_and_failed_says_so_and_asks_for_a_reset():
    env = probe(InPlace)
    env.reset()
    with pytest.raises(RuntimeError, match=r"a hook of InPlace wrote into the env's state in place \(state\.seen\) "
                                           r"and the call failed, so it cannot be undone: call reset\(\)"):
        env.step(torch.zeros(W, 2, dtype=torch.long))
    with pytest.raises(RuntimeError, match=r"call reset\(\) before using this InPlace environment"):
        env.step(torch.zeros(W, 2, dtype=torch.long))
    env.close()


@item(8)
def test_steps_from_two_threads_at_once_are_all_taken():
    """Two threads stepping one env: each step read the same state and one of two was lost."""
    env, twin = make_env("spread", num_worlds=W, resolution=RES, seed=0), make_env("spread", num_worlds=W,
                                                                                   resolution=RES, seed=0)
    env.reset(), twin.reset()
    actions = torch.ones(W, 3, dtype=torch.long)
    errors = []

    def run():
        try:
            for _ in range(25):
                env.step(actions)
        except Exception as error:  # noqa: BLE001 (reported below)
            errors.append(error)

    threads = [threading.Thread(target=run) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for _ in range(50):
        twin.step(actions)
    assert errors == [] and env.step_count.tolist() == [50] * W
    assert_same(env.get_state(), twin.get_state())
    env.close(), twin.close()


class NaNRules(Probe):
    def rules(self, before, moved, actions, alive, generator):
        state, *rest = super().rules(before, moved, actions, alive, generator)
        return (dataclasses.replace(state, pos=state.pos.clone().index_fill_(1, torch.tensor([1]), math.nan)),
                *rest)


class NaNReward(Probe):
    def rules(self, before, moved, actions, alive, generator):
        state, reward, *rest = super().rules(before, moved, actions, alive, generator)
        return (state, reward * math.inf, *rest)


@item(8)
@pytest.mark.parametrize("task, words", [
    (NaNRules, r"NaNRules\.rules returned a state with non-finite values \(NaN or Inf\) in state\.pos"),
    (NaNReward, r"NaNReward\.rules's reward must be finite, got NaN or Inf in world\(s\) \[0, 1\]"),
])
def test_non_finite_results_of_rules_are_named_by_hook_and_field(task, words):
    env = probe(task)
    env.reset()
    before = env.get_state()
    with pytest.raises(ValueError, match=words):
        env.step(torch.zeros(W, 2, dtype=torch.long))
    assert_same(env.get_state(), before)
    env.close()


# ---------------------------------------------------------------------- 9. states the env made load back
@item(9)
@pytest.mark.parametrize("autoreset", [False, "next_step", "same_step"])
@pytest.mark.parametrize("name", ENVS)
def test_every_state_the_env_produced_loads_back(name, autoreset):
    """Past max_steps without autoreset too (done worlds keep stepping and counting)."""
    env = make_env(name, num_worlds=W, resolution=RES, seed=0, max_steps=3, autoreset=autoreset)
    env.reset()
    generator = torch.Generator().manual_seed(0)
    for step in range(8):
        env.step(env.heuristic_actions() if step % 2 else env.random_actions(generator))
        state = env.get_state()
        env.set_state(state)
        assert_same(env.get_state(), state)
    if autoreset:
        assert bool((env.step_count <= 3).all())
    else:  # done worlds kept stepping, counting past max_steps
        assert env.step_count.tolist() == [8] * W
    env.close()


class Outside(Probe):
    """Spawns its agents outside the walls (|x| <= 1.5) in the second episode."""

    def spawn(self, generator):
        state = super().spawn(generator)
        return dataclasses.replace(state, pos=state.pos + 4.0) if self.calls["spawn"] > 1 else state


@item(9)
def test_a_spawn_outside_the_walls_is_refused_by_name():
    env = probe(Outside, autoreset="next_step")
    env.reset()
    actions = torch.zeros(W, 2, dtype=torch.long)
    for _ in range(3):
        env.step(actions)
    before = env.get_state()
    with pytest.raises(ValueError, match=r"Outside\.spawn's state\.pos must be within \[\[-1\.5, -1\.5\], "
                                         r"\[1\.5, 1\.5\]\], got values in"):
        env.step(actions)
    assert_same(env.get_state(), before)
    with pytest.raises(ValueError, match=r"Outside\.spawn's state\.pos must be within"):
        env.reset()
    assert_same(env.get_state(), before)
    env.close()



# ---------------------------------------------------------------------- 10. the benchmarks check their arguments first
@item(10)
@pytest.mark.parametrize("argv, words", [
    (["floor", "--rounds", "0"], r"argument --rounds: expected an int >= 1, got 0"),
    (["floor", "--block-seconds", "nan"], r"argument --block-seconds: expected a finite number of seconds > 0, got "
                                          r"'nan'"),
    (["floor", "--env", "spread:x"], r"argument --env: expected NAME:AGENTS with AGENTS an int >= 1, got 'spread:x'"),
    (["floor", "--env", "sprad"], r"argument --env: unknown env 'sprad'"),
    (["floor", "--env", "cartpole:2"], r"argument --env: cartpole takes 1 to 1 agents, got 'cartpole:2'"),
    (["floor", "--worlds", "16", "0"], r"argument --worlds: expected an int >= 1, got 0"),
    # The adversarial pass: the other benchmarks divided by their counts after building everything.
    (["env", "--steps", "0"], r"argument --steps: expected an int >= 1, got 0"),
    (["env", "--worlds", "16", "-1"], r"argument --worlds: expected an int >= 1, got -1"),
    (["render", "--steps", "0"], r"argument --steps: expected an int >= 1, got 0"),
    (["effects", "--steps", "0"], r"argument --steps: expected an int >= 1, got 0"),
    (["scale", "--views", "0"], r"argument --views: expected an int >= 1, got 0"),
    (["parallel", "--workers", "0"], r"argument --workers: expected an int >= 1, got 0"),
    # The recheck: an unknown env ended in a traceback after the first line of work.
    (["env", "--env", "spread:x"], r"argument --env: unknown env 'spread:x'"),
    (["parallel", "--env", "sprad"], r"argument --env: unknown env 'sprad'"),
    (["soak", "--env", "sprad"], r"argument --env: unknown env 'sprad'"),
    (["peers", "--block-seconds", "inf"], r"argument --block-seconds: expected a finite number of seconds > 0, got "
                                          r"'inf'"),
])
def test_the_benchmarks_check_their_arguments_before_any_work(argv, words, capsys):
    with pytest.raises(SystemExit) as exit_:
        bench_main.main(argv)
    assert exit_.value.code == 2
    assert re.search(words, capsys.readouterr().err)
