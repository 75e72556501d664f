"""Bad input everywhere in the environment API: a clear error that names the argument, the
expected and the given, and no change of state.

Table-driven over every registered environment: constructor keywords (make_env and the
PettingZoo / TorchRL front ends), BatchedEnv.step with bad discrete and continuous actions,
reset / reset_worlds / render_overview arguments, PettingZoo step dicts and TorchRL action
tensors. After every rejected call the whole state (env tensors, counters, RNG, the
renderer's instance data and cameras) is compared with a snapshot taken before it.
Failures of the environment itself (a shader that does not compile, no GL driver) must
raise with the GL log, never return black frames.

Scene / renderer bad input is covered by test_renderer_errors.py, the backend by
test_backend.py; this file extends them to the environment layer.
"""
from __future__ import annotations

import functools
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from marl_render import backend
from marl_render.envs import env_class, list_envs, make_env

W = 2  # worlds of the batched envs here
RES = 16
ENVS = list_envs()
GL_LIMIT = backend.gl_info().max_framebuffer_size


# ---------------------------------------------------------------------- helpers
def snapshot(env) -> dict:
    """Everything a rejected call must leave alone: env state + RNG + renderer data."""
    state = {f"env/{k}": v for k, v in env.get_state().items()}
    renderer = env.renderer
    for group in renderer.scene.groups:
        state.update({f"renderer/{group}/{k}": v for k, v in renderer.instance_state(group).items()})
    for key in ("camera_position", "camera_rotation", "fov_y", "near", "far", "world_origin"):
        state[f"renderer/{key}"] = getattr(renderer, key).clone()
    state["needs_reset"] = torch.tensor(env.needs_reset)
    return state


def assert_unchanged(before: dict, after: dict, what: str = ""):
    assert before.keys() == after.keys()
    changed = [k for k in before if not torch.equal(before[k], after[k])]
    assert not changed, f"rejected call {what} changed {changed}"


def expect_error(call, error, message, label):
    """call() must raise `error` matching `message`; the failure names the case."""
    try:
        call()
    except error as exc:
        import re

        assert re.search(message, str(exc)), f"{label}: message {str(exc)!r} does not match {message!r}"
        return exc
    except Exception as exc:  # noqa: BLE001 - report the wrong type with the case label
        raise AssertionError(f"{label}: expected {error}, got {type(exc).__name__}: {exc}") from exc
    raise AssertionError(f"{label}: expected {error}, nothing was raised")


def windows() -> int:
    return backend.context().engine.get_num_windows()


