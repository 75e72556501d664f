"""Levels (envs/levels.py): a reset as a pure function of (task, parameters, level id), train and
test sets that never meet, reset_to_level and levels= through the driver and every front end, the
level-sampler hook (prioritised level replay), and the default path's numbers left as they were."""
from __future__ import annotations

import json
import pathlib
import re
import runpy
import warnings

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from marl_render.baselines import run
from marl_render.envs import levels as lv
from marl_render.envs import make_env, make_parallel_env, make_sb3_env, make_torchrl_env, make_vec_env
from marl_render.envs.scenario import Scenario

warnings.filterwarnings("ignore", message="The given NumPy array is not writable")

TASKS = ("capture_flag", "cartpole", "clean_up", "commons", "cooking", "coop_mining", "forage", "matrix", "push",
         "rooms", "speaker_listener", "spread", "tag", "territory")
DIGESTS = pathlib.Path(__file__).parent / "data" / "default_path_digests.json"
DOC = pathlib.Path(__file__).resolve().parents[1] / "docs" / "levels.md"


def world_state(env, world: int) -> dict:
    """{name: tensor} of one world's part of the state (every field and counter has the worlds first)."""
    return {key: value[world] for key, value in env.get_state().items() if key != "rng"}


def same_world(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)


# ----------------------------------------------------------------------------- the default path
def test_the_default_path_is_bit_identical_to_before_levels():
    """Without levels= every task draws what it drew before levels existed: digests of the state and
    pixels of a reset, a partial reset and 4 autoresetting steps, recorded on main before the change
    (tools/default_path_digests.py), for every task and with appearance on."""
    recorded = json.loads(DIGESTS.read_text())
    if recorded["torch"] != torch.__version__:
        pytest.skip(f"digests were recorded with torch {recorded['torch']}, this is {torch.__version__}")
    tool = runpy.run_path(str(DIGESTS.parents[2] / "tools" / "default_path_digests.py"))
    BUILT_IN, digest = tool["BUILT_IN"], tool["digest"]
    assert set(BUILT_IN) == set(TASKS)
    for name, want in recorded["digests"].items():
        task, _, option = name.partition("+")
        assert digest(task, **({"appearance": "train"} if option else {})) == want, name


# ----------------------------------------------------------------------------- a level is its id
def test_level_k_is_the_same_in_any_slot_batch_and_history():
    """Level k in worlds 0, 5 and 37 of batches of 1, 8 and 64 worlds, after different histories:
    bit-identical state and pixels (rooms: per-world walls and doors; appearance on: the look too)."""
    k = 123_456
    seen = []
    for worlds, slots, history in ((1, (0,), 0), (8, (0, 5), 3), (64, (0, 5, 37), 7)):
        env = make_env("rooms", num_worlds=worlds, resolution=8, seed=worlds, levels="train", appearance="train")
        env.reset()
        for _ in range(history):  # a different past in every batch: steps and resets of other levels
            env.step(env.random_actions())
        mask = torch.zeros(worlds, dtype=torch.bool)
        mask[list(slots)] = True
        obs = env.reset_to_level(mask, torch.full((worlds,), k))
        assert env.level_ids[list(slots)].tolist() == [k] * len(slots)
        seen += [(world_state(env, slot), obs["pixels"][slot]) for slot in slots]
        env.close()
    first_state, first_pixels = seen[0]
    assert first_pixels.float().std() > 0  # a picture, not a blank
    for state, pixels in seen[1:]:
        assert same_world(state, first_state)
        assert torch.equal(pixels, first_pixels)


