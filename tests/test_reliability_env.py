"""The batched env core under adversarial use (issue 9): actions that require grad, thread
counts and batch sizes the machine cannot hold, devices and tensors torch has but the env
cannot use, state read before reset, and an env stepped in a forked child.

Each test failed before its fix. Bad input must raise a clear error that names the
argument, before anything changes; nothing the env returns or keeps may carry an
autograd graph.
"""
from __future__ import annotations

import multiprocessing
import re
import statistics
import subprocess
import sys
import textwrap
import warnings

import pytest
import torch

import marl_render as mr
from marl_render import backend, memory, threads
from marl_render.bench.soak import rss_mb
from marl_render.envs import list_envs, make_env

W = 2
RES = 8
ENVS = list_envs()
GL_LIMIT = backend.gl_info().max_framebuffer_size

pytestmark = pytest.mark.usefixtures("single_torch_thread")


def states_equal(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------------- autograd at the boundary
def tensors_in(value, path: str):
    """(path, tensor) of every tensor inside nested dicts, lists and tuples (named ones too)."""
    if isinstance(value, torch.Tensor):
        yield path, value
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from tensors_in(item, f"{path}[{key!r}]")
    elif isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            yield from tensors_in(item, f"{path}[{index}]")


def held_tensors(env):
    """Every tensor the env and its renderers keep as attributes (state, counters, instance data)."""
    for name, value in vars(env).items():
        yield from tensors_in(value, f"env.{name}")
    for label, renderer in (("renderer", env.renderer), ("overview", env.views.overview_renderer)):
        if renderer is not None:
            for name, value in vars(renderer).items():
                yield from tensors_in(value, f"{label}.{name}")


def with_graph(pairs) -> list[str]:
    return [path for path, tensor in pairs if tensor.requires_grad or tensor.grad_fn is not None]


def policy_output(env) -> torch.Tensor:
    """Continuous actions as a policy returns them: in [-1, 1], attached to its parameters."""
    weight = torch.full((env.action_dim,), 0.5, requires_grad=True)
    return torch.tanh(env.random_actions(torch.Generator().manual_seed(0)) * 3 * weight)


@pytest.mark.parametrize("name", ENVS)
def test_actions_that_require_grad_leave_no_graph_anywhere(name):
    env = make_env(name, num_worlds=W, resolution=RES, seed=0, continuous=True, state_obs=True, depth=True)
    twin = make_env(name, num_worlds=W, resolution=RES, seed=0, continuous=True, state_obs=True, depth=True)
    try:
        returned = [("reset", env.reset())]
        twin.reset()
        actions = policy_output(env)
        assert actions.grad_fn is not None
        assert with_graph([("check_actions", env.check_actions(actions))]) == []
        for step in range(2):
            returned.append((f"step {step}", env.step(actions)))
            returned.append(("get_state", env.get_state()))
        returned.append(("reset_worlds", env.reset_worlds(torch.tensor([True, False]))))
        returned.append(("render_overview", env.render_overview(resolution=RES)))
        returned.append(("reset", env.reset(seed=1)))
        returned.append(("get_state after reset", env.get_state()))
        leaks = with_graph(tensors_in(returned, "")) + with_graph(held_tensors(env))
        assert leaks == [], f"tensors with an autograd graph: {leaks}"
        # ... and the detached actions are the same actions.
        twin.step(actions.detach())
        twin.step(actions.detach())
        twin.reset_worlds(torch.tensor([True, False]))
        twin.reset(seed=1)
        assert states_equal(env.get_state(), twin.get_state())
    finally:
        env.close()
        twin.close()


def test_renderer_keeps_no_graph_of_its_inputs():
    import marl_render as mr

    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=RES)
    scene.add_static("floor", "plane", position=torch.zeros(1, 3, requires_grad=True) * 1)
    scene.add_group("box", "box", capacity=1)
    with mr.BatchRenderer(scene) as renderer:
        position = torch.tensor([[[0.0, 2.0, 0.0]]], requires_grad=True)
        renderer.update("box", position=position * 1, scale=torch.ones(1, 1, 3, requires_grad=True),
                        active=[[True]])
        renderer.set_cameras(position=torch.zeros(1, 1, 3, requires_grad=True) * 1,
                             look_at=position * 1, fov_y=torch.tensor(1.0, requires_grad=True))
        frame = renderer.render()
        kept = list(tensors_in(scene.static["floor"].position, "scene.floor.position"))
        kept += list(tensors_in(vars(renderer), "renderer")) + [("frame", frame.rgb)]
        assert with_graph(kept) == []