# ---------------------------------------------------------------------- constructor keywords
def _common_cases(name):
    low, high = env_class(name).agent_range
    cases = [
        ("num_worlds=0", dict(num_worlds=0), ValueError, r"num_worlds must be an int >= 1, got 0"),
        ("num_worlds=-3", dict(num_worlds=-3), ValueError, r"num_worlds must be an int >= 1, got -3"),
        ("num_worlds=2.5", dict(num_worlds=2.5), TypeError, r"num_worlds must be an int >= 1, got 2\.5"),
        ("num_worlds='4'", dict(num_worlds="4"), TypeError, r"num_worlds must be an int >= 1, got '4'"),
        ("num_worlds=True", dict(num_worlds=True), TypeError, r"num_worlds must be an int >= 1, got True"),
        ("resolution=0", dict(resolution=0), ValueError, r"resolution must be >= 1 pixel on each side, got \(0, 0\)"),
        ("resolution=(0,32)", dict(resolution=(0, 32)), ValueError, r"resolution must be >= 1 .*got \(0, 32\)"),
        ("resolution=-5", dict(resolution=-5), ValueError, r"resolution must be >= 1 .*got \(-5, -5\)"),
        ("resolution=(16,)", dict(resolution=(16,)), TypeError, r"resolution must be an int or a pair of ints"),
        ("resolution=(16.,16)", dict(resolution=(16.0, 16)), TypeError, r"resolution must be an int or a pair"),
        ("resolution='64'", dict(resolution="64"), TypeError, r"resolution must be an int or a pair.*'64'"),
        ("resolution=(16,20000)", dict(resolution=(16, 20000)), ValueError,
         rf"resolution must be at most {GL_LIMIT} pixels per side.*\(16, 20000\)"),
        ("resolution=(limit+1,8)", dict(resolution=(GL_LIMIT + 1, 8)), ValueError,
         rf"resolution must be at most {GL_LIMIT} pixels per side.*\({GL_LIMIT + 1}, 8\)"),
        ("resolution=10**9", dict(resolution=10 ** 9), ValueError, rf"resolution must be at most {GL_LIMIT}"),
        ("num_agents=high+1", dict(num_agents=high + 1), ValueError,
         rf"num_agents must be an int in \[{low}, {high}\] for {name}, got {high + 1}"),
        ("num_agents=low-1", dict(num_agents=low - 1), ValueError,
         rf"num_agents must be an int in \[{low}, {high}\] for {name}, got {low - 1}"),
        ("num_agents=2.0", dict(num_agents=2.0), TypeError, rf"num_agents must be an int in \[{low}, {high}\]"),
        ("num_agents='3'", dict(num_agents="3"), TypeError, r"num_agents must be an int.*got '3'"),
        ("unknown kwarg", dict(bogus=1), TypeError, rf"make_env\('{name}'\) got unknown keyword argument\(s\) "
                                                   r"\['bogus'\]; accepted: \[.*'num_worlds'"),
        ("typo kwarg", dict(num_world=2), TypeError, r"unknown keyword argument\(s\) \['num_world'\]"),
        ("seed=-1", dict(seed=-1), ValueError, r"seed must be None or an int in \[0, 2\*\*63\), got -1"),
        ("seed=2**63", dict(seed=2 ** 63), ValueError, r"seed must be None or an int in \[0, 2\*\*63\)"),
        ("seed=1.5", dict(seed=1.5), TypeError, r"seed must be None or an int.*got 1\.5"),
        ("seed='0'", dict(seed="0"), TypeError, r"seed must be None or an int.*got '0'"),
        ("seed=True", dict(seed=True), TypeError, r"seed must be None or an int.*got True"),
        ("max_steps=0", dict(max_steps=0), ValueError, r"max_steps must be an int >= 1, got 0"),
        ("max_steps=-1", dict(max_steps=-1), ValueError, r"max_steps must be an int >= 1, got -1"),
        ("max_steps=1.5", dict(max_steps=1.5), TypeError, r"max_steps must be an int >= 1, got 1\.5"),
        # Accepted before, then every step raised OverflowError after advancing the state.
        ("max_steps=2**70", dict(max_steps=2 ** 70), ValueError, r"max_steps must be an int in \[1, 2\*\*63\)"),
        ("device='cuda:7'", dict(device="cuda:7"), ValueError, r"device 'cuda:7' was asked for but torch sees"),
        ("device='meta'", dict(device="meta"), ValueError, r"device must be a CPU or CUDA device.*'meta'"),
        ("device='mps'", dict(device="mps"), ValueError, r"device must be a CPU or CUDA device.*'mps'"),
        ("device='gpu0'", dict(device="gpu0"), ValueError, r"device must name a torch device.*'gpu0'"),
        ("device=0", dict(device=0), TypeError, r"device must be a str or torch\.device.*got 0"),
        ("continuous=1", dict(continuous=1), TypeError, r"continuous must be a bool, got 1"),
        ("state_obs='yes'", dict(state_obs="yes"), TypeError, r"state_obs must be a bool, got 'yes'"),
        ("depth=None", dict(depth=None), TypeError, r"depth must be a bool, got None"),
        ("autoreset=0", dict(autoreset=0), TypeError, r"autoreset must be False, True .*'next_step'.*got 0"),
        ("autoreset='next'", dict(autoreset="next"), ValueError, r"autoreset must be .*'same_step'.*got 'next'"),
        ("torch_threads=0", dict(torch_threads=0), ValueError,
         r"torch_threads must be None or an int in \[1, 1024\], got 0"),
        ("torch_threads=1.5", dict(torch_threads=1.5), TypeError,
         r"torch_threads must be None or an int in \[1, 1024\]"),
    ]
    return [(name, *case) for case in cases]


OWN_CASES = {
    "spread": [
        ("num_landmarks=0", dict(num_landmarks=0), ValueError, r"num_landmarks must be an int >= 1, got 0"),
        ("num_landmarks=13", dict(num_landmarks=13), ValueError, r"num_landmarks must be an int in \[1, 12\], got 13"),
        ("collision_penalty=-1", dict(collision_penalty=-1.0), ValueError, r"collision_penalty must be a finite"),
        ("collision_penalty=nan", dict(collision_penalty=float("nan")), ValueError, r"collision_penalty .*nan"),
    ],
    "tag": [
        ("num_predators=0", dict(num_predators=0), ValueError, r"num_predators must be an int >= 1, got 0"),
        ("num_obstacles=9", dict(num_obstacles=9), ValueError, r"num_obstacles must be an int in \[0, 8\], got 9"),
        ("catch_reward=nan", dict(catch_reward=float("nan")), ValueError, r"catch_reward must be a finite"),
        ("shaping=-1", dict(shaping=-1.0), ValueError, r"shaping must be a finite number >= 0, got -1"),
    ],
    "forage": [
        ("num_items=33", dict(num_items=33), ValueError, r"num_items must be an int in \[1, 32\], got 33"),
        ("respawn_delay=0", dict(respawn_delay=0), ValueError,
         r"respawn_delay must be an int in \[1, 1000000000\], got 0"),
        ("item_reward=inf", dict(item_reward=float("inf")), ValueError, r"item_reward must be a finite"),
    ],
    "push": [
        ("num_agents=3 (odd)", dict(num_agents=3), ValueError, r"num_agents must be even for push.*got 3"),
        ("goal_reward=nan", dict(goal_reward=float("nan")), ValueError, r"goal_reward must be a finite"),
        ("shaping=-0.5", dict(shaping=-0.5), ValueError, r"shaping must be a finite number >= 0"),
    ],
}