@pytest.mark.parametrize("name", TASKS)
def test_every_task_resets_a_level_alike_in_any_slot_and_levels_differ(name):
    """Every task: level 9 in slot 2 of 3 worlds equals level 9 in slot 4 of 5 (state and pixels);
    another level is another reset (the level id reaches the draws)."""
    envs = [make_env(name, num_worlds=w, resolution=8, seed=w, levels=50) for w in (3, 5)]
    got = []
    for env, slot in zip(envs, (2, 4), strict=True):
        env.reset()
        mask = torch.zeros(env.num_worlds, dtype=torch.bool)
        mask[slot] = True
        obs = env.reset_to_level(mask, torch.full((env.num_worlds,), 9))
        got.append((world_state(env, slot), obs["pixels"][slot]))
    assert same_world(got[0][0], got[1][0]) and torch.equal(got[0][1], got[1][1])
    envs[0].reset_to_level(torch.ones(3, dtype=torch.bool), torch.tensor([9, 10, 11]))
    states = [world_state(envs[0], w) for w in range(3)]
    assert not same_world(states[0], states[1]) and not same_world(states[1], states[2])
    for env in envs:
        env.close()


@pytest.mark.parametrize("name", TASKS)
def test_train_and_test_levels_never_meet(name):
    """Every task: the levels a train set plays (through resets and autoresets) lie below TEST_START,
    those of the test distribution and the published set at or above it."""
    plays = {}
    for levels in (200, "train", "test", "published"):
        with make_env(name, num_worlds=4, resolution=8, seed=0, levels=levels, autoreset="same_step",
                      max_steps=2) as env:
            env.reset()
            played = [env.level_ids]
            for _ in range(4):
                played.append(env.step(env.random_actions())[4]["level"])
            plays[levels] = torch.cat(played)
    assert bool((plays[200] < 200).all()) and bool((plays["train"] < lv.TEST_START).all())
    for test in ("test", "published"):
        assert bool((plays[test] >= lv.TEST_START).all()) and bool((plays[test] < lv.LEVEL_LIMIT).all())
    assert set(plays["published"].tolist()) <= set(lv.PUBLISHED_TEST_LEVELS)


def test_the_level_sets_are_disjoint_by_construction():
    assert min(lv.PUBLISHED_TEST_LEVELS) >= lv.TEST_START and len(set(lv.PUBLISHED_TEST_LEVELS)) == 1000
    assert lv.as_sampler("test").start == lv.as_sampler("train").stop == lv.TEST_START
    with pytest.raises(ValueError, match=r"levels as a train set must hold ids in \[0, 1099511627776\)"):
        make_env("spread", num_worlds=2, levels=[3, lv.TEST_START])  # a test id in a train list
    with pytest.raises(ValueError, match="reaching the test ids"):
        make_env("spread", num_worlds=2, levels=range(lv.TEST_START - 1, lv.TEST_START + 1))


# ----------------------------------------------------------------------------- state and errors
def test_get_state_and_set_state_keep_the_levels():
    env = make_env("forage", num_worlds=3, resolution=8, seed=0, levels=20, autoreset="next_step", max_steps=3,
                   appearance="heldout")
    env.reset()
    saved = env.get_state()
    assert torch.equal(saved["level_ids"], env.level_ids) and torch.equal(saved["appearance_ids"], env.level_ids)
    actions = [env.random_actions() for _ in range(5)]
    first = [env.step(a) for a in actions]
    env.set_state(saved)
    again = [env.step(a) for a in actions]
    for one, two in zip(first, again, strict=True):
        assert torch.equal(one[0]["pixels"], two[0]["pixels"]) and torch.equal(one[4]["level"], two[4]["level"])
    broken = dict(saved, appearance_ids=saved["appearance_ids"] + 1)
    before = env.get_state()
    with pytest.raises(ValueError, match="appearance_ids'] must equal state\\['level_ids'\\]"):
        env.set_state(broken)
    with pytest.raises(ValueError, match="level_ids'\\] must hold level ids"):
        env.set_state(dict(saved, level_ids=torch.full((3,), -5)))
    assert same_world(world_state(env, 0), {k: v[0] for k, v in before.items() if k != "rng"})
    env.close()


