"""Reliability round 4 (issue 24): the env's memory, atomic steps, states that load back, and the
traps a task author meets. Each test failed before its fix; the numbers in the section titles
are the issue's items. Cases that compile (item 6) run in a child process with a timeout, and so
do those of items 7-10 (tests/isolated_crash_cases.py), which could crash or hang before their fixes."""
from __future__ import annotations

import argparse
import dataclasses
import pathlib
import subprocess
import sys
import textwrap
import warnings

import gymnasium
import numpy as np
import pytest
import torch

import isolated_crash_cases
from departing_env import Departing
from marl_render import play
from marl_render.bench import peers
from marl_render.envs import (
    ArenaState,
    Prop,
    make_env,
    make_parallel_env,
    make_torchrl_env,
    make_vec_env,
    numbered,
    planar,
)
from marl_render.envs import cartpole as cartpole_module
from marl_render.envs import compiled as compiled_kernels
from marl_render.envs.evaluation import evaluate, random_policy
from probe_task import ENVS, LOOKS, RES, Probe, ProbeState, W, assert_same, probe, scribble

pytestmark = pytest.mark.usefixtures("single_torch_thread")


# ---------------------------------------------------------------------- 1. what the env hands out is the caller's
@pytest.mark.parametrize("autoreset", [False, "next_step", "same_step"])
@pytest.mark.parametrize("name", ENVS)
def test_writing_into_what_the_env_returned_changes_nothing(name, autoreset):
    """obs (pixels, state, action_mask), rewards, flags, info (commons' depleted_at), final_obs,
    state_observation() and heuristic_actions(): all the caller's. A twin that never sees the
    writes stays bit-identical."""
    scribble_and_compare(name, autoreset=autoreset)


@pytest.mark.parametrize("autoreset", [False, "same_step"])
def test_lidar_and_appearance_ids_handed_out_are_the_callers(autoreset):
    scribble_and_compare("tag", autoreset=autoreset, **LOOKS)


def scribble_and_compare(name, **options):
    kwargs = dict(num_worlds=W, resolution=RES, seed=0, state_obs=True, max_steps=2, **options)
    with make_env(name, **kwargs) as env, make_env(name, **kwargs) as twin:
        scribble(env.reset())
        twin.reset()
        generator = torch.Generator().manual_seed(0)
        for _ in range(4):
            actions = env.random_actions(generator)
            got, expected = env.step(actions), twin.step(actions)
            assert_same(got, expected)
            scribble(got)
            scribble(env.state_observation())
            scribble(env.heuristic_actions())
            assert_same(env.get_state(), twin.get_state())
            scribble(env.get_state())


class LidarEcho(Probe):
    """Its lidar hook returns a state field as it is (3 rays)."""

    def lidar(self, state, rays, reach):
        return state.seen


def test_a_state_field_handed_out_as_lidar_is_a_copy():
    env = probe(LidarEcho, lidar=3)
    obs = env.reset()
    assert torch.equal(obs["lidar"], env.sim.seen)
    obs["lidar"].zero_()
    assert bool((env.sim.seen >= 1).all())
    env.close()


def test_a_state_field_handed_out_as_observation_is_a_copy():
    env = probe(state_obs=True)
    obs = env.reset()
    assert torch.equal(obs["state"], env.sim.seen)
    obs["state"].zero_()
    obs["action_mask"][:] = False
    assert bool((env.sim.seen >= 1).all()) and bool(env.scenario.everything.all())
    pixels = obs["pixels"]
    obs, reward, *_ = env.step(torch.zeros(W, 2, dtype=torch.long))
    assert obs["pixels"].untyped_storage().data_ptr() != pixels.untyped_storage().data_ptr()  # a new readback
    assert bool(obs["action_mask"].all()) and bool((reward >= 2).all())
    env.close()


@dataclasses.dataclass(frozen=True)
class EchoState(Departing.State):
    seen: torch.Tensor  # [W, A, 3] float32