KWARG_CASES = [case for name in ENVS for case in _common_cases(name) + [(name, *c) for c in OWN_CASES.get(name, [])]]


@pytest.mark.parametrize("name,label,kwargs,error,message", KWARG_CASES,
                         ids=[f"{c[0]}-{c[1]}" for c in KWARG_CASES])
def test_make_env_rejects_bad_keywords(name, label, kwargs, error, message, framebuffers_made):
    arguments = dict(num_worlds=W, resolution=RES, seed=0)
    arguments.update(kwargs)
    open_before = windows()
    with pytest.raises(error, match=message):
        make_env(name, **arguments)
    # Fails fast (no framebuffer is allocated, e.g. for a resolution beyond the GL limit) and
    # leaves no GL framebuffer behind.
    assert framebuffers_made == []
    assert windows() == open_before


def test_framebuffers_made_sees_the_framebuffers_of_an_env_that_is_made(framebuffers_made):
    env = make_env("spread", num_worlds=W, resolution=RES, shadows=True)
    env.close()
    assert sorted(framebuffers_made) == [f"pass of {W * 3} views", "shadow atlas"]  # spread: 3 agents a world


@pytest.mark.parametrize("name", ENVS)
def test_absurd_num_worlds_is_a_clear_error(name):
    with pytest.raises(ValueError, match="num_worlds"):
        make_env(name, num_worlds=2 ** 40, resolution=8)


def test_resolution_beyond_the_gl_limit_allocates_nothing():
    from marl_render.bench.soak import rss_mb

    before = rss_mb()
    for shape in ((16, 20000), (GL_LIMIT + 1, GL_LIMIT + 1), (10 ** 6, 10 ** 6)):
        with pytest.raises(ValueError, match=rf"at most {GL_LIMIT} pixels per side"):
            make_env("spread", num_worlds=64, resolution=shape)
    assert rss_mb() - before < 50


WRAPPER_CASES = [
    ("parallel", dict(num_worlds=2), TypeError, r"make_parallel_env\(\) does not accept 'num_worlds'"),
    ("parallel", dict(autoreset=True), TypeError, r"does not accept 'autoreset'"),
    ("parallel", dict(render_mode="ansi"), ValueError, r"render_mode must be None or one of \['human', 'rgb_array'\]"),
    ("parallel", dict(departed_actions="drop"), ValueError, r"departed_actions must be one of \['raise', 'ignore'\]"),
    ("parallel", dict(action_mask=1), TypeError, r"action_mask must be a bool, got 1"),
    ("parallel", dict(resolution=0), ValueError, r"resolution must be >= 1 pixel"),
    ("parallel", dict(resolution=(16, 20000)), ValueError, rf"at most {GL_LIMIT} pixels per side"),
    ("parallel", dict(seed=-1), ValueError, r"seed must be None or an int"),
    ("parallel", dict(bogus=1), TypeError, r"unknown keyword argument\(s\) \['bogus'\]"),
    ("torchrl", dict(num_worlds=0), ValueError, r"num_worlds must be an int >= 1, got 0"),
    ("torchrl", dict(autoreset=True), TypeError, r"does not accept 'autoreset'"),
    ("torchrl", dict(group_map="teams"), ValueError, r"group_map must be one of \['team', 'one_group', 'per_agent'\]"),
    ("torchrl", dict(group_map={"a": ["agent_0"]}), ValueError, r"group_map must place every agent in a group"),
    ("torchrl", dict(resolution=(16, 20000)), ValueError, rf"at most {GL_LIMIT} pixels per side"),
    ("torchrl", dict(device="cuda:7"), ValueError, r"device 'cuda:7'"),
    ("torchrl", dict(max_steps=0), ValueError, r"max_steps must be an int >= 1, got 0"),
    ("torchrl", dict(bogus=1), TypeError, r"unknown keyword argument\(s\) \['bogus'\]"),
]


@pytest.mark.parametrize("front,kwargs,error,message", WRAPPER_CASES,
                         ids=[f"{c[0]}-{'-'.join(map(str, c[1].items()))}" for c in WRAPPER_CASES])
def test_front_ends_reject_bad_keywords_and_leak_nothing(front, kwargs, error, message):
    from marl_render.envs import make_parallel_env, make_torchrl_env

    open_before = windows()
    with pytest.raises(error, match=message):
        if front == "parallel":
            make_parallel_env("spread", resolution=kwargs.pop("resolution", RES), **kwargs)
        else:
            make_torchrl_env("spread", **{"num_worlds": W, "resolution": RES, **kwargs})
    assert windows() == open_before, "a rejected construction left a GL framebuffer open"