def test_bad_levels_and_reset_to_level_calls_are_refused_and_change_nothing():
    for bad, error in ((0, ValueError), (-3, ValueError), ("easy", ValueError), (2.5, TypeError),
                       (True, TypeError), ([], ValueError), ([1.5], ValueError)):
        with pytest.raises(error, match="levels"):
            make_env("spread", num_worlds=2, levels=bad)
    env = make_env("spread", num_worlds=4, resolution=8, seed=0, levels=10)
    env.reset()
    before = env.get_state()
    mask = torch.tensor([True, False, True, False])
    calls = [((mask, torch.tensor([1.0, 2, 3, 4])), TypeError, "level_ids must be an int64 tensor"),
             ((mask, torch.tensor([1, 2, 3])), ValueError, r"level_ids must be an int64 tensor of shape \[4\]"),
             ((mask, torch.tensor([-1, 0, 3, 0])), ValueError, r"level_ids must hold level ids in \[0, "),
             ((mask, [1, 2, 3, 4]), TypeError, "level_ids must be an int64 tensor"),
             ((torch.tensor([1, 0, 1, 0]), torch.zeros(4, dtype=torch.int64)), TypeError, "mask"),
             ((mask[:3], torch.zeros(4, dtype=torch.int64)), ValueError, r"mask must be a bool tensor of shape \[4\]")]
    for args, error, message in calls:
        with pytest.raises(error, match=message):
            env.reset_to_level(*args)
    after = env.get_state()
    assert all(torch.equal(before[key], after[key]) for key in before)
    # Ids where the mask is False are not read: any value there is fine.
    env.reset_to_level(mask, torch.tensor([3, -7, 4, 2 ** 63 - 1]))
    assert env.level_ids[[0, 2]].tolist() == [3, 4]
    env.close()
    with make_env("spread", num_worlds=2, resolution=8) as plain:
        plain.reset()
        with pytest.raises(ValueError, match="reset_to_level needs an env built with levels="):
            plain.reset_to_level(torch.ones(2, dtype=torch.bool), torch.zeros(2, dtype=torch.int64))


def test_a_task_with_only_spawn_generator_works_but_has_no_levels():
    """A user task that overrides spawn(generator) keeps working without levels; levels= is refused
    by name; a subclass of a built-in task that overrides spawn has no levels either."""
    spread = make_env("spread").scenario.__class__

    class Decorated(spread):
        def spawn(self, generator):
            return super().spawn(generator)

    assert spread.has_levels() and not Decorated.has_levels() and not Scenario.has_levels()
    with make_env(Decorated, num_worlds=2, resolution=8, seed=0) as env:
        env.reset()
    with pytest.raises(ValueError, match="implements only spawn\\(generator\\): levels must be None"):
        make_env(Decorated, num_worlds=2, levels=5)


# ----------------------------------------------------------------------------- the sampler hook
def test_prioritised_level_replay_drives_the_env_and_prefers_high_scores():
    plr = lv.PrioritisedLevelReplay(range(6), temperature=0.5, staleness=0.0)
    generator = torch.Generator().manual_seed(0)
    first = plr.sample(64, generator)
    assert set(first.tolist()) <= set(range(6))  # unscored levels first, uniformly
    plr.update(torch.arange(6), torch.tensor([0.0, 0.1, 5.0, 0.2, 0.3, 0.4]))
    draws = plr.sample(2000, generator)
    counts = torch.bincount(draws, minlength=6)
    assert counts.argmax() == 2 and counts[2] > 0.5 * 2000  # rank 1 of 6 at temperature 0.5: weight 0.68
    with pytest.raises(ValueError, match="outside this sampler's set"):
        plr.update(torch.tensor([99]), torch.tensor([1.0]))
    with make_env("rooms", num_worlds=4, resolution=8, seed=0, levels=plr, autoreset="same_step", max_steps=1) as env:
        env.reset()
        _, _, _, _, info = env.step(env.random_actions())
        assert set(env.level_ids.tolist()) <= set(range(6))
        plr.update(info["final_level"], torch.rand(4, dtype=torch.float64))  # the hook: scores of ended episodes