class DepartingEcho(Departing):
    """Departing (prey leave in world 0), its observation a state field that the reward reads."""

    State = EchoState

    def setup(self):
        super().setup()
        self.state_dim = 3

    def at_rest(self, pos, yaw, **extra):
        return super().at_rest(pos, yaw, **{"seen": torch.ones(pos.shape[0], 3, 3), **extra})

    def rules(self, before, moved, actions, alive, generator):
        state, _, terminated, info = super().rules(before, moved, actions, alive, generator)
        shared = before.seen.sum((1, 2))[:, None].expand(-1, 3)
        return state, shared, terminated, info

    def observation(self, state, alive):
        return state.seen


def test_black_death_zeros_do_not_reach_the_simulation():
    """The issue's case: the vector env zeroes departed agents' observations; when those were the
    state itself, the shared reward changed (4.17 in the core, 2.33 through the vector env)."""
    kwargs = dict(num_worlds=W, resolution=RES, seed=0, state_obs=True)
    core = make_env(DepartingEcho, **kwargs)
    vec = make_vec_env(DepartingEcho, autoreset_mode=gymnasium.vector.AutoresetMode.DISABLED, **kwargs)
    core.reset()
    vec.reset(seed=0)
    actions = torch.zeros(W, 3, dtype=torch.long)
    for _ in range(5):
        _, reward, *_ = core.step(actions)
        _, vec_reward, *_ = vec.step(actions.reshape(-1).numpy())
        np.testing.assert_array_equal(vec_reward, reward.reshape(-1).numpy())
    assert bool((vec.core.sim.seen == 1).all())
    core.close(), vec.close()

    pz = make_parallel_env(DepartingEcho, resolution=RES, seed=0, state_obs=True, black_death=True)
    pz.reset(seed=0)
    for _ in range(4):
        pz.step({agent: 0 for agent in pz.agents})
    pz.state()[:] = 0
    assert bool((pz.core.sim.seen == 1).all())
    pz.close()


@pytest.mark.parametrize("group_map", ["one_group", "team"])
def test_torchrl_action_masks_are_the_callers(group_map):
    env = make_torchrl_env("speaker_listener", num_worlds=W, resolution=RES, group_map=group_map)
    td = env.reset()
    masks = [td[group, "action_mask"] for group in env.group_map]
    expected = [mask.clone() for mask in masks]
    for mask in masks:
        mask.zero_()
    td = env.rand_step(env.reset())
    for group, mask in zip(env.group_map, expected, strict=True):
        assert torch.equal(td["next", group, "action_mask"], mask)
    env.close()


@dataclasses.dataclass(frozen=True)
class MemoState(ProbeState):
    last: torch.Tensor  # [W, A] int64: the actions of the last step


class Memo(Probe):
    """Keeps the actions it is given in its state (the driver must hand it a copy)."""

    State = MemoState

    def at_rest(self, pos, yaw, **extra):
        return super().at_rest(pos, yaw, **{"last": torch.zeros(pos.shape[0], 2, dtype=torch.long), **extra})

    def rules(self, before, moved, actions, alive, generator):
        state, *rest = super().rules(before, moved, actions, alive, generator)
        return (dataclasses.replace(state, last=actions), *rest)


@pytest.mark.parametrize("kind", ["tensor", "numpy"])
def test_actions_the_env_keeps_are_its_own(kind):
    env = probe(Memo)
    env.reset()
    actions = torch.ones(W, 2, dtype=torch.long)
    actions = actions if kind == "tensor" else actions.numpy()
    env.step(actions)
    actions[:] = 4  # a rollout buffer written in place
    assert bool((env.sim.last == 1).all())
    env.close()


class Forbidding(Probe):
    """Agent 0 may never go forward (action 1)."""

    def action_mask(self, state, alive):
        mask = super().action_mask(state, alive).clone()
        mask[:, 0, 1] = False
        return mask