# ---------------------------------------------------------------------- BatchedEnv.step
def _discrete_cases(A, n):
    big = torch.zeros(W, A, dtype=torch.long)
    big[-1, -1] = n + 3
    want = rf"actions must be an integer tensor of shape \[{W}, {A}\] \(worlds, agents\) with values in \[0, {n}\)"
    return [
        ("extra agent", torch.zeros(W, A + 1, dtype=torch.long), ValueError, rf"{want}, got shape \[{W}, {A + 1}\]"),
        ("no agent dim", torch.zeros(W, dtype=torch.long), ValueError, rf"{want}, got shape \[{W}\]"),
        ("trailing dim", torch.zeros(W, A, 1, dtype=torch.long), ValueError, rf"{want}, got shape \[{W}, {A}, 1\]"),
        ("scalar", torch.tensor(0), ValueError, rf"{want}, got shape \[\]"),
        ("empty list", [], TypeError, rf"{want}, got \[\]"),
        ("float tensor", torch.zeros(W, A), TypeError,
         rf"{want}, got tensor of shape \({W}, {A}\), dtype torch.float32"),
        ("bool tensor", torch.zeros(W, A, dtype=torch.bool), TypeError, rf"{want}, got tensor .*dtype torch.bool"),
        ("complex tensor", torch.zeros(W, A, dtype=torch.complex64), TypeError, rf"{want}, got .*complex64"),
        ("float numpy", np.zeros((W, A), np.float32), TypeError, rf"{want}, got array of shape .*float32"),
        ("too big", torch.full((W, A), n), ValueError, rf"{want}, got values in \[{n}, {n}\]"),
        ("negative", torch.full((W, A), -1), ValueError, rf"{want}, got values in \[-1, -1\]"),
        ("one bad entry", big, ValueError, rf"{want}, got values in \[0, {n + 3}\]"),
        ("huge", torch.full((W, A), 2 ** 62), ValueError, rf"{want}, got values in \[{2 ** 62}, {2 ** 62}\]"),
        # torch has no comparison kernels for uint16/32/64: these raised NotImplementedError.
        ("uint16 too big", torch.full((W, A), 60000, dtype=torch.uint16), ValueError, rf"{want}, got values"),
        ("uint64 huge", np.full((W, A), 2 ** 64 - 1, np.uint64), ValueError, rf"{want}, got values"),
        ("string", "left", TypeError, r"actions must be a torch\.Tensor \(or array-like\), got 'left'"),
        ("None", None, TypeError, r"actions must be a torch\.Tensor \(or array-like\), got None"),
        ("dict", {"agent_0": 0}, TypeError, r"actions must be a torch\.Tensor \(or array-like\), got \{"),
        ("ragged list", [[0] * A, [0] * (A + 1)], TypeError, rf"{want}, got \[\["),
        ("list of str", [["a"] * A] * W, TypeError, rf"{want}, got \[\['a'"),
        ("python int 2**70", [[2 ** 70] * A] * W, TypeError, rf"{want}, got \[\[{2 ** 70}"),
        # These raised NotImplementedError / RuntimeError from torch before.
        ("meta tensor", torch.zeros(W, A, dtype=torch.long, device="meta"), TypeError,
         r"actions must be a dense tensor with data, got layout torch.strided on meta"),
        ("sparse tensor", torch.zeros(W, A, dtype=torch.long).to_sparse(), TypeError,
         r"actions must be a dense tensor with data, got layout torch.sparse_coo"),
    ]


def _continuous_cases(A, d):
    one_nan = torch.zeros(W, A, d)
    one_nan[0, -1, -1] = float("nan")
    want = (rf"actions must be a float tensor of shape \[{W}, {A}, {d}\] \(worlds, agents, action_dim\) "
            rf"in \[-1, 1\]")
    return [
        ("no action dim", torch.zeros(W, A), ValueError, rf"{want}, got shape \[{W}, {A}\]"),
        ("wide", torch.zeros(W, A, d + 1), ValueError, rf"{want}, got shape \[{W}, {A}, {d + 1}\]"),
        ("int tensor", torch.zeros(W, A, d, dtype=torch.long), TypeError, rf"{want}, got tensor .*torch.int64"),
        ("bool tensor", torch.zeros(W, A, d, dtype=torch.bool), TypeError, rf"{want}, got tensor .*torch.bool"),
        ("complex tensor", torch.zeros(W, A, d, dtype=torch.complex64), TypeError, rf"{want}, got .*complex64"),
        ("int numpy", np.zeros((W, A, d), np.int32), TypeError, rf"{want}, got array .*int32"),
        ("nan", torch.full((W, A, d), float("nan")), ValueError, rf"{want}, got non-finite values \(NaN/Inf\)"),
        ("one nan", one_nan, ValueError, rf"{want}, got non-finite values"),
        ("+inf", torch.full((W, A, d), float("inf")), ValueError, rf"{want}, got non-finite values"),
        ("-inf numpy", np.full((W, A, d), -np.inf, np.float32), ValueError, rf"{want}, got non-finite values"),
        ("1.5", torch.full((W, A, d), 1.5), ValueError, rf"{want}, got values in \[1\.5, 1\.5\] \(clamp them first\)"),
        ("-1.001", torch.full((W, A, d), -1.001), ValueError, rf"{want}, got values in \[-1\.001, -1\.001\]"),
        ("float64 1e300", torch.full((W, A, d), 1e300, dtype=torch.float64), ValueError, rf"{want}, got values in"),
        # float8 has no isfinite / comparison kernels: this raised NotImplementedError before.
        ("float8 2.0", torch.full((W, A, d), 2.0).to(torch.float8_e4m3fn), ValueError, rf"{want}, got values in \[2,"),
        ("string", "up", TypeError, r"actions must be a torch\.Tensor \(or array-like\), got 'up'"),
        ("None", None, TypeError, r"actions must be a torch\.Tensor \(or array-like\), got None"),
        ("ragged list", [[[0.0] * d] * A, [[0.0] * (d + 1)] * A], TypeError, r"actions must be array-like of numbers"),
        ("list wrong shape", [[0.0] * A] * W, ValueError, rf"{want}, got shape \[{W}, {A}\]"),
        ("meta tensor", torch.zeros(W, A, d, device="meta"), TypeError, r"actions must be a dense tensor with data"),
        ("sparse tensor", torch.zeros(W, A, d).to_sparse(), TypeError, r"actions must be a dense tensor with data"),
    ]