@pytest.mark.parametrize("group_map", ["one_group", "per_agent"])
def test_torchrl_actions_that_require_grad_leave_no_graph(group_map):
    from marl_render.envs import make_torchrl_env

    env = make_torchrl_env("spread", num_worlds=W, resolution=RES, seed=0, continuous=True, state_obs=True,
                           group_map=group_map)
    try:
        td = env.reset()
        actions = policy_output(env.core)
        for group, names in env.group_map.items():
            td[group, "action"] = actions[:, [env.agent_names.index(n) for n in names]]
        out = env.step(td)
        next_td = out["next"]
        leaks = [key for key, value in next_td.items(include_nested=True, leaves_only=True)
                 if value.requires_grad or value.grad_fn is not None]
        leaks += with_graph(held_tensors(env.core)) + with_graph(tensors_in(env.core.get_state(), "get_state"))
        assert leaks == [], f"tensors with an autograd graph: {leaks}"
    finally:
        env.close()


# ---------------------------------------------------------------------- thread counts
@pytest.mark.parametrize("value,error,given", [
    (10 ** 6, ValueError, "1000000"), (1025, ValueError, "1025"), (2 ** 63, ValueError, str(2 ** 63)),
    (0, ValueError, "0"), (-4, ValueError, "-4"), (True, TypeError, "True"), (2.0, TypeError, r"2\.0"),
])
def test_torch_threads_out_of_range_is_a_clear_error(value, error, given, framebuffers_made):
    with pytest.raises(error, match=rf"torch_threads must be None or an int in \[1, 1024\], got {given}$"):
        make_env("cartpole", num_worlds=W, resolution=RES, torch_threads=value)
    assert framebuffers_made == []  # refused before anything was allocated


@pytest.mark.parametrize("value,error", [(10 ** 6, ValueError), (2 ** 31, ValueError), (2 ** 64, ValueError),
                                         (0, ValueError), (True, TypeError), (4.0, TypeError)])
def test_limited_threads_rejects_bad_counts_before_changing_anything(value, error):
    before = torch.get_num_threads()
    with pytest.raises(error, match=r"n must be None or an int in \[1, 1024\]"):
        with threads.limited_threads(value):
            pass
    assert torch.get_num_threads() == before
    assert getattr(threads._state, "depth", 0) == 0  # caller_threads() still knows it is outside