def test_a_step_that_enforce_action_mask_refuses_changes_nothing():
    """The state, counters, generator and appearance ids; the frames that follow equal a twin's."""
    env, twin = (probe(Forbidding, enforce_action_mask=True, **LOOKS) for _ in range(2))
    env.reset(), twin.reset()
    before = env.get_state()
    with pytest.raises(ValueError, match=r"got 2 forbidden: world 0 agent 'agent_0' took 1 \('forward'\)"):
        env.step(torch.tensor([[1, 1]] * W))
    assert_same(env.get_state(), before)
    allowed = torch.tensor([[2, 1]] * W)
    assert_same(env.step(allowed), twin.step(allowed))
    env.close(), twin.close()


# ---------------------------------------------------------------------- 2. the driver's info names are reserved
@pytest.mark.parametrize("key", ["step_count", "done_worlds", "autoreset_worlds", "final_obs"])
def test_a_task_info_key_with_a_driver_name_is_refused(key):
    task = type("Clash", (Probe,), {"info_keys": {**Probe.info_keys, key: torch.bool}})
    with pytest.raises(ValueError, match=rf"Clash\.info_keys names \['{key}'\], which the driver's own info"):
        probe(task)


# ---------------------------------------------------------------------- 3. obstacles are solid or refused
class Pillar(Probe):
    """One box the physics must know of."""

    def obstacles(self, state):
        W = self.num_worlds
        return planar.Obstacles(torch.zeros(W, 1, 2), torch.full((W, 1, 2), 0.3), torch.zeros(W, 1))


def test_obstacles_without_the_obstacles_term_are_refused_by_name():
    with pytest.raises(ValueError, match=r"Pillar\.obstacles returns 1 box\(es\) but physics_terms \['drag', "
                                         r"'walls'\] has no 'obstacles'"):
        probe(Pillar)
    solid = type("SolidPillar", (Pillar,), {"physics_terms": frozenset({"walls", "drag", "obstacles"})})
    env = probe(solid)
    env.reset()
    state = env.get_state()
    state["pos"][:] = torch.tensor([[0.0, -0.6], [1.0, 1.0]])
    state["yaw"][:] = 0.0  # facing +y: straight at the box
    env.set_state(state)
    for _ in range(15):
        env.step(torch.tensor([[1, 0]] * W))
    assert bool((env.sim.pos[:, 0, 1] <= -0.3 - 0.15 + 1e-4).all())  # stopped at the box's face
    env.close()


# ---------------------------------------------------------------------- 4. reward weights that overflow float32
WEIGHTS = [("push", "shaping"), ("push", "goal_reward"), ("capture_flag", "shaping"),
           ("capture_flag", "capture_reward"), ("rooms", "found_reward"), ("rooms", "step_penalty"),
           ("rooms", "explore_reward"), ("tag", "catch_reward"), ("tag", "shaping"), ("spread", "collision_penalty"),
           ("forage", "item_reward")]


@pytest.mark.parametrize("name, weight", WEIGHTS)
def test_reward_weights_that_overflow_float32_are_refused(name, weight):
    with pytest.raises(ValueError, match=rf"{weight} must be a number >=? 0 and <= 1e\+06 .*got 1e\+39"):
        make_env(name, **{weight: 1e39})


@pytest.mark.parametrize("name", sorted({name for name, _ in WEIGHTS}))
def test_the_largest_reward_weights_give_finite_rewards(name):
    weights = {weight: 1e6 for task, weight in WEIGHTS if task == name}
    env = make_env(name, num_worlds=W, resolution=RES, seed=0, **weights)
    env.reset()
    generator = torch.Generator().manual_seed(0)
    for step in range(6):
        actions = env.heuristic_actions() if step % 2 else env.random_actions(generator)
        _, reward, *_ = env.step(actions)
        assert bool(torch.isfinite(reward).all())
    env.close()


@pytest.mark.parametrize("name, keyword", [("commons", "tag_timeout"), ("forage", "respawn_delay"),
                                           ("capture_flag", "captures_to_win")])