VARIANTS = [(name, continuous) for name in ENVS for continuous in (False, True)]


@pytest.fixture(scope="module", params=VARIANTS, ids=[f"{n}-{'continuous' if c else 'discrete'}" for n, c in VARIANTS])
def stepped_env(request):
    name, continuous = request.param
    env = make_env(name, num_worlds=W, resolution=RES, seed=0, continuous=continuous, state_obs=True)
    env.reset()
    env.step(env.random_actions(torch.Generator().manual_seed(1)))
    yield env
    env.close()


def _step_cases(env):
    if env.continuous:
        return _continuous_cases(env.num_agents, env.action_dim)
    return _discrete_cases(env.num_agents, env.num_actions)


def test_step_rejects_bad_actions_and_changes_nothing(stepped_env):
    env = stepped_env
    twin = make_env(env.name, num_worlds=W, resolution=RES, seed=0, continuous=env.continuous, state_obs=True)
    twin.reset()
    g = torch.Generator().manual_seed(1)
    twin.step(twin.random_actions(g))
    cases = _step_cases(env)
    for label, actions, error, message in cases:
        before = snapshot(env)
        expect_error(functools.partial(env.step, actions), error, message, f"step({label})")
        assert_unchanged(before, snapshot(env), f"step({label})")
    # ... and the env goes on exactly like one that never saw the bad calls.
    actions = env.random_actions(g)
    out, out_twin = env.step(actions), twin.step(actions)
    for key in out[0]:
        assert torch.equal(out[0][key], out_twin[0][key]), key
    for a, b in zip(out[1:4], out_twin[1:4], strict=True):
        assert torch.equal(a, b)
    twin.close()


@pytest.mark.parametrize("name", ENVS)
def test_unusual_but_valid_action_containers_step_like_int64(name):
    """uint8/uint16/int32 tensors, numpy arrays and nested lists of in-range actions are the same
    actions as the int64 tensor (the uint16 path used to raise NotImplementedError)."""
    reference = make_env(name, num_worlds=W, resolution=RES, seed=3)
    reference.reset()
    actions = reference.random_actions(torch.Generator().manual_seed(0))
    expected = reference.step(actions)
    reference.close()
    forms = [actions.to(torch.uint8), actions.to(torch.uint16), actions.to(torch.int32),
             actions.numpy().astype(np.uint32), actions.tolist(), tuple(map(tuple, actions.tolist()))]
    for form in forms:
        env = make_env(name, num_worlds=W, resolution=RES, seed=3)
        env.reset()
        got = env.step(form)
        assert torch.equal(got[0]["pixels"], expected[0]["pixels"]) and torch.equal(got[1], expected[1]), type(form)
        env.close()


def test_list_of_grad_tensors_steps_like_its_detached_copy():
    """Was a raw RuntimeError from numpy; actions are now detached where they enter."""
    envs = [make_env("spread", num_worlds=W, resolution=RES, seed=0, continuous=True) for _ in range(2)]
    try:
        for env in envs:
            env.reset()
        rows = [torch.full((envs[0].num_agents, 2), 0.25 * (w + 1), requires_grad=True) for w in range(W)]
        assert not envs[0].check_actions(rows).requires_grad
        out = envs[0].step(rows)
        expected = envs[1].step(torch.stack([row.detach() for row in rows]))
        assert torch.equal(out[0]["pixels"], expected[0]["pixels"]) and torch.equal(out[1], expected[1])
        assert not out[1].requires_grad
    finally:
        for env in envs:
            env.close()