def test_a_level_sampler_that_returns_bad_ids_is_named():
    class Broken:
        def sample(self, count, generator):
            return torch.full((count,), -1)

    with make_env("spread", num_worlds=2, resolution=8, levels=Broken()) as env:
        with pytest.raises(ValueError, match="sample\\(2, generator\\) must hold level ids"):
            env.reset()


# ----------------------------------------------------------------------------- front ends
def test_levels_through_pettingzoo():
    env = make_parallel_env("spread", resolution=8, levels="published")
    obs, infos = env.reset(seed=0)
    assert all(info["level"] in lv.PUBLISHED_TEST_LEVELS for info in infos.values())
    obs, infos = env.reset(options={"level": 77})
    again, _ = env.reset(options={"level": 77})
    assert {info["level"] for info in infos.values()} == {77}
    assert all(np.array_equal(obs[agent]["pixels"] if isinstance(obs[agent], dict) else obs[agent],
                              again[agent]["pixels"] if isinstance(again[agent], dict) else again[agent])
               for agent in obs)
    _, _, _, _, infos = env.step({agent: env.action_space(agent).sample() for agent in env.agents})
    assert {info["level"] for info in infos.values()} == {77}
    with pytest.raises(TypeError, match="options\\['level'\\] must be an int"):
        env.reset(options={"level": 1.5})
    env.close()


def test_levels_on_a_held_out_scenario():
    """A focal-only env (marl_render.heldout's bots in the other slots) plays levels as its core does."""
    with make_env("tag", heldout="tag/prey_vs_interceptors", num_worlds=2, resolution=8, levels="test") as env:
        env.reset(seed=0)
        obs = env.reset_to_level(torch.tensor([True, True]), torch.tensor([5, 5]))
        assert env.level_ids.tolist() == [5, 5]
        assert torch.equal(obs["pixels"][0], obs["pixels"][1])  # one level, one start: the same view
        env.step(torch.zeros(2, 1, dtype=torch.int64))  # the bots act on the new worlds
    env = make_parallel_env("tag", heldout="tag/prey_vs_interceptors", resolution=8, levels="published")
    _, infos = env.reset(options={"level": 77})
    assert [info["level"] for info in infos.values()] == [77]
    env.close()


def test_levels_through_torchrl():
    env = make_torchrl_env("spread", num_worlds=3, resolution=8, levels=10)
    td = env.reset()
    assert td["info", "level"].dtype == torch.int64 and bool((td["info", "level"] < 10).all())
    td = env.reset(TensorDict({"level_ids": torch.tensor([4, 5, 6])}, batch_size=[3]))
    assert td["info", "level"].tolist() == [4, 5, 6]
    reset = torch.tensor([[False], [True], [False]])
    td = env.reset(TensorDict({"_reset": reset, "level_ids": torch.tensor([0, 9, 0])}, batch_size=[3]))
    assert td["info", "level"][1] == 9 and env.core.level_ids.tolist() == [4, 9, 6]  # TorchRL fills the others
    td = env.rand_step(td)
    assert td["next", "info", "level"].tolist() == [4, 9, 6]
    env.close()


def test_levels_through_the_vector_env_and_sb3():
    envs = make_vec_env("spread", num_worlds=2, resolution=8, levels="test")  # 3 agents: 6 entries
    _, infos = envs.reset(seed=0)
    assert bool((infos["level"] >= lv.TEST_START).all()) and infos["_level"].all()
    _, infos = envs.reset(options={"level_ids": np.array([3, 8])})
    assert infos["level"].tolist() == [3, 3, 3, 8, 8, 8]
    mask = np.array([False] * 3 + [True] * 3)
    _, infos = envs.reset(options={"reset_mask": mask, "level_ids": np.array([0, 5])})
    assert infos["level"].tolist() == [3, 3, 3, 5, 5, 5]
    with pytest.raises(ValueError, match="options\\['level_ids'\\] must be an int64 numpy array of shape \\(2,\\)"):
        envs.reset(options={"level_ids": np.array([1, 2, 3])})
    envs.close()
    venv = make_sb3_env("spread", num_worlds=2, resolution=8, levels=10)
    venv.reset()
    venv.set_options({"level_ids": np.array([7, 7])})
    venv.reset()
    assert venv.get_attr("level_ids")[0].tolist() == [7, 7]
    venv.close()