def test_step_counts_beyond_int64_are_refused(name, keyword):
    with pytest.raises(ValueError, match=rf"{keyword} must be an int in \[\d, 1000000000\], got {2 ** 70}"):
        make_env(name, **{keyword: 2 ** 70})


# ---------------------------------------------------------------------- 6. compile_physics never raises in a step
COMPILE_CHILD = textwrap.dedent("""
    import torch, torch._dynamo
    from torch._dynamo.utils import counters
    from marl_render.envs import make_env
    torch._dynamo.config.recompile_limit = 1  # what three sizes and two modes reached at 8: reached at once
    envs = [make_env("cartpole", num_worlds=w, resolution=8, seed=0, continuous=True, compile_physics=True)
            for w in (2, 3)]
    defaults = [make_env("cartpole", num_worlds=w, resolution=8, seed=0, continuous=True) for w in (2, 3)]
    graphs = counters["stats"]["unique_graphs"]
    for env in envs + defaults:
        env.reset()
    for mode in ("plain", "inference", "plain", "inference"):
        for env, default in zip(envs, defaults):
            actions = torch.linspace(-1, 1, env.num_worlds)[:, None, None]
            with torch.inference_mode(mode == "inference"):
                env.step(actions), default.step(actions)
            assert env.physics_compiled, env.num_worlds
            gap = float((env.sim.qstate - default.sim.qstate).abs().max())
            assert gap < 1e-12, gap
    assert counters["stats"]["unique_graphs"] == graphs, "a step compiled again"
    print("ok", graphs)
""")


def test_compiled_physics_steps_in_every_mode_without_recompiling():
    child = subprocess.run([sys.executable, "-c", COMPILE_CHILD], capture_output=True, text=True, timeout=400)
    assert child.returncode == 0, child.stderr[-3000:]
    assert child.stdout.split() == ["ok", "2"]  # one graph per env size, compiled when the env was built


def test_a_compiled_kernel_that_fails_in_a_step_falls_back_for_good():
    def broken(*args):
        raise RuntimeError("recompile limit reached")

    with probe_cartpole() as env, probe_cartpole() as default:
        env.scenario._kernel = compiled_kernels.Kernel(broken, "cartpole physics for 2 worlds")
        assert env.physics_compiled
        actions = torch.full((W, 1, 1), 0.5)
        env.reset(), default.reset()
        with pytest.warns(RuntimeWarning, match=r"the compiled cartpole physics for 2 worlds failed in a step "
                                                r"\(RuntimeError: recompile limit reached\); this env takes the "
                                                r"default path from now on"):
            assert_same(env.step(actions), default.step(actions))
        assert not env.physics_compiled
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # once
            assert_same(env.step(actions), default.step(actions))


def probe_cartpole():
    return make_env("cartpole", num_worlds=W, resolution=RES, seed=0, continuous=True)


# ---------------------------------------------------------------------- 7-10. in a child process
ISOLATED = pathlib.Path(isolated_crash_cases.__file__)


@pytest.mark.parametrize("item", sorted(isolated_crash_cases.ITEMS))
def test_in_a_child_process(item):
    """The tests of an item in isolated_crash_cases.py, all their cases, in a fresh Python under a timeout
    (a bound on a hang, not on speed): a crash or a hang there fails this test, not the session."""
    tests = [f"{ISOLATED}::{name}" for name in isolated_crash_cases.ITEMS[item]]
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *tests]
    try:
        child = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=ISOLATED.parent.parent)
    except subprocess.TimeoutExpired as error:
        output = error.stdout.decode(errors="replace") if isinstance(error.stdout, bytes) else error.stdout or ""
        pytest.fail(f"item {item} hung: no result after {error.timeout} s; its output so far:\n{output[-3000:]}")
    assert child.returncode == 0, (f"item {item}: exit status {child.returncode}\n"
                                   f"{child.stdout[-4000:]}{child.stderr[-2000:]}")