# ---------------------------------------------------------------------- reset, reset_worlds, render_overview
@pytest.mark.parametrize("name", ENVS)
def test_reset_arguments_are_checked_before_anything_changes(name):
    env = make_env(name, num_worlds=W, resolution=RES, seed=0, state_obs=True)
    env.reset()
    env.step(env.random_actions(torch.Generator().manual_seed(0)))
    cases = [
        (lambda: env.reset(seed=-1), ValueError, r"seed must be None or an int in \[0, 2\*\*63\), got -1"),
        (lambda: env.reset(seed="7"), TypeError, r"seed must be None or an int.*got '7'"),
        (lambda: env.reset(seed=2.0), TypeError, r"seed must be None or an int.*got 2\.0"),
        (lambda: env.reset_worlds(torch.ones(W + 1, dtype=torch.bool)), ValueError,
         rf"mask must be a bool tensor of shape \[{W}\] \(num_worlds\), got shape \[{W + 1}\]"),
        (lambda: env.reset_worlds(torch.ones(W)), TypeError, r"mask must have dtype torch\.bool, got torch\.float32"),
        (lambda: env.reset_worlds([1, 0]), TypeError, r"mask must have dtype torch\.bool, got torch\.int64"),
        (lambda: env.reset_worlds(None), TypeError, r"mask must be a torch\.Tensor or array-like, got NoneType"),
        (lambda: env.reset_worlds(torch.ones(W, 1, dtype=torch.bool)), ValueError, r"mask must be a bool tensor"),
        (lambda: env.reset_worlds(torch.ones(W, dtype=torch.bool), seed=-5), ValueError, r"seed must be None"),
        (lambda: env.render_overview(resolution=0), ValueError, r"resolution must be >= 1 pixel on each side"),
        (lambda: env.render_overview(resolution=(8, GL_LIMIT + 1)), ValueError,
         rf"resolution must be at most {GL_LIMIT} pixels per side"),
        (lambda: env.render_overview(resolution="big"), TypeError, r"resolution must be an int or a pair of ints"),
    ]
    for call, error, message in cases:
        before = snapshot(env)
        expect_error(call, error, message, message)
        assert_unchanged(before, snapshot(env), message)
    env.close()


# ---------------------------------------------------------------------- PettingZoo step
def _pz_cases(env):
    agents = list(env.agents)
    first, core = agents[0], env.core
    good = {a: env.action_space(a).sample() for a in agents}
    who = rf"actions\['{first}'\]"
    cases = [
        ("unknown agent", {**good, "ghost": 0}, KeyError, r"actions has an action for unknown agent 'ghost'"),
        ("int agent key", {**good, 0: 0}, KeyError, r"actions has an action for unknown agent 0"),
        ("missing agent", {a: v for a, v in good.items() if a != first}, KeyError,
         rf"actions is missing an action for agent\(s\) \['{first}'\]"),
        ("not a dict", list(good.values()), TypeError, r"actions must be a dict \{agent: action\}"),
        ("None", None, TypeError, r"actions must be a dict"),
    ]
    if core.continuous:
        d = core.action_dim
        want = rf"{who} must be a float array of shape \({d},\) in \[-1, 1\]"
        per_agent = [
            ("nan", np.full(d, np.nan, np.float32), ValueError, rf"{want}.*got non-finite values"),
            ("inf", np.full(d, np.inf), ValueError, rf"{want}.*got non-finite values"),
            ("out of range", np.full(d, 1.5, np.float32), ValueError, rf"{want}.*clip them first"),
            ("wrong shape", np.zeros(d + 1, np.float32), ValueError, rf"{want}.*got shape \({d + 1},\)"),
            ("string", "x", TypeError, rf"{want}.*got 'x'"),
            ("None", None, TypeError, rf"{want}.*got None"),
            ("bool array", np.ones(d, bool), TypeError, rf"{want}"),
            ("dict", {}, TypeError, rf"{want}"),
        ]
    else:
        n = core.num_actions
        want = rf"{who} must be an int in \[0, {n}\) \(Discrete\({n}\)\)"
        per_agent = [
            ("too big", n, ValueError, rf"{want}, got {n}"),
            ("negative", -1, ValueError, rf"{want}, got -1"),
            ("huge", 2 ** 70, ValueError, rf"{want}, got {2 ** 70}"),
            ("nan", float("nan"), TypeError, rf"{want}, got nan"),
            ("float", 1.5, TypeError, rf"{want}, got 1\.5"),
            ("string", "1", TypeError, rf"{want}, got '1'"),
            ("None", None, TypeError, rf"{want}, got None"),
            ("bool", True, TypeError, rf"{want}, got True"),
            ("vector", np.array([1, 2]), TypeError, rf"{want}, got array of shape \(2,\)"),
        ]
    cases += [(label, {**good, first: value}, error, message) for label, value, error, message in per_agent]
    return cases