def test_the_largest_torch_threads_steps_and_restores_the_caller():
    code = textwrap.dedent("""
        import torch
        from marl_render.envs import make_env
        from marl_render.threads import MAX_THREADS
        torch.set_num_threads(2)
        env = make_env("cartpole", num_worlds=2, resolution=8, torch_threads=MAX_THREADS)
        env.reset()
        env.step(env.random_actions())
        print("threads after", torch.get_num_threads())
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "threads after 2" in out.stdout


# ---------------------------------------------------------------------- memory
@pytest.mark.parametrize("name", ENVS)
def test_twenty_million_worlds_at_resolution_1_is_a_clear_error(name, framebuffers_made):
    before = rss_mb()
    with pytest.raises(ValueError, match=r"^num_worlds=20000000 x num_agents=\d+ at resolution 1x1 needs about "
                                         r"[\d.]+ GiB of host memory, more than the [\d.]+ GiB available "
                                         r"\(\d+ > \d+ bytes\); lower num_worlds"):
        make_env(name, num_worlds=20_000_000, resolution=1)
    assert framebuffers_made == []  # refused before anything was allocated ...
    assert rss_mb() - before < 50  # ... on the GL side or in torch


def test_the_guard_counts_views_instances_and_state_not_only_pixels(monkeypatch):
    """4,000 worlds of spread at 1x1 pixel: 36 kB of pixels, about 60 MB in all."""
    env = make_env("spread", num_worlds=4000, resolution=1)
    needed = memory.renderer_bytes(env.renderer.scene) + env.num_worlds * memory.ENV_WORLD_BYTES
    env.close()
    assert needed > 1000 * 4000 * env.num_agents * 3
    monkeypatch.setattr(memory, "available_bytes", lambda: needed - 1)
    with pytest.raises(ValueError, match=rf"num_worlds=4000 .* \({needed} > {needed - 1} bytes\)"):
        make_env("spread", num_worlds=4000, resolution=1)
    monkeypatch.setattr(memory, "available_bytes", lambda: needed)
    make_env("spread", num_worlds=4000, resolution=1).close()


# (env, num_worlds, resolution, shadow map resolution or 0, depth): views and instances, pixels,
# the shadow atlas (the old estimate counted 8 of its 11.4 bytes per texel: 0.69x), a mix.
ESTIMATE_POINTS = [("spread", 10000, 1, 0, False), ("cartpole", 2000, 64, 0, False),
                   ("spread", 1024, 8, 256, False), ("spread", 500, 32, 128, True)]


@pytest.mark.skipif(sys.platform != "linux", reason="reads the peak RSS from /proc")
@pytest.mark.parametrize("name, worlds, resolution, shadow_map, depth", ESTIMATE_POINTS)
def test_the_estimate_is_within_25_percent_of_the_measured_peak(name, worlds, resolution, shadow_map, depth):
    """Peak RSS of building, resetting and stepping a batch, in a fresh process, against the
    guard's estimate: within docs/reliability.md's ±25% (the old guard counted 3 bytes a world at 1x1)."""
    code = textwrap.dedent(f"""
        import resource, torch
        import marl_render as mr
        from marl_render import memory
        from marl_render.envs import make_env

        def high_water_mark():  # of this process image (ru_maxrss would include the parent's before exec)
            status = open("/proc/self/status").read()
            return int(status.split("VmHWM:")[1].split()[0]) * 1024

        options = dict(shadows=mr.Shadows({shadow_map}) if {shadow_map} else False, depth={depth})
        warm = make_env({name!r}, num_worlds=1, resolution=4, **options)
        warm.reset(); warm.step(warm.random_actions()); warm.close()
        base = int(open("/proc/self/statm").read().split()[1]) * resource.getpagesize()
        env = make_env({name!r}, num_worlds={worlds}, resolution={resolution}, seed=0, **options)
        env.reset()
        for _ in range(5):
            env.step(env.random_actions())
        peak = high_water_mark() - base
        estimate = memory.renderer_bytes(env.renderer.scene) + env.num_worlds * memory.ENV_WORLD_BYTES
        print("ratio", peak / estimate, "peak", peak)
    """)
    # One process's peak varies by up to ~45 MB between identical runs (the allocator's and llvmpipe's
    # memory come in steps of ~6 MB, taken or not by the time of the peak): the median of three runs.
    ratios, outputs = [], []
    for _ in range(3):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
        ratios.append(float(re.search(r"ratio ([\d.]+)", out.stdout).group(1)))
        outputs.append(out.stdout.strip())
    ratio = statistics.median(ratios)
    assert 0.75 < ratio < 1.25, f"measured peak / estimate = {ratio:.2f}, the median of {outputs}"


def test_render_overview_beyond_any_machine_is_a_clear_error_and_keeps_the_old_overview():
    env = make_env("cartpole", num_worlds=4096, resolution=1, seed=0)
    try:
        env.reset()
        first = env.render_overview(resolution=2)
        overview, state = env.views.overview_renderer, env.get_state()
        with pytest.raises(ValueError, match=rf"^render_overview\(resolution=\({GL_LIMIT}, {GL_LIMIT}\)\) with "
                                             r"num_worlds=4096 needs about [\d.]+ GiB of host memory"):
            env.render_overview(resolution=GL_LIMIT)
        assert env.views.overview_renderer is overview and not overview._closed
        assert states_equal(state, env.get_state())
        assert torch.equal(env.render_overview(resolution=2), first)
    finally:
        env.close()


def test_render_overview_counts_its_views_before_replacing_the_old_one(monkeypatch):
    env = make_env("spread", num_worlds=W, resolution=RES, seed=0)
    try:
        env.reset()
        first = env.render_overview()
        overview = env.views.overview_renderer
        monkeypatch.setattr(memory, "available_bytes", lambda: 32 * 2 ** 20)
        with pytest.raises(ValueError, match=r"render_overview\(resolution=\(2048, 2048\)\) with num_worlds=2 "
                                             r"needs about 0\.\d\d GiB of host memory, more than the 0\.03 GiB"):
            env.render_overview(resolution=2048)
        assert env.views.overview_renderer is overview
        assert torch.equal(env.render_overview(), first)
    finally:
        env.close()


# ---------------------------------------------------------------------- smaller items
@pytest.mark.parametrize("device", ["cpu:1", "cpu:7", torch.device("cpu", 3)])
def test_a_second_cpu_device_is_a_clear_error(device):
    with pytest.raises(ValueError, match=r"device must be 'cpu' \(torch has a single CPU device\) or a CUDA "
                                         r"device, got .*cpu.*[137]"):
        make_env("cartpole", num_worlds=W, resolution=RES, device=device)


def test_cpu_0_is_the_cpu():
    env = make_env("cartpole", num_worlds=W, resolution=RES, device="cpu:0")
    try:
        assert env.device == torch.device("cpu")
        assert env.reset()["pixels"].device == env.device
    finally:
        env.close()


@pytest.mark.parametrize("layout", [torch.strided, torch.jagged])
@pytest.mark.parametrize("continuous", [False, True])
def test_nested_tensors_are_a_type_error_naming_the_argument(layout, continuous):
    env = make_env("spread", num_worlds=W, resolution=RES, seed=0, continuous=continuous)
    try:
        env.reset()
        env.step(env.random_actions(torch.Generator().manual_seed(0)))
        before = env.get_state()
        parts = list(env.random_actions(torch.Generator().manual_seed(1)))
        with warnings.catch_warnings():  # "nested tensors are a prototype"
            warnings.simplefilter("ignore", UserWarning)
            actions = torch.nested.nested_tensor(parts, layout=layout)
            mask = torch.nested.nested_tensor([torch.ones(1, dtype=torch.bool)] * W, layout=layout)
        with pytest.raises(TypeError, match=r"^actions must be a dense tensor with data, got a nested tensor on cpu"):
            env.step(actions)
        with pytest.raises(TypeError, match=r"^mask must be a dense tensor with data, got a nested tensor on cpu"):
            env.reset_worlds(mask)
        assert states_equal(before, env.get_state())
    finally:
        env.close()


def test_get_state_before_reset_is_an_error_like_step():
    env = make_env("cartpole", num_worlds=W, resolution=RES)
    try:
        for call in (env.get_state, lambda: env.step(env.random_actions())):
            with pytest.raises(RuntimeError, match=r"call reset\(\) before using this CartPoleBalance environment"):
                call()
        env.reset()
        assert set(env.get_state()) >= {"step_count", "alive", "rng"}
    finally:
        env.close()
    with pytest.raises(RuntimeError, match="closed"):
        env.get_state()


def _use_in_forked_child(env, results):
    """Each GL-backed call must raise ForkedContextError before the state changes."""
    torch.set_num_threads(1)  # no OpenMP pool in a forked child
    report = []
    try:
        for label, call in (("step", lambda: env.step(env.random_actions(torch.Generator().manual_seed(2)))),
                            ("reset", lambda: env.reset(seed=5)),
                            ("reset_worlds", lambda: env.reset_worlds(torch.tensor([True, False]), seed=5)),
                            ("render_overview", lambda: env.render_overview(resolution=4))):
            before = env.get_state()
            try:
                call()
                report.append(f"{label}: nothing raised")
            except backend.ForkedContextError:
                if not states_equal(before, env.get_state()):
                    report.append(f"{label}: state changed before ForkedContextError")
            except Exception as exc:  # noqa: BLE001 - reported to the parent
                report.append(f"{label}: {type(exc).__name__}: {exc}")
    finally:
        results.put(report)


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method is Linux-only")
@pytest.mark.parametrize("name", ["cartpole", "tag"])
def test_a_forked_child_is_refused_before_anything_changes(name):
    env = make_env(name, num_worlds=W, resolution=RES, seed=0)
    try:
        env.reset()
        env.step(env.random_actions(torch.Generator().manual_seed(1)))
        context = multiprocessing.get_context("fork")
        results = context.Queue()
        child = context.Process(target=_use_in_forked_child, args=(env, results))
        child.start()
        report = results.get(timeout=120)
        child.join(timeout=60)
        assert report == []
        env.step(env.random_actions())  # the parent's env still works
    finally:
        env.close()


def test_batch_renderer_refuses_a_batch_beyond_memory_before_allocating():
    # Built directly, without an env: the renderer checks its own estimate first.
    scene = mr.Scene(num_worlds=20_000_000, agents_per_world=1, resolution=1)
    scene.add_group("bodies", "box", capacity=2)
    with pytest.raises(ValueError, match=r"BatchRenderer of num_worlds=20000000 .* needs about .* GiB of host memory"):
        mr.BatchRenderer(scene)
    # Supersampling multiplies the pixels: a batch that fits at k=1 is refused at a huge k.
    small = mr.Scene(num_worlds=64, agents_per_world=4, resolution=64)
    assert memory.renderer_bytes(small, supersample=256) > 2 ** 39  # 0.96 TB: more than any test machine has
    with pytest.raises(ValueError, match=r"supersample=256\).* needs about"):
        mr.BatchRenderer(small, supersample=256)
    with mr.BatchRenderer(small) as renderer:
        assert renderer.render().rgb.shape == (64, 4, 64, 64, 3)


# ---------------------------------------------------------------------- pickling (issue 17, item 15)
def _front_ends():
    from marl_render.envs import make_sb3_env, make_torchrl_env, make_vec_env
    return [(lambda: make_env("spread", num_worlds=W, resolution=RES), "BatchedEnv|Spread", "make_env"),
            (lambda: make_vec_env("spread", num_worlds=W, resolution=RES), "MarlRenderVectorEnv", "make_vec_env"),
            (lambda: make_sb3_env("cartpole", num_worlds=W, resolution=RES), "MarlRenderSB3VecEnv", "make_sb3_env"),
            (lambda: make_torchrl_env("spread", num_worlds=W, resolution=RES), "MarlRenderTorchRLEnv",
             "make_torchrl_env")]


@pytest.mark.parametrize("index", range(4), ids=["core", "vector", "sb3", "torchrl"])
def test_pickling_an_env_says_to_build_it_from_its_configuration(index):
    """pickle.dumps (and so a spawn worker's arguments) and copy.deepcopy of an env that owns GL
    state raise a TypeError that says what to do, not "cannot pickle '_thread.RLock' object"."""
    import copy
    import pickle

    build, kind, maker = _front_ends()[index]
    env = build()
    # (the core's copies are refused by its own __copy__ / __deepcopy__)
    for attempt in (pickle.dumps,) if index == 0 else (pickle.dumps, copy.deepcopy):
        with pytest.raises(TypeError, match=rf"({kind}).*cannot be pickled or copied: it owns an OpenGL renderer"
                                            rf".*configuration.*{maker}"):
            attempt(env)
    env.reset()  # the env is untouched
    env.close()


def test_a_spawn_worker_given_an_env_gets_the_clear_error():
    env = make_env("cartpole", num_worlds=1, resolution=RES)
    process = multiprocessing.get_context("spawn").Process(target=print, args=(env,))
    with pytest.raises(TypeError, match="cannot be pickled or copied.*make_env"):
        process.start()
    env.close()


# ---------------------------------------------------------------------- exit (issue 17, item 19)
EXIT_SCRIPT = textwrap.dedent("""
    import atexit, sys
    def teardown():  # registered before marl_render is imported, so it runs after marl_render's exit hook
        for module in ("marl_render.render.backend", "marl_render.render.renderer"):
            sys.modules[module].os = None  # what the interpreter's teardown leaves once it clears module globals
        for owner in owners:
            owner.__del__()
    atexit.register(teardown)
    from marl_render.envs import make_env, make_vec_env, make_sb3_env
    class Owner:  # like RLlib's VectorMultiAgentEnv, whose __del__ closes the env it holds
        def __init__(self, env):
            self.env = env
        def __del__(self):
            self.env.close()
    owners = []
    for env in (make_env("spread", num_worlds=2, resolution=8), make_vec_env("tag", num_worlds=2, resolution=8),
                make_sb3_env("cartpole", num_worlds=2, resolution=8)):
        env.reset()
        owners.append(Owner(env))
    kept = make_vec_env("spread", num_worlds=1, resolution=8)  # alive at exit, never closed
    kept.reset()
    print("done")
""")


def test_envs_alive_at_exit_and_closed_by_late_finalisers_are_silent():
    """Envs still open at exit, closed by finalisers after module globals are gone: no noise."""
    done = subprocess.run([sys.executable, "-c", EXIT_SCRIPT], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout == "done\n"
    assert done.stderr == ""


def test_an_interrupted_sync_is_made_whole_by_the_next_render(monkeypatch):
    """A caught Ctrl-C inside reset_worlds' instance sync used to leave the renderer with the old
    episode's landmarks while the state had the new ones."""
    env = make_env("spread", num_worlds=3, resolution=16, seed=2)
    twin = make_env("spread", num_worlds=3, resolution=16, seed=2)
    env.reset(), twin.reset()
    original = env.scenario.instances
    calls = {"n": 0}

    def interrupted_once(state, full):
        if full and calls["n"] == 0:
            calls["n"] += 1
            raise KeyboardInterrupt
        return original(state, full)

    monkeypatch.setattr(env.scenario, "instances", interrupted_once)
    with pytest.raises(KeyboardInterrupt):
        env.reset_worlds(torch.tensor([True, False, True]))
    twin.set_state(env.get_state())  # the same state, synced in full
    actions = torch.tensor([[1, 2, 3], [0, 1, 4], [3, 3, 1]])
    for _ in range(3):
        mine, theirs = env.step(actions)[0], twin.step(actions)[0]
        assert torch.equal(mine["pixels"], theirs["pixels"])
    env.close(), twin.close()


def test_the_memory_estimate_counts_skinned_joints():
    """W=512, C=8 instances of a 300-joint skin were estimated at 3.7 MB while the forward
    kinematics of a render took about 275 MB more than at W=16."""
    from marl_render import memory

    limb = mr.skinned_limb(bones=300)

    def scene(worlds, mesh):
        s = mr.Scene(num_worlds=worlds, agents_per_world=1, resolution=8)
        s.add_group("walkers", mesh, capacity=8)
        return s

    skinned = memory.renderer_bytes(scene(512, limb)) - memory.renderer_bytes(scene(16, limb))
    rigid = memory.renderer_bytes(scene(512, "box")) - memory.renderer_bytes(scene(16, "box"))
    assert skinned - rigid == (512 - 16) * 8 * limb.num_joints * memory.JOINT_BYTES
    assert 200e6 < skinned < 400e6  # the measured growth was about 275 MB