def test_the_levels_page_runs_as_written(capsys):
    """docs/levels.md: every python block runs (its asserts are the checks: the same level in two
    slots is the same picture, the front ends' level entries, the curriculum's levels)."""
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    assert len(blocks) == 3
    for block in blocks:
        exec(compile(block, str(DOC), "exec"), {})


def test_the_jax_front_end_refuses_levels_it_would_cut_to_32_bits():
    jax = pytest.importorskip("jax")
    from marl_render.envs import make_jax_env  # noqa: PLC0415 (jax is an optional extra)

    if jax.config.jax_enable_x64:
        pytest.skip("64-bit JAX is on in this process")
    with pytest.raises(ValueError, match="levels= with the JAX front end needs 64-bit JAX"):
        make_jax_env("spread", resolution=8, levels=5)


def test_the_generalisation_study_runs_end_to_end(tmp_path):
    """One tiny run of the study (1 update, 2 episodes per set) and its report: every evaluation set
    and the references appear, with the command that reproduces the run (never what it reaches)."""
    from marl_render.baselines import generalisation  # noqa: PLC0415 (the learner: only this test needs it)

    result = generalisation.run_one("speaker_listener", "levels200", 0, root=str(tmp_path), env_steps=1, episodes=2,
                                    worlds=2, rollout=2)
    assert set(result["evaluation"]) == set(generalisation.SETS) and result["training_levels"] == 200
    assert all(r["episodes"] == 2 for r in result["evaluation"].values())
    generalisation.references("speaker_listener", root=str(tmp_path), episodes=2)
    text = generalisation.report(str(tmp_path), str(tmp_path / "page.md"))
    assert "## speaker_listener" in text and "| `levels=200` |" in text and "| heuristic |" in text
    assert "gap: train - test levels" in text and "Runs above random on their own train levels: " in text
    glance = text.split("## At a glance")[1].split("## speaker_listener")[0]
    assert "\n| speaker_listener | " in glance and " of 1 | " in glance  # one run, in the summary too
    assert generalisation.command("speaker_listener", "levels200", 0) in text


@pytest.mark.parametrize("levels", ["published", "test"])
def test_test_levels_are_refused_as_a_training_curriculum(levels):
    with pytest.raises(ValueError, match=rf"PrioritisedLevelReplay needs a finite train set, got levels='{levels}': "
                                         r"the test levels are for evaluation only"):
        lv.PrioritisedLevelReplay(levels)