@pytest.mark.parametrize("name,continuous", VARIANTS,
                         ids=[f"{n}-{'continuous' if c else 'discrete'}" for n, c in VARIANTS])
def test_pettingzoo_step_rejects_bad_actions_and_changes_nothing(name, continuous):
    from marl_render.envs import make_parallel_env

    env = make_parallel_env(name, resolution=RES, seed=0, continuous=continuous)
    env.reset(seed=0)
    for label, actions, error, message in _pz_cases(env):
        before, agents = snapshot(env.core), list(env.agents)
        expect_error(functools.partial(env.step, actions), error, message, f"pettingzoo step({label})")
        assert_unchanged(before, snapshot(env.core), f"pettingzoo step({label})")
        assert env.agents == agents
    env.step({a: env.action_space(a).sample() for a in env.agents})  # still usable
    env.close()


def test_pettingzoo_meta_tensor_action_is_a_clear_error():
    from marl_render.envs import make_parallel_env

    env = make_parallel_env("spread", resolution=RES, num_agents=1)
    env.reset(seed=0)
    try:
        with pytest.raises(TypeError, match=r"actions\['agent_0'\]"):
            env.step({"agent_0": torch.zeros((), dtype=torch.long, device="meta")})
    finally:
        env.close()


# ---------------------------------------------------------------------- TorchRL step
TORCHRL_VARIANTS = [(name, continuous, group_map) for name in ENVS for continuous in (False, True)
                    for group_map in ("team", "one_group")]


@pytest.mark.parametrize("name,continuous,group_map", TORCHRL_VARIANTS,
                         ids=[f"{n}-{'continuous' if c else 'discrete'}-{g}" for n, c, g in TORCHRL_VARIANTS])
def test_torchrl_step_rejects_bad_action_tensors_and_changes_nothing(name, continuous, group_map):
    from marl_render.envs import make_torchrl_env

    env = make_torchrl_env(name, num_worlds=W, resolution=RES, seed=0, continuous=continuous, group_map=group_map)
    td = env.reset()
    group, names = next(iter(env.group_map.items()))
    N, core = len(names), env.core
    if continuous:
        d = core.action_dim
        bad = [
            ("nan", torch.full((W, N, d), float("nan")), r"non-finite"),
            ("out of range", torch.full((W, N, d), 1.5), r"\[-1, 1\]"),
            ("int dtype", torch.zeros(W, N, d, dtype=torch.long), r"float tensor"),
            ("bool dtype", torch.zeros(W, N, d, dtype=torch.bool), r"float tensor"),
            ("wide", torch.zeros(W, N, d + 1), r"shape"),
        ]
    else:
        n = core.num_actions
        bad = [
            ("too big", torch.full((W, N), n), rf"values in \[0, {n}\)"),
            ("negative", torch.full((W, N), -1), r"got values in \[-1"),
            ("float dtype", torch.zeros(W, N), r"integer tensor"),
            ("bool dtype", torch.zeros(W, N, dtype=torch.bool), r"integer tensor"),
            ("trailing dim", torch.zeros(W, N, 2, dtype=torch.long), r"shape"),
        ]
    for label, action, message in bad:
        step_td = env.rand_action(td.clone())
        step_td.set((group, "action"), action)
        before = snapshot(core)
        expect_error(functools.partial(env.step, step_td), (ValueError, TypeError), message, f"torchrl step({label})")
        assert_unchanged(before, snapshot(core), f"torchrl step({label})")
    env.rollout(2, break_when_any_done=False)  # still usable
    env.close()


def test_torchrl_missing_group_action_is_a_clear_error():
    from marl_render.envs import make_torchrl_env

    env = make_torchrl_env("tag", num_worlds=W, resolution=RES, seed=0, group_map="team")
    try:
        td = env.rand_action(env.reset())
        del td["prey", "action"]
        with pytest.raises((KeyError, ValueError), match=r"prey.*action"):
            env.step(td)
    finally:
        env.close()


@pytest.mark.parametrize("continuous,dtype", [(False, torch.int32), (True, torch.float64)])
def test_torchrl_group_actions_of_another_dtype(continuous, dtype):
    """int32 (discrete) or float64 (continuous) group actions step exactly like the same
    actions in the spec's dtype (int64 / float32) on a twin env."""
    from marl_render.envs import make_torchrl_env

    envs = [make_torchrl_env("tag", num_worlds=W, resolution=RES, seed=0, continuous=continuous, group_map="team")
            for _ in range(2)]
    try:
        td = envs[0].rand_action(envs[0].reset())
        envs[1].reset()
        other = td.clone()
        other.set(("predator", "action"), td.get(("predator", "action")).to(dtype))
        expected = envs[0].step(td)["next"]
        got = envs[1].step(other)["next"]
        assert set(got.keys(True, True)) == set(expected.keys(True, True))
        for key in expected.keys(True, True):
            assert torch.equal(got.get(key), expected.get(key)), key
    finally:
        for env in envs:
            env.close()