def test_every_isolated_test_belongs_to_an_item():
    tests = {name for name in vars(isolated_crash_cases) if name.startswith("test_")}
    assert sorted(tests) == sorted(name for names in isolated_crash_cases.ITEMS.values() for name in names)


# ---------------------------------------------------------------------- 11. TorchRL group names
class NamedTeams(Probe):
    team_names = ("next", "other")

    def setup(self):
        super().setup()
        self.teams = dict(zip(self.team_names, (["agent_0"], ["agent_1"]), strict=True))


@pytest.mark.parametrize("team, words", [("next", r"group names \['next'\] clash with TorchRL's root keys"),
                                         ("", r"group names must be non-empty str .*got \[''\]")])
def test_torchrl_refuses_group_names_it_cannot_use(team, words):
    task = type("Teams", (NamedTeams,), {"team_names": (team, "other")})
    with pytest.raises(ValueError, match=words):
        make_torchrl_env(task, num_worlds=W, resolution=RES)
    if team:  # an explicit group map already refused "" (a TypeError)
        with pytest.raises(ValueError, match=words):
            make_torchrl_env("spread", num_worlds=W, resolution=RES,
                             group_map={team: ["agent_0", "agent_1", "agent_2"]})


# ---------------------------------------------------------------------- 12. gymnasium.make_vec with team sizes
@pytest.mark.parametrize("num_envs, worlds", [(5, 1), (10, 2)])
def test_make_vec_counts_the_agents_the_task_keywords_set(num_envs, worlds):
    envs = gymnasium.make_vec("marl_render/tag-v0", num_envs=num_envs, num_prey=2, resolution=RES)
    assert (envs.num_envs, envs.num_worlds, envs.num_agents) == (num_envs, worlds, 5)
    envs.close()
    with pytest.raises(ValueError, match=r"num_envs must be a multiple of num_agents=5 for 'tag'"):
        gymnasium.make_vec("marl_render/tag-v0", num_envs=4, num_prey=2, resolution=RES)


# ---------------------------------------------------------------------- 13. early, clear errors
class PlainParams(Probe):
    class Params:  # not a dataclass
        pass


def test_params_that_are_not_a_dataclass_are_named():
    with pytest.raises(TypeError, match=r"PlainParams\.Params must be a dataclass of the task's keywords"):
        make_env(PlainParams, num_worlds=W)


class NoStateObs(Probe):
    def setup(self):
        super().setup()
        self.state_dim = 0


class Unbatched(Probe):
    """A field without the worlds axis (length 2: W's, by chance)."""

    @dataclasses.dataclass(frozen=True)
    class State(ProbeState):
        weights: torch.Tensor

    def at_rest(self, pos, yaw, **extra):
        return super().at_rest(pos, yaw, weights=torch.ones(2), **extra)


class ThreeValues(Probe):
    def rules(self, before, moved, actions, alive, generator):
        return super().rules(before, moved, actions, alive, generator)[:3]


class BadHeuristic(Probe):
    def heuristic(self, state, alive):
        return torch.zeros(self.num_worlds, dtype=torch.long)


class TeamsByKeyword(Probe):
    @dataclasses.dataclass(frozen=True)
    class Params:
        scouts: int = 3

    def setup(self):
        self.setup_arena({"scouts": numbered("scout", self.params.scouts)}, state_dim=3, radius=0.15, max_speed=2.0)


class MissingField(Probe):
    def props(self):
        return [Prop("flag", "box", count=1, position="flags", height=0.2)]


class NoStateClass(Probe):
    State = ArenaState


class EmptyProp(Probe):
    def props(self):
        return [Prop("flag", "box", count=0, position=lambda state: state.flag[:, :0], height=0.2)]


class AllOpponents(Probe):
    opponents = ("agents",)