@pytest.mark.parametrize("levels", ["published", "test"])
def test_the_trainer_refuses_to_train_on_test_levels(levels, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        run.parse_args(["--env", "forage", "--levels", levels, "--out", str(tmp_path / "out")])
    assert exit_.value.code == 2
    assert f"--levels {levels}: the test levels are for evaluation only (--eval-levels {levels})" in \
        capsys.readouterr().err
    assert run.parse_args(["--env", "forage", "--eval-levels", levels, "--out", str(tmp_path / "out")]).eval_levels \
        == levels


@pytest.mark.parametrize("kwargs, error, words", [
    (dict(temperature="a"), TypeError, r"PrioritisedLevelReplay needs temperature to be a number, got 'a'"),
    (dict(staleness=None), TypeError, r"PrioritisedLevelReplay needs staleness to be a number, got None"),
    (dict(temperature=True), TypeError, r"needs temperature to be a number, got True"),
])
def test_prioritised_level_replay_names_a_setting_that_is_not_a_number(kwargs, error, words):
    with pytest.raises(error, match=words):
        lv.PrioritisedLevelReplay(range(4), **kwargs)


@pytest.mark.parametrize("levels", [np.array(5), torch.tensor(5)])
def test_a_scalar_array_as_levels_is_named(levels):
    with pytest.raises(TypeError, match=r"levels must be .*got a 0-d .*: pass int\(levels\) for a count"):
        lv.as_sampler(levels)
    with pytest.raises(TypeError, match=r"levels must be .*got a 0-d"):
        make_env("spread", num_worlds=1, resolution=8, levels=levels)


# ----------------------------------------------------------------------------- the picture
SLOT_PLAN = ((2, {0: 7, 1: 8}), (5, {4: 7, 2: 9, 1: 8}), (3, {2: 9}))  # (worlds, {slot: level id})


def pictures_by_level(name: str, resolution: int = 16, **views) -> dict:
    """{level id: [uint8 pixels of that level's world, one per (batch, slot) it was reset into]}: test
    levels 7, 8 and 9 reset into several slots of batches of 2, 5 and 3 worlds (appearance on), each
    after random steps of its own (as the issue's reproduction: level 7 in slot 0 of 2 worlds and in
    slot 5 of 7); `views`: how the env draws its views (exact_tiles=True or layered=True)."""
    seen = {}
    for worlds, plan in SLOT_PLAN:
        with make_env(name, num_worlds=worlds, resolution=resolution, levels="test", seed=123,
                      appearance="train", **views) as env:
            env.reset()
            for _ in range(2):
                env.step(env.random_actions())
            mask = torch.zeros(worlds, dtype=torch.bool)
            ids = torch.zeros(worlds, dtype=torch.int64)
            for slot, level in plan.items():
                mask[slot], ids[slot] = True, level
            pixels = env.reset_to_level(mask, ids)["pixels"]
            for slot, level in plan.items():
                seen.setdefault(level, []).append(pixels[slot].clone())
    return seen


@pytest.mark.parametrize("views, resolution", [({"exact_tiles": True}, 16), ({"layered": True}, 64)],
                         ids=["exact_tiles", "layered"])
@pytest.mark.parametrize("name", TASKS)
def test_a_level_is_the_same_picture_in_any_slot_and_batch_size(name, views, resolution):
    """exact_tiles=True and layered=True: every task's level gives bit-identical pixels (every agent's
    view) in any world slot at any batch size, with appearance on. Without them the rasteriser's
    rounding depends on where a view's tile sits in the framebuffer (docs/levels.md says how)."""
    seen = pictures_by_level(name, resolution, **views)
    assert {level: len(p) for level, p in seen.items()} == {7: 2, 8: 2, 9: 2}
    for level, pictures in seen.items():
        first = pictures[0]
        assert first.dtype == torch.uint8 and first.float().std() > 0  # a picture, not a blank
        assert first.shape[-3:-1] == (resolution, resolution)
        for other in pictures[1:]:
            assert torch.equal(other, first), (name, level, int((other != first).any(-1).sum()))
    assert not torch.equal(seen[7][0], seen[8][0])  # levels differ


@pytest.mark.parametrize("option", ["exact_tiles", "layered"])
def test_exact_tiles_and_layered_must_be_bools(option):
    with pytest.raises(TypeError, match=f"{option} must be a bool, got"):
        make_env("spread", num_worlds=1, resolution=8, **{option: 1})


def test_layered_refuses_multisamples_and_exact_tiles_naming_both():
    for other in ({"multisamples": 4}, {"exact_tiles": True}):
        with pytest.raises(ValueError, match="layered=True cannot be combined with exact_tiles or multisamples"):
            make_env("spread", num_worlds=1, resolution=8, layered=True, **other)