# ---------------------------------------------------------------------- renderer: tensors torch cannot check
def test_renderer_rejects_exotic_tensors_and_changes_nothing():
    """Extends test_renderer_errors.py: dtypes without comparison kernels (uint16/32/64, float8) and
    sparse tensors raised NotImplementedError from torch before; now a clear error (or they work)."""
    import marl_render as mr

    C = 3
    scene = mr.Scene(num_worlds=W, agents_per_world=2, resolution=8)
    scene.add_group("boxes", "box", capacity=C)
    with mr.BatchRenderer(scene) as renderer:
        renderer.render()
        state = lambda: {**renderer.instance_state("boxes"), "fov_y": renderer.fov_y.clone()}  # noqa: E731
        cases = [
            (dict(owner=torch.full((W, C), 7, dtype=torch.uint16)), ValueError, r"owner must be <= 1, got maximum 7"),
            (dict(owner=np.full((W, C), 2 ** 64 - 1, np.uint64)), ValueError, r"owner must be <= 1"),
            (dict(position=torch.full((W, C, 3), float("nan")).to(torch.float8_e5m2)), ValueError,
             r"position must be finite"),
            (dict(position=torch.zeros(W, C, 3).to_sparse()), TypeError,
             r"position must be a dense \(strided\) tensor, got layout torch.sparse_coo"),
            (dict(active=torch.ones(W, C, dtype=torch.bool).to_sparse()), TypeError, r"active must be a dense"),
            (dict(owner=torch.zeros(W, C, dtype=torch.long).to_sparse()), TypeError, r"owner must be a dense"),
        ]
        for kwargs, error, message in cases:
            before = state()
            expect_error(functools.partial(renderer.update, "boxes", **kwargs), error, message, str(list(kwargs)))
            assert_unchanged(before, state(), str(list(kwargs)))
        before = state()
        expect_error(lambda: renderer.set_cameras(fov_y=torch.ones(W, 2).to_sparse()), TypeError,
                     r"fov_y must be a dense", "fov_y sparse")
        assert_unchanged(before, state(), "fov_y sparse")
        # The same values in those dtypes are accepted and stored like their plain counterparts.
        renderer.update("boxes", owner=torch.ones(W, C, dtype=torch.uint16),
                        position=torch.full((W, C, 3), 0.5).to(torch.float8_e4m3fn))
        stored = renderer.instance_state("boxes")
        assert stored["owner"].dtype == torch.int64 and bool((stored["owner"] == 1).all())
        assert bool((stored["position"] == 0.5).all())
        renderer.render()


# ---------------------------------------------------------------------- failures of the environment itself
def _broken_shader():
    from panda3d.core import Shader

    return Shader.make(Shader.SL_GLSL, "#version 410\nvoid main() { gl_Position = vec4(0.0); }",
                       "#version 410\nout vec4 c;\nvoid main() { c = undefined_colour; }")


@pytest.mark.parametrize("front", ["core", "pettingzoo", "torchrl"])
def test_a_shader_failing_during_step_raises_with_the_gl_log(front):
    """The env path must not swallow the renderer's ShaderCompileError (no black frames)."""
    from marl_render.envs import make_parallel_env, make_torchrl_env

    if front == "core":
        env = make_env("spread", num_worlds=W, resolution=RES, seed=0)
        core, step = env, lambda: env.step(torch.zeros(W, env.num_agents, dtype=torch.long))
        env.reset()
    elif front == "pettingzoo":
        env = make_parallel_env("spread", resolution=RES, seed=0)
        core = env.core
        env.reset(seed=0)
        step = lambda: env.step({a: 0 for a in env.agents})  # noqa: E731
    else:
        env = make_torchrl_env("spread", num_worlds=W, resolution=RES, seed=0)
        core = env.core
        td = env.reset()
        step = lambda: env.step(env.rand_action(td.clone()))  # noqa: E731
    core.renderer._groups["agents"].node.set_shader(_broken_shader())
    for _ in range(2):  # every call raises, not only the first
        with pytest.raises(backend.ShaderCompileError, match=r"(?s)group\(s\) \['agents'\] failed.*undefined_colour"):
            step()
    env.close()


def test_a_failing_overview_shader_raises_too():
    env = make_env("spread", num_worlds=W, resolution=RES, seed=0)
    env.reset()
    env.render_overview()
    env.views.overview_renderer._groups["landmarks"].node.set_shader(_broken_shader())
    with pytest.raises(backend.ShaderCompileError, match="landmarks"):
        env.render_overview()
    env.close()


def test_no_gl_driver_is_one_clear_error_from_make_env():
    script = ("from marl_render.envs import make_env\n"
              "make_env('spread', num_worlds=1, resolution=8)\n")
    env = dict(os.environ, __EGL_VENDOR_LIBRARY_FILENAMES="/nonexistent/vendor.json")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode != 0
    assert "GLUnavailableError" in out.stderr and "no EGL display could be initialised" in out.stderr
    assert "apt-get install libegl1" in out.stderr