@pytest.mark.parametrize("task, kwargs, error, words", [
    (NoStateObs, dict(state_obs=True), ValueError, r"state_obs=True needs a task with a state observation, and "
                                                   r"NoStateObs has none"),
    (type("Still", (Probe,), {"dt": 0}), {}, ValueError, r"Still\.dt \(simulated seconds per step\) must be a finite "
                                                          r"number > 0, got 0"),
    (Unbatched, {}, ValueError, r"Unbatched\.initial_state's field 'weights' must be a tensor with the worlds first, "
                                r"\[W, \.\.\.\] .*with W=2 it has shape \[2\], with W=1 shape \[2\]"),
    (TeamsByKeyword, {}, ValueError, r"TeamsByKeyword\.setup_arena: teams hold 3 agents but the env is built for "
                                     r"num_agents=2; .* num_agents_for"),
    (MissingField, {}, ValueError, r"MissingField\.props: Prop 'flag''s position names 'flags', which is not a "
                                   r"field of the state"),
    (NoStateClass, {}, TypeError, r"NoStateClass\.State is ArenaState, which has no field\(s\) \['flag', 'seen'\]"),
    (EmptyProp, {}, ValueError, r"EmptyProp\.props: Prop 'flag''s count must be an int >= 1, got 0"),
])
def test_a_task_author_mistake_is_named_when_the_env_is_built(task, kwargs, error, words):
    with pytest.raises(error, match=words):
        probe(task, **kwargs)


def test_hooks_with_the_wrong_result_are_named():
    env = probe(ThreeValues)
    env.reset()
    with pytest.raises(TypeError, match=r"ThreeValues\.rules must return \(state, reward, terminated, info\), got"):
        env.step(torch.zeros(W, 2, dtype=torch.long))
    env.close()
    env = probe(BadHeuristic)
    env.reset()
    with pytest.raises(ValueError, match=r"BadHeuristic\.heuristic must return valid actions: actions must be .*"
                                         r"got shape \[2\]"):
        env.heuristic_actions()
    env.close()


def test_options_are_checked_before_compiling(monkeypatch):
    compiled = []
    monkeypatch.setattr(cartpole_module, "compile_kernel", lambda *args, **kwargs: compiled.append(args))
    for bad in (dict(multisamples=-1), dict(supersample=0), dict(multisamples=4, depth=True)):
        with pytest.raises((TypeError, ValueError), match="multisamples|supersample"):
            make_env("cartpole", num_worlds=W, resolution=RES, compile_physics=True, **bad)
    assert compiled == []


def test_numpy_ints_are_taken_for_multisamples():
    env = make_env("spread", num_worlds=1, resolution=RES, multisamples=np.int64(4), supersample=np.int64(1))
    assert env.renderer.multisamples == 4 and type(env.renderer.multisamples) is int
    env.close()


def test_evaluating_a_task_of_opponents_only_is_refused():
    with pytest.raises(ValueError, match=r"AllOpponents\.opponents \['agents'\] names every team \['agents'\], so "
                                         r"no agent is evaluated"):
        evaluate(AllOpponents, random_policy, episodes=2, resolution=RES)


# ---------------------------------------------------------------------- 14. bench peers
def test_bench_peers_records_compile_physics_in_its_command():
    parser = argparse.ArgumentParser()
    peers.add_arguments(parser)
    assert "--compile-physics" in peers.command_line(parser.parse_args(["--compile-physics"])).split()
    assert "--compile-physics" not in peers.command_line(parser.parse_args([])).split()


# ---------------------------------------------------------------------- the adversarial pass: play's --frames
@pytest.mark.parametrize("where", ["a file", "inside a file"])
def test_play_checks_its_frames_folder_before_playing(where, tmp_path, capsys, framebuffers_made):
    """A --frames that cannot be a folder failed with a traceback after the whole sequence was played."""
    (tmp_path / "taken").write_text("")
    folder = tmp_path / "taken" if where == "a file" else tmp_path / "taken" / "frames"
    assert play.main(["tag", "--keys", "w w", "--frames", str(folder)]) == 2
    assert f"marl_render.play: --frames '{folder}': cannot be made a folder" in capsys.readouterr().err
    assert framebuffers_made == []  # no env was built
