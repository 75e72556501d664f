"""Fuzzing the step functions (and the renderer's updates) with random malformed input.

For every input the contract is: either a clean call, or a ValueError / TypeError that
leaves the state exactly as it was. Any other exception type, a crash, or a change of
state on error fails. Inputs: numpy arrays and torch tensors of random dtypes (ints,
unsigned ints, floats incl. float16 / bfloat16 / float8, bool, complex), shapes (the right
one, near misses, random) and values (NaN, +-inf, huge ints, in-range values), sparse and
meta tensors, nested lists and random Python objects. PettingZoo's step may also raise
KeyError for missing / unknown agent keys (its documented convention).

Examples are bounded (deterministic: derandomize=True, no example database), deadline=None.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import marl_render as mr
from marl_render.envs import make_env, make_parallel_env, make_torchrl_env

W = 2
RES = 16
SETTINGS = dict(deadline=None, database=None, derandomize=True, print_blob=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.filter_too_much, HealthCheck.large_base_example])

NUMPY_DTYPES = [np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32, np.uint64,
                np.float16, np.float32, np.float64, np.bool_, np.complex64]
TORCH_ONLY_FLOATS = [torch.bfloat16, torch.float8_e4m3fn, torch.float8_e5m2]


# ---------------------------------------------------------------------- strategies
def near_shapes(correct: tuple) -> st.SearchStrategy:
    """The right shape, shapes one edit away from it, and random small shapes."""
    edits = [correct, correct[:-1], correct + (1,), correct + (2,), correct[1:], tuple(reversed(correct))]
    for i in range(len(correct)):
        edits += [correct[:i] + (correct[i] + 1,) + correct[i + 1:],
                  correct[:i] + (max(correct[i] - 1, 0),) + correct[i + 1:]]
    right = st.just(correct)  # most draws keep the right shape so that dtypes and values get tested
    return st.one_of(right, right, right, st.sampled_from(edits),
                     hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=4))


def elements(dtype, low: float, high: float) -> st.SearchStrategy:
    """Values of a numpy dtype: mostly around [low, high], sometimes anything (NaN, inf, extremes)."""
    dtype = np.dtype(dtype)
    anything = hnp.from_dtype(dtype)
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        near = st.integers(max(int(low) - 2, int(info.min)), min(int(high) + 2, int(info.max)))
    elif dtype.kind == "f":
        lo, hi = (float(dtype.type(v)) for v in (low - 0.5, high + 0.5))  # representable in the dtype
        near = st.floats(lo, hi, width=8 * dtype.itemsize)
    else:
        return anything
    return st.one_of(near, near, anything)


@st.composite
def arrays(draw, correct: tuple, low: float, high: float):
    dtype = draw(st.sampled_from(NUMPY_DTYPES))
    shape = draw(near_shapes(correct))
    return draw(hnp.arrays(dtype, shape, elements=elements(dtype, low, high)))


@st.composite
def tensors(draw, correct: tuple, low: float, high: float, exotic: bool = True):
    array = draw(arrays(correct, low, high))
    tensor = torch.from_numpy(np.ascontiguousarray(array))
    kind = draw(st.sampled_from(["plain", "cast", "noncontiguous", "grad", "sparse", "meta"] if exotic
                                else ["plain", "cast", "noncontiguous", "grad"]))
    if kind == "cast" and (tensor.is_floating_point() or tensor.dtype in (torch.int64, torch.int32)):
        tensor = tensor.to(draw(st.sampled_from(TORCH_ONLY_FLOATS)))
    elif kind == "noncontiguous" and tensor.ndim >= 2:
        tensor = tensor.transpose(0, 1).contiguous().transpose(0, 1)
    elif kind == "grad" and tensor.is_floating_point():
        tensor = tensor.clone().requires_grad_(True)
    elif kind == "sparse" and tensor.ndim >= 1 and tensor.dtype not in (torch.uint16, torch.uint32, torch.uint64):
        tensor = tensor.to_sparse()
    elif kind == "meta":
        tensor = torch.empty(tensor.shape, dtype=tensor.dtype, device="meta")
    return tensor


SCALARS = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.complex_numbers(max_magnitude=10),
                    st.text(max_size=4), st.binary(max_size=4))
PYTHON_OBJECTS = st.one_of(
    SCALARS,
    st.recursive(SCALARS, lambda children: st.lists(children, max_size=4) | st.tuples(children, children),
                 max_leaves=12),
    st.dictionaries(st.text(max_size=3), SCALARS, max_size=3),
    st.sets(st.integers(), max_size=3),
    st.builds(object),
)


def nested_lists(correct: tuple, low: float, high: float):
    """Python lists of the right (or a nearby) shape, with random numbers (huge ints, NaN)."""
    number = st.one_of(st.integers(int(low) - 2, int(high) + 2), st.integers(), st.floats(low - 1, high + 1),
                       st.floats(), st.booleans(), st.none())
    return near_shapes(correct).flatmap(
        lambda shape: st.just(number) if not shape else _lists_of(number, shape))


def _lists_of(leaf, shape):
    strategy = leaf
    for size in reversed(shape):
        strategy = st.lists(strategy, min_size=size, max_size=size)
    return strategy


def malformed(correct: tuple, low: float, high: float, exotic: bool = True) -> st.SearchStrategy:
    tensor = tensors(correct, low, high, exotic)
    return st.one_of(tensor, tensor, arrays(correct, low, high), nested_lists(correct, low, high), PYTHON_OBJECTS)


# ---------------------------------------------------------------------- state snapshots
def snapshot(env) -> dict:
    state = dict(env.get_state())
    for group in env.renderer.scene.groups:
        state.update({f"renderer/{group}/{k}": v for k, v in env.renderer.instance_state(group).items()})
    return state


def assert_unchanged(before: dict, after: dict, what):
    changed = [k for k in before if not torch.equal(before[k], after[k])]
    assert not changed, f"a rejected call with {what!r} changed {changed}"


def call_checked(call, state, value, allowed=(ValueError, TypeError), names=None):
    """call(): success, or an `allowed` error with state() unchanged (and, if `names` is given,
    a message that names that argument). Anything else propagates."""
    before = state()
    try:
        call()
    except allowed as error:
        assert_unchanged(before, state(), value)
        assert names is None or names in str(error), (names, value, error)


# ---------------------------------------------------------------------- BatchedEnv.step
CORE_VARIANTS = [(n, c) for n in ("cartpole", "spread", "tag", "forage", "push") for c in (False, True)]


@pytest.fixture(scope="module", params=CORE_VARIANTS, ids=[f"{n}-{'continuous' if c else 'discrete'}"
                                                           for n, c in CORE_VARIANTS])
def core_env(request):
    name, continuous = request.param
    env = make_env(name, num_worlds=W, resolution=RES, seed=0, continuous=continuous, state_obs=True,
                   autoreset=True)
    env.reset()
    yield env
    env.close()


@settings(max_examples=60, **SETTINGS)
@given(data=st.data())
def test_core_step(core_env, data):
    env = core_env
    A = env.num_agents
    if env.continuous:
        actions = data.draw(malformed((W, A, env.action_dim), -1.0, 1.0), label="actions")
    else:
        actions = data.draw(malformed((W, A), 0, env.num_actions - 1), label="actions")
    call_checked(lambda: env.step(actions), lambda: snapshot(env), actions)


@settings(max_examples=60, **SETTINGS)
@given(mask=malformed((W,), 0, 1), seed=st.one_of(st.none(), st.integers(-2, 2 ** 64), PYTHON_OBJECTS))
def test_core_reset_worlds(core_env, mask, seed):
    env = core_env
    call_checked(lambda: env.reset_worlds(mask, seed=seed), lambda: snapshot(env), (mask, seed))


# ---------------------------------------------------------------------- PettingZoo step
PZ_VARIANTS = [(n, c) for n in ("spread", "tag") for c in (False, True)]


@pytest.fixture(scope="module", params=PZ_VARIANTS, ids=[f"{n}-{'continuous' if c else 'discrete'}"
                                                         for n, c in PZ_VARIANTS])
def pz_env(request):
    name, continuous = request.param
    env = make_parallel_env(name, resolution=RES, seed=0, continuous=continuous)
    env.reset(seed=0)
    yield env
    env.close()


def pz_action(env, agent) -> st.SearchStrategy:
    core = env.core
    if core.continuous:
        return malformed((core.action_dim,), -1.0, 1.0, exotic=False)
    return st.one_of(malformed((), 0, core.num_actions - 1, exotic=False), st.integers(-1, core.num_actions))


@settings(max_examples=80, **SETTINGS)
@given(data=st.data())
def test_pettingzoo_step(pz_env, data):
    env = pz_env
    if not env.agents:
        env.reset()
    agents = list(env.agents)
    actions = {a: env.action_space(a).sample() for a in agents}
    mode = data.draw(st.sampled_from(["one_value", "one_value", "all_values", "keys", "not_a_dict"]), label="mode")
    if mode == "one_value":
        actions[data.draw(st.sampled_from(agents), label="agent")] = data.draw(pz_action(env, None), label="action")
    elif mode == "all_values":
        actions = {a: data.draw(pz_action(env, a), label=a) for a in agents}
    elif mode == "keys":
        extra = data.draw(st.dictionaries(st.one_of(st.text(max_size=8), st.integers(), st.sampled_from(
            env.possible_agents)), st.integers(0, 1), max_size=2), label="extra keys")
        dropped = data.draw(st.lists(st.sampled_from(agents), max_size=len(agents), unique=True), label="dropped")
        actions = {**{a: v for a, v in actions.items() if a not in dropped}, **extra}
    else:
        actions = data.draw(PYTHON_OBJECTS, label="actions")
    state = lambda: {**snapshot(env.core), "agents": torch.tensor([hash(a) for a in env.agents])}  # noqa: E731
    # PettingZoo convention (documented in wrappers/pettingzoo.py): wrong agent keys are a KeyError.
    call_checked(lambda: env.step(actions), state, actions, allowed=(ValueError, TypeError, KeyError))


# ---------------------------------------------------------------------- TorchRL step
TORCHRL_VARIANTS = [pytest.param((name, continuous, group_map),
                                 id=f"{name}-{group_map}-{'continuous' if continuous else 'discrete'}")
                    for name, group_map in (("spread", "team"), ("tag", "one_group"), ("tag", "team"))
                    for continuous in (False, True)]


@pytest.fixture(scope="module", params=TORCHRL_VARIANTS)
def torchrl_env(request):
    name, continuous, group_map = request.param
    env = make_torchrl_env(name, num_worlds=W, resolution=RES, seed=0, continuous=continuous, group_map=group_map)
    td = env.reset()
    yield env, td
    env.close()


@settings(max_examples=60, **SETTINGS)
@given(data=st.data())
def test_torchrl_step(torchrl_env, data):
    env, td = torchrl_env
    core = env.core
    step_td = env.rand_action(td.clone())
    group = data.draw(st.sampled_from(sorted(env.group_map)), label="group")
    N = len(env.group_map[group])
    trailing = (core.action_dim,) if core.continuous else ()
    low, high = (-1.0, 1.0) if core.continuous else (0, core.num_actions - 1)
    dtype = data.draw(st.sampled_from(NUMPY_DTYPES), label="dtype")
    extra = data.draw(st.sampled_from([trailing, trailing + (1,), (2,), (3,), trailing[:-1] if trailing else (1,)]),
                      label="trailing")
    array = data.draw(hnp.arrays(dtype, (W, N) + extra, elements=elements(dtype, low, high)), label="action")
    step_td.set((group, "action"), torch.from_numpy(np.ascontiguousarray(array)))
    call_checked(lambda: env.step(step_td), lambda: snapshot(core), array)


# ---------------------------------------------------------------------- renderer and scene
@pytest.fixture(scope="module")
def renderer():
    scene = mr.Scene(num_worlds=W, agents_per_world=2, resolution=(8, 12), effects=("lighting",))
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[10, 10, 1])
    scene.add_group("boxes", "box", capacity=3)
    r = mr.BatchRenderer(scene)
    r.render()
    yield r
    r.close()


FIELDS = {"position": ((W, 3, 3), -5.0, 5.0), "rotation": ((W, 3, 4), -1.0, 1.0), "scale": ((W, 3, 3), 0.0, 2.0),
          "color": ((W, 3, 4), 0.0, 1.0), "active": ((W, 3), 0, 1), "owner": ((W, 3), -1, 1)}


def renderer_state(r):
    return {**r.instance_state("boxes"), "camera_position": r.camera_position.clone(),
            "camera_rotation": r.camera_rotation.clone(), "fov_y": r.fov_y.clone(), "near": r.near.clone(),
            "far": r.far.clone()}


@settings(max_examples=200, **SETTINGS)
@given(data=st.data())
def test_renderer_update_and_cameras(renderer, data):
    if data.draw(st.booleans(), label="cameras"):
        name = data.draw(st.sampled_from(["position", "look_at", "rotation", "fov_y", "near", "far"]), label="arg")
        correct = {"position": (W, 2, 3), "look_at": (W, 2, 3), "rotation": (W, 2, 4)}.get(name, ())
        value = data.draw(st.one_of(malformed(correct, 0.01, 3.0), st.floats()), label=name)
        call = lambda: renderer.set_cameras(**{name: value})  # noqa: E731
    elif data.draw(st.booleans(), label="group"):
        name, value = "group", data.draw(st.one_of(PYTHON_OBJECTS, st.sampled_from(["boxes", "floor"])), label="group")
        call = lambda: renderer.update(value, active=torch.ones(W, 3, dtype=torch.bool))  # noqa: E731
    else:
        name = data.draw(st.sampled_from(sorted(FIELDS)), label="field")
        value = data.draw(malformed(*FIELDS[name]), label=name)
        call = lambda: renderer.update("boxes", **{name: value})  # noqa: E731
    call_checked(call, lambda: renderer_state(renderer), (name, value), names=name)
    frame = renderer.render()  # whatever was accepted renders
    assert frame.rgb.shape == (W, 2, 8, 12, 3)


SCENE_VALUES = st.one_of(st.integers(-3, 40), st.floats(), PYTHON_OBJECTS,
                         st.tuples(st.integers(-2, 40), st.integers(-2, 40)))


@settings(max_examples=150, **SETTINGS)
@given(kwargs=st.fixed_dictionaries({}, optional={
    "num_worlds": SCENE_VALUES, "agents_per_world": SCENE_VALUES, "resolution": SCENE_VALUES,
    "effects": st.one_of(st.lists(st.sampled_from(["lighting", "fog", "depth", "bloom", ""]), max_size=3),
                         PYTHON_OBJECTS),
    "background": st.one_of(st.lists(st.floats(), max_size=5), PYTHON_OBJECTS),
    "fov_y": st.one_of(st.floats(), PYTHON_OBJECTS), "near": st.one_of(st.floats(), PYTHON_OBJECTS),
    "far": st.one_of(st.floats(), PYTHON_OBJECTS)}))
def test_scene_arguments(kwargs):
    """Malformed arguments raise naming one of them; an accepted scene holds what was given
    and renders a frame of [worlds, agents, height, width, 3] pixels of its background."""
    arguments = {"num_worlds": 1, "agents_per_world": 1, "resolution": 8, **kwargs}
    try:
        scene = mr.Scene(**arguments)
    except (ValueError, TypeError) as error:  # the defaults are valid: the message names a given argument
        assert any(name in str(error) for name in kwargs), (kwargs, error)
        return
    resolution = arguments["resolution"]
    height, width = (resolution, resolution) if isinstance(resolution, int) else resolution
    worlds, agents = arguments["num_worlds"], arguments["agents_per_world"]
    assert (scene.num_worlds, scene.agents_per_world, scene.resolution) == (worlds, agents, (height, width))
    assert scene.num_views == worlds * agents
    if "effects" in kwargs:
        assert scene.effects == tuple(sorted(set(kwargs["effects"])))
    with mr.BatchRenderer(scene) as renderer:
        frame = renderer.render()
    assert frame.rgb.dtype == torch.uint8 and frame.rgb.shape == (worlds, agents, height, width, 3)
    background = torch.tensor(scene.background[:3], dtype=torch.float64) * 255
    assert (frame.rgb.to(torch.float64) - background).abs().max() <= 0.5 + 1e-6, (scene.background, frame.rgb[0, 0, 0])


@settings(max_examples=25, **SETTINGS)
@given(worlds=st.integers(1, 6), agents=st.integers(1, 4),
       resolution=st.one_of(st.integers(1, 24), st.tuples(st.integers(1, 24), st.integers(1, 24))),
       # shadows need lighting and something to cast on: tests/test_shadows.py covers them
       effects=st.sets(st.sampled_from([e for e in mr.shaders.EFFECTS if e != "shadows"]), max_size=3),
       background=st.lists(st.floats(0, 1), min_size=3, max_size=4))
def test_valid_scene_arguments_render(worlds, agents, resolution, effects, background):
    """The accepted side of test_scene_arguments, drawn often: the frame has the scene's shape,
    shows the background everywhere (nothing added), and carries the outputs it declares."""
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=resolution, effects=effects,
                     background=background)
    height, width = (resolution, resolution) if isinstance(resolution, int) else resolution
    with mr.BatchRenderer(scene) as renderer:
        frame = renderer.render()
    assert frame.rgb.dtype == torch.uint8 and frame.rgb.shape == (worlds, agents, height, width, 3)
    expected = torch.tensor(background[:3], dtype=torch.float64) * 255
    assert (frame.rgb.to(torch.float64) - expected).abs().max() <= 0.5 + 1e-6, (background, frame.rgb[0, 0, 0, 0])
    assert (frame.depth is not None) == ("depth" in effects)  # log_depth changes the depth buffer, not the outputs
    if frame.depth is not None:
        assert frame.depth.shape == (worlds, agents, height, width) and bool(torch.isinf(frame.depth).all())
    assert (frame.segmentation is not None) == ("segmentation" in effects)
    if frame.segmentation is not None:
        assert frame.segmentation.shape == (worlds, agents, height, width)
        assert bool((frame.segmentation == 0).all())


def scene_with_bodies():
    scene = mr.Scene(num_worlds=1, agents_per_world=2, resolution=8)
    scene.add_group("bodies", "box", capacity=3)
    return scene


def scene_state(scene):
    return sorted(scene.static), sorted(scene.groups), scene.camera_mount


POSE = {"position": ((2, 3), -5.0, 5.0), "rotation": ((2, 4), -1.0, 1.0), "scale": ((2, 3), 0.0, 2.0),
        "color": ((2, 3), 0.0, 1.0)}


@settings(max_examples=150, **SETTINGS)
@given(data=st.data())
def test_scene_building_calls(data):
    """add_static / mount_cameras with one malformed argument: success, or a ValueError /
    TypeError whose message names that argument, with the scene unchanged."""
    scene = scene_with_bodies()
    if data.draw(st.booleans(), label="static"):
        name = data.draw(st.sampled_from(sorted(POSE)), label="argument")
        arguments = {"position": [[0, 0, 0], [1, 0, 0]], name: data.draw(malformed(*POSE[name]), label=name)}
        call = lambda: scene.add_static("walls", "box", **arguments)  # noqa: E731
    else:
        name = data.draw(st.sampled_from(["group", "instance", "offset", "pitch", "hide_owner"]), label="argument")
        value = data.draw({"group": st.one_of(st.sampled_from(["bodies", "ghosts"]), PYTHON_OBJECTS),
                           "instance": malformed((2,), 0, 2), "offset": malformed((3,), -1.0, 1.0),
                           "pitch": st.one_of(st.floats(), PYTHON_OBJECTS, malformed((), -1.0, 1.0)),
                           "hide_owner": st.one_of(st.booleans(), PYTHON_OBJECTS)}[name], label=name)
        arguments = {"group": "bodies", "instance": [0, 1], name: value}
        call = lambda: scene.mount_cameras(**arguments)  # noqa: E731
    before = scene_state(scene)
    try:
        call()
    except (ValueError, TypeError) as error:
        assert name in str(error), (name, error)
        assert scene_state(scene) == before


# ---------------------------------------------------------------------- make_env
ENV_VALUES = st.one_of(st.integers(-2, 4), st.floats(), PYTHON_OBJECTS)


@settings(max_examples=60, **SETTINGS)
@given(name=st.sampled_from(["cartpole", "spread", "tag", "forage", "push"]),
       kwargs=st.fixed_dictionaries({}, optional={
           "num_worlds": ENV_VALUES, "num_agents": ENV_VALUES, "max_steps": st.one_of(ENV_VALUES, st.integers()),
           "seed": st.one_of(ENV_VALUES, st.integers()), "device": st.one_of(ENV_VALUES, st.sampled_from(
               ["cpu", "cuda", "cuda:3", "meta", "mps", "xpu", "hpu", "cpu:0", ""])),
           "resolution": st.one_of(st.integers(-2, 24), st.tuples(st.integers(-2, 24), st.sampled_from([8, 20000])),
                                   PYTHON_OBJECTS),
           "continuous": ENV_VALUES, "torch_threads": ENV_VALUES, "bogus": st.integers()}))
def test_make_env_arguments(name, kwargs):
    from marl_render import backend

    open_before = backend.context().engine.get_num_windows()
    try:
        env = make_env(name, **kwargs)
    except (ValueError, TypeError):
        assert backend.context().engine.get_num_windows() == open_before
        return
    env.close()
