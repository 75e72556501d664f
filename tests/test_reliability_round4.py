"""Reliability round 4 (issue 24): the env's memory, atomic steps, states that load back, and the
traps a task author meets. Each test failed before its fix; the numbers in the section titles
are the issue's items. Cases that compile (item 6) run in a child process with a timeout."""
from __future__ import annotations

import argparse
import collections
import dataclasses
import math
import re
import subprocess
import sys
import textwrap
import threading
import warnings

import gymnasium
import numpy as np
import pytest
import torch

from departing_env import Departing
from marl_render.bench import __main__ as bench_main
from marl_render.bench import peers
from marl_render.envs import (
    ArenaScenario,
    ArenaState,
    Prop,
    list_envs,
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

W = 2
RES = 8
ENVS = list_envs()

pytestmark = pytest.mark.usefixtures("single_torch_thread")


# ---------------------------------------------------------------------- a small task to break on purpose
@dataclasses.dataclass(frozen=True)
class ProbeState(ArenaState):
    seen: torch.Tensor  # [W, A, 3] float32: handed out by observation() as it is
    flag: torch.Tensor  # [W, 1, 2] a prop's place


class Probe(ArenaScenario):
    """Two agents; observation() returns a state field as it is, action_mask() one constant tensor,
    and the reward reads the field. ``fail = (hook, n)`` makes the n-th call of that hook raise."""

    name, State, physics_terms = "probe", ProbeState, frozenset({"walls", "drag"})
    default_num_agents, agent_range, default_max_steps = 2, (2, 2), 3  # episodes end at the third step
    info_keys = {"seen_sum": torch.float32}
    fail = None

    def setup(self):
        self.setup_arena({"agents": numbered("agent", 2)}, state_dim=3, radius=0.15, max_speed=2.0)
        self.calls = collections.Counter()
        self.everything = torch.ones(self.num_worlds, 2, self.num_actions, dtype=torch.bool)

    def check(self, hook):
        self.calls[hook] += 1
        if self.fail == (hook, self.calls[hook]):
            raise RuntimeError(f"{hook} failed on purpose")

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self.at_rest(torch.zeros(W, N, 2), torch.zeros(W, N), seen=torch.zeros(W, N, 3),
                            flag=torch.zeros(W, 1, 2))

    def props(self):
        return [Prop("flag", "box", count=1, position="flag", height=0.2, scale=(0.2, 0.2, 0.4), moves=False)]

    def spawn(self, generator):
        self.check("spawn")
        W, N = self.num_worlds, self.num_agents
        pos = torch.rand(W, N, 2, generator=generator) * 2 - 1
        return self.at_rest(pos, torch.zeros(W, N), seen=torch.rand(W, N, 3, generator=generator) + 1,
                            flag=torch.rand(W, 1, 2, generator=generator) - 0.5)

    def rules(self, before, moved, actions, alive, generator):
        self.check("rules")
        noise = torch.rand(self.num_worlds, generator=generator)  # draws: a failed step must not lose them
        reward = before.seen.sum(-1) + noise[:, None]
        return moved, reward, torch.zeros_like(alive), {"seen_sum": before.seen.sum((1, 2))}

    def observation(self, state, alive):
        self.check("observation")
        return state.seen

    def action_mask(self, state, alive):
        self.check("action_mask")
        return self.everything

    def instances(self, state, full):
        self.check("instances")
        return super().instances(state, full)


def probe(task=Probe, **kwargs):
    return make_env(task, **{"num_worlds": W, "resolution": RES, "seed": 0, **kwargs})


def assert_same(a, b, where=""):
    """Nested dicts / tuples of tensors are equal, bit for bit."""
    if isinstance(a, torch.Tensor):
        assert torch.equal(a, b), where
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            assert_same(a[key], b[key], f"{where}[{key!r}]")
    else:
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")


def tensors(value):
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, dict):
        for item in value.values():
            yield from tensors(item)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from tensors(item)


def scribble(value) -> None:
    """Write into every tensor of `value`, as a caller that owns them may."""
    for tensor in tensors(value):
        if tensor.dtype == torch.bool:
            tensor.logical_not_()
        else:
            tensor.fill_(3)


# ---------------------------------------------------------------------- 1. what the env hands out is the caller's
@pytest.mark.parametrize("autoreset", [False, "next_step", "same_step"])
@pytest.mark.parametrize("name", ENVS)
def test_writing_into_what_the_env_returned_changes_nothing(name, autoreset):
    """obs (pixels, state, action_mask), rewards, flags, info (commons' depleted_at), final_obs,
    state_observation() and heuristic_actions(): all the caller's. A twin that never sees the
    writes stays bit-identical."""
    kwargs = dict(num_worlds=W, resolution=RES, seed=0, state_obs=True, autoreset=autoreset, max_steps=2)
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
    ("spawn", 2, "next_step", 4), ("spawn", 2, "same_step", 3), ("action_mask", 5, "same_step", 3),
    ("spawn", 1, False, 0), ("observation", 1, False, 0),
]


@pytest.mark.parametrize("hook, call, autoreset, failing_step", FAILURES)
def test_a_hook_that_raises_leaves_the_env_as_it_was(hook, call, autoreset, failing_step):
    env = probe(state_obs=True, autoreset=autoreset)
    twin = probe(state_obs=True, autoreset=autoreset)
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
                assert_same(env.get_state(), before)  # the RNG, step counts and simulation
            assert_same(env.step(actions), twin.step(actions), f"step {step}")  # the frames too
    finally:
        env.close(), twin.close()


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


def test_a_hook_that_wrote_into_the_state_and_failed_says_so_and_asks_for_a_reset():
    env = probe(InPlace)
    env.reset()
    with pytest.raises(RuntimeError, match=r"a hook of InPlace wrote into the env's state in place \(state\.seen\) "
                                           r"and the call failed, so it cannot be undone: call reset\(\)"):
        env.step(torch.zeros(W, 2, dtype=torch.long))
    with pytest.raises(RuntimeError, match=r"call reset\(\) before using this InPlace environment"):
        env.step(torch.zeros(W, 2, dtype=torch.long))
    env.close()


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


# ---------------------------------------------------------------------- 10 (bench floor) and 14 (bench peers)
@pytest.mark.parametrize("argv, words", [
    (["--rounds", "0"], r"argument --rounds: expected an int >= 1, got 0"),
    (["--block-seconds", "nan"], r"argument --block-seconds: expected a finite number of seconds > 0, got 'nan'"),
    (["--env", "spread:x"], r"argument --env: expected NAME:AGENTS with AGENTS an int >= 1, got 'spread:x'"),
    (["--env", "sprad"], r"argument --env: unknown env 'sprad'"),
    (["--env", "cartpole:2"], r"argument --env: cartpole takes 1 to 1 agents, got 'cartpole:2'"),
    (["--worlds", "16", "0"], r"argument --worlds: expected an int >= 1, got 0"),
])
def test_bench_floor_checks_its_arguments_before_any_work(argv, words, capsys):
    with pytest.raises(SystemExit) as exit_:
        bench_main.main(["floor", *argv])
    assert exit_.value.code == 2
    assert re.search(words, capsys.readouterr().err)


def test_bench_peers_records_compile_physics_in_its_command():
    parser = argparse.ArgumentParser()
    peers.add_arguments(parser)
    assert "--compile-physics" in peers.command_line(parser.parse_args(["--compile-physics"])).split()
    assert "--compile-physics" not in peers.command_line(parser.parse_args([])).split()
