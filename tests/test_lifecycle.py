"""Lifecycle: close() and use after close, memory over many environments and long runs,
several environments in one process, fork safety, determinism within and across processes.

Memory is read from /proc/self/statm. Before each reading the garbage collector runs and
glibc's malloc_trim(0) returns freed heap pages to the OS, so that the numbers measure
memory still in use rather than freed blocks the allocator keeps for reuse (without it
a closed 25 MB framebuffer can linger in RSS). Closed framebuffers are released by the
GL driver lazily (on later GL work), so at most about one framebuffer's worth may linger.
"""
from __future__ import annotations

import gc
import hashlib
import json
import multiprocessing
import subprocess
import sys
from argparse import ArgumentParser

import numpy as np
import pytest
import torch

import marl_render as mr
from marl_render import backend
from marl_render.bench.common import settled_rss_mb as memory_mb
from marl_render.envs import list_envs, make_env, make_parallel_env, make_torchrl_env

ENVS = list_envs()
W = 2
RES = 16

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="reads /proc/self/statm; fork is Linux-only")


def windows() -> int:
    return backend.context().engine.get_num_windows()


# ---------------------------------------------------------------------- close() and use after close
def test_renderer_close_frees_gl_objects_and_is_final():
    baseline = windows()
    scene = mr.Scene(num_worlds=2, agents_per_world=2, resolution=16, effects=("lighting", "depth"))
    scene.add_group("boxes", "box", capacity=2)
    renderer = mr.BatchRenderer(scene)
    renderer.render()
    assert windows() == baseline + 1
    textures = [renderer.views_texture] + [t for p in renderer._passes for t in (p.color, *p.aux.values())]
    textures += [t for g in renderer._groups.values() for t in (g.instances, g.pairs)]
    roots = [p.root for p in renderer._passes]
    renderer.close()
    renderer.close()  # idempotent
    assert windows() == baseline, "the framebuffer was not removed from the engine"
    assert renderer._passes == [] and all(root.is_empty() for root in roots)
    assert not any(t.has_ram_image() for t in textures), "a texture kept its host copy"
    for call in (renderer.render, lambda: renderer.update("boxes", active=torch.ones(2, 2, dtype=torch.bool)),
                 lambda: renderer.set_cameras(fov_y=1.0)):
        with pytest.raises(RuntimeError, match=r"this BatchRenderer is closed; create a new one"):
            call()
    with mr.BatchRenderer(scene) as other:
        other.render()
    assert other._closed and windows() == baseline


def test_env_close_frees_both_renderers_and_is_final():
    baseline = windows()
    env = make_env("tag", num_worlds=W, resolution=RES, seed=0)
    env.reset()
    env.render_overview()
    assert windows() == baseline + 2
    env.close()
    env.close()
    assert windows() == baseline and env.closed and env.views.overview_renderer is None
    for call in (env.reset, lambda: env.step(torch.zeros(W, env.num_agents, dtype=torch.long)), env.get_state,
                 env.render_overview, lambda: env.reset_worlds(torch.ones(W, dtype=torch.bool))):
        with pytest.raises(RuntimeError, match=r"this Tag environment is closed; create a new one"):
            call()


def test_pettingzoo_close_is_idempotent_and_final():
    baseline = windows()
    env = make_parallel_env("spread", resolution=RES, seed=0, render_mode="rgb_array")
    env.reset(seed=0)
    env.render()
    assert windows() == baseline + 2
    env.close()
    env.close()
    assert windows() == baseline
    for call in (env.reset, lambda: env.step({a: 0 for a in env.possible_agents}), env.render):
        with pytest.raises(RuntimeError, match="closed"):
            call()


def test_torchrl_close_is_idempotent_and_final():
    baseline = windows()
    env = make_torchrl_env("spread", num_worlds=W, resolution=RES, seed=0)
    td = env.reset()
    env.render_overview()
    assert windows() == baseline + 2
    env.close()
    env.close()
    assert windows() == baseline and env.is_closed and env.core.closed
    for call in (env.reset, lambda: env.step(env.rand_action(td.clone())), lambda: env.rollout(2),
                 env.render_overview):
        with pytest.raises(RuntimeError, match="closed"):
            call()


MEMORY_SCRIPT = """
import json, torch
from marl_render.bench.common import settled_rss_mb as memory_mb
from marl_render.envs import make_env
make_env("spread", num_worlds=2, resolution=16).close()
baseline = memory_mb()
footprint = None
for _ in range(5):
    env = make_env("spread", num_worlds=64, resolution=128, seed=0)
    env.reset()
    env.step(torch.zeros(64, env.num_agents, dtype=torch.long))
    env.render_overview()
    if footprint is None:
        footprint = memory_mb() - baseline
    env.close()
print(json.dumps({"footprint": footprint, "grown": memory_mb() - baseline}))
"""


def test_close_returns_host_memory():
    """Repeatedly building and closing a large env (64 worlds x 3 agents at 128 px: a ~25 MB
    framebuffer, ~10 MB of observations) must not accumulate its footprint.

    It runs in a fresh process: in a worker that has run other tests, GL objects those tests closed
    are released lazily during this one's first env, which hid part of its footprint (12.7 MB once in CI)."""
    child = subprocess.run([sys.executable, "-c", MEMORY_SCRIPT], capture_output=True, text=True, timeout=300)
    assert child.returncode == 0, child.stderr
    measured = json.loads(child.stdout.strip().splitlines()[-1])
    footprint, grown = measured["footprint"], measured["grown"]
    assert footprint > 20, f"the large env should take memory ({footprint:.1f} MB)"
    # A leak of 1/3 of the footprint per env would add > 1.6 footprints over 5 envs.
    assert grown < 1.5 * footprint + 10, (f"5 large envs built and closed left {grown:.1f} MB "
                                          f"(one env takes {footprint:.1f} MB)")


# ---------------------------------------------------------------------- many environments, long runs
CYCLES = 300
GROWTH_LIMIT_MB = 5.0  # ~17 KB per cycle; a renderer used to leave ~3.5 KB here (37-45 KB elsewhere)


def _small_renderer_cycle():
    scene = mr.Scene(num_worlds=2, agents_per_world=2, resolution=16, effects=("lighting", "depth"))
    scene.add_group("boxes", "box", capacity=2)
    with mr.BatchRenderer(scene) as renderer:
        renderer.update("boxes", active=torch.ones(2, 2, dtype=torch.bool))
        renderer.render()


def _small_env_cycle(seed):
    env = make_env("spread", num_worlds=2, resolution=16, seed=seed)
    env.reset()
    env.step(torch.zeros(2, env.num_agents, dtype=torch.long))
    env.render_overview(resolution=16)
    env.close()


def _growth_mb(cycle) -> float:
    for seed in range(30):  # warm-up: shader cache, torch kernels, allocator pools, llvmpipe threads
        cycle(seed)
    baseline_windows, baseline = windows(), memory_mb()
    for seed in range(CYCLES):
        cycle(seed)
    assert windows() == baseline_windows
    return memory_mb() - baseline


def test_300_renderers_in_one_process_keep_memory_flat():
    grown = _growth_mb(lambda seed: _small_renderer_cycle())
    print(f"{CYCLES} renderers created and closed: resident memory {grown:+.2f} MB")
    assert grown < GROWTH_LIMIT_MB, f"creating and closing {CYCLES} renderers grew resident memory by {grown:.1f} MB"


def test_300_environments_in_one_process_keep_memory_flat():
    grown = _growth_mb(_small_env_cycle)
    print(f"{CYCLES} environments created and closed: resident memory {grown:+.2f} MB")
    assert grown < GROWTH_LIMIT_MB, f"creating and closing {CYCLES} environments grew resident memory by {grown:.1f} MB"


def test_closed_renderers_leave_no_panda3d_bookkeeping_behind():
    """What used to grow per renderer: a statistics collector per (uniquely named) buffer and
    the "render-texture-targets-changed" events nobody consumes without ShowBase. Events of
    others stay queued, in order."""
    from panda3d.core import Event, EventQueue, PStatClient

    queue, stats = EventQueue.get_global_event_queue(), PStatClient.get_global_pstats()
    _small_renderer_cycle()
    _small_env_cycle(0)
    queue.queue_event(Event("user-event-1"))
    queue.queue_event(Event("user-event-2"))
    collectors = stats.get_num_collectors()
    for seed in range(10):
        _small_renderer_cycle()
        _small_env_cycle(seed)
    assert stats.get_num_collectors() == collectors, "Panda3D statistics collectors accumulate"
    names = []
    while not queue.is_queue_empty():
        names.append(queue.dequeue_event().name)
    assert names == ["user-event-1", "user-event-2"]


def test_render_states_do_not_accumulate():
    from panda3d.core import RenderState

    env = make_env("spread", num_worlds=W, resolution=RES, seed=0)
    env.reset()
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        env.step(env.random_actions(g))
    before = RenderState.get_num_states()
    for _ in range(100):
        env.step(env.random_actions(g))
    per_step = RenderState.get_num_states() - before
    env.close()
    before = RenderState.get_num_states()
    for seed in range(20):
        other = make_env("spread", num_worlds=W, resolution=RES, seed=seed)
        other.reset()
        other.close()
    per_env = RenderState.get_num_states() - before
    assert per_step < 20 and per_env < 40, f"render states grew by {per_step} over 100 steps, {per_env} over 20 envs"


def test_texture_memory_is_one_view_and_still_marks_each_call_for_upload():
    from marl_render.panda_buffers import TextureMemory, buffer_texture

    texture = buffer_texture("test", 2)  # 2 RGBA32F texels: 8 floats
    memory = TextureMemory(texture, np.float32)
    first = memory()
    first[:] = torch.arange(8.0)
    seen = texture.get_image_modified().get_seq()
    assert memory() is first and texture.get_image_modified().get_seq() != seen  # same view, marked again
    assert np.frombuffer(texture.get_ram_image(), np.float32).tolist() == list(range(8))
    texture.clear_ram_image()  # Panda3D's array is gone: the next call views the new one
    second = memory()
    assert second is not first and second.shape == (8,) and second.dtype == torch.float32
    second[:] = 5.0
    assert np.frombuffer(texture.get_ram_image(), np.float32).tolist() == [5.0] * 8


def test_steps_make_no_buffer_request_on_panda3d_arrays(monkeypatch):
    """Each buffer request on a Panda3D array leaves 32 bytes behind (Panda3D never frees the
    shape it reports); views made per frame grew an env with shadows by 0.3-0.6 MB per 1,000
    steps (issue 17 item 16). The packing targets and the shadow pass view each texture once."""
    from marl_render import panda_buffers
    from marl_render.bench.soak import skinned_agents
    from marl_render.envs.registry import env_class

    requests = []
    view = panda_buffers.array_view
    monkeypatch.setattr(panda_buffers, "array_view", lambda array, dtype: requests.append(dtype) or view(array, dtype))
    env = make_env(skinned_agents(env_class("spread")), num_worlds=W, resolution=RES, seed=0, shadows=True,
                   depth=True, autoreset="same_step", max_steps=4)
    try:
        g = torch.Generator().manual_seed(0)
        env.reset()
        env.step(env.random_actions(g))
        made = len(requests)
        assert made >= 7  # views, and instances and pairs of each group (the shadow pass's too)
        for step in range(12):  # moving agents, skinned joints, auto-resets every 4 steps, partial resets
            env.step(env.random_actions(g))
            if step % 5 == 0:
                env.reset_worlds(torch.tensor([True, False]))
        assert len(requests) == made, f"{len(requests) - made} buffer requests in 12 steps"
    finally:
        env.close()


@pytest.fixture(scope="module")
def soak_result(tmp_path_factory):
    from marl_render.bench import soak

    out = tmp_path_factory.mktemp("soak")
    # Parsed by the bench's own parser, so a new option gets its default here as it does on the command line.
    parser = ArgumentParser()
    soak.add_arguments(parser)
    args = parser.parse_args(["--env", "spread", "--worlds", "8", "--resolution", "32", "--steps", "300",
                              "--every", "25", "--warmup", "50", "--max-steps", "40", "--depth", "--out", str(out)])
    return soak.run(args)


def test_soak_runs_resets_and_stays_finite(soak_result):
    r = soak_result
    assert r["steps"] == 300 and r["non_finite_count"] == 0, r["non_finite"]
    assert r["partial_resets"] > 0 and r["auto_resets"] > 0  # episodes of 40 steps end inside 300 steps
    assert r["steps_per_s"] > 0 and r["env_steps_per_s"] == pytest.approx(8 * r["steps_per_s"])
    assert [s["step"] for s in r["samples"]] == list(range(0, 301, 25))
    with open(r["files"]["json"]) as f:
        assert json.load(f)["growth_mb"] == pytest.approx(r["growth_mb"])
    with open(r["files"]["png"], "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    print(f"soak: {r['steps_per_s']:.1f} steps/s, growth after warm-up {r['growth_mb']:+.2f} MB "
          f"({r['growth_mb_per_1000_steps']:+.2f} MB/1000 steps)")


def test_soak_memory_is_flat_after_warmup(soak_result):
    r = soak_result
    assert r["growth_mb"] < 4.0, (f"resident memory grew {r['growth_mb']:.1f} MB over {r['growth_steps']} steps "
                                  f"after warm-up ({r['growth_mb_per_1000_steps']:.1f} MB per 1000 steps)")
    assert r["render_states_growth"] < 50


def test_soak_runs_shadows_skinned_agents_and_next_step_autoreset():
    from marl_render.bench import soak

    r = soak.soak("spread", worlds=2, steps=24, resolution=16, every=8, warmup=8, max_steps=6, depth=True,
                  shadows=True, skinned=True, autoreset="next_step")
    assert (r["shadows"], r["skinned"], r["autoreset"]) == (True, True, "next_step")
    assert r["non_finite_count"] == 0, r["non_finite"]
    assert r["auto_resets"] > 0 and [s["step"] for s in r["samples"]] == [0, 8, 16, 24]
    assert all(s["heap_in_use_mb"] > 0 for s in r["samples"])  # glibc's mallinfo2 (Linux only, as this module)


def test_soak_skinned_agents_need_an_arena_env():
    from marl_render.bench import soak

    with pytest.raises(ValueError, match=r"^skinned agents need an arena env \(an ArenaScenario: spread, tag, "
                                         r"\.\.\.\), got 'cartpole'"):
        soak.soak("cartpole", worlds=1, steps=1, skinned=True)


def test_soak_command_line(tmp_path):
    out = subprocess.run([sys.executable, "-m", "marl_render.bench", "soak", "--json", "--steps", "20", "--worlds", "2",
                          "--resolution", "16", "--every", "10", "--no-plot", "--out", str(tmp_path)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["benchmark"] == "soak" and result["steps"] == 20 and result["non_finite_count"] == 0
    assert (tmp_path / "soak.json").exists() and "soak spread: step 20/20" in out.stderr
    out = subprocess.run([sys.executable, "-m", "marl_render.bench", "soak", "--json", "--steps", "20", "--worlds", "2",
                          "--resolution", "16", "--every", "10", "--no-plot", "--shadows", "--autoreset", "next_step",
                          "--max-steps", "5", "--out", str(tmp_path)], capture_output=True, text=True, timeout=300)
    result = json.loads(out.stdout)
    assert result["shadows"] is True and result["autoreset"] == "next_step" and result["auto_resets"] > 0


# ---------------------------------------------------------------------- several environments in one process
def _trace(env, actions_list, overview=False):
    trace = [{k: v.clone() for k, v in env.reset().items()}]
    for actions in actions_list:
        obs, reward, terminated, truncated, info = env.step(actions)
        trace.append({**obs, "reward": reward, "terminated": terminated, "truncated": truncated,
                      "done_worlds": info["done_worlds"]})
        if overview:
            env.render_overview()
    return trace


def test_interleaved_environments_match_each_run_alone():
    configs = [("spread", dict(seed=0)), ("tag", dict(seed=1, continuous=True)),
               ("cartpole", dict(seed=2, depth=True)), ("spread", dict(seed=3, num_agents=2, state_obs=True))]
    envs = [make_env(name, num_worlds=W, resolution=RES, autoreset=True, max_steps=4, **kw) for name, kw in configs]
    g = torch.Generator().manual_seed(0)
    actions = [[env.random_actions(g) for _ in range(8)] for env in envs]
    traces = [[{k: v.clone() for k, v in env.reset().items()}] for env in envs]
    for step in range(8):
        for i, env in enumerate(envs):
            obs, reward, terminated, truncated, info = env.step(actions[i][step])
            traces[i].append({**obs, "reward": reward, "terminated": terminated, "truncated": truncated,
                              "done_worlds": info["done_worlds"]})
            if i == 0:
                env.render_overview()  # a third renderer drawing in between
    for env in envs:
        env.close()
    for (name, kw), trace, acts in zip(configs, traces, actions, strict=True):
        alone = make_env(name, num_worlds=W, resolution=RES, autoreset=True, max_steps=4, **kw)
        expected = _trace(alone, acts)
        alone.close()
        for t, (got, want) in enumerate(zip(trace, expected, strict=True)):
            for key in want:
                assert torch.equal(got[key], want[key]), f"{name} {kw}: step {t} {key} differs when interleaved"


# ---------------------------------------------------------------------- fork
def _in_forked_child(queue, env):
    results = {}
    for label, call in [
        ("step inherited env", lambda: env.step(torch.zeros(W, env.num_agents, dtype=torch.long))),
        ("make_env", lambda: make_env("spread", num_worlds=1, resolution=8)),
        ("make_parallel_env", lambda: make_parallel_env("spread", resolution=8)),
        ("make_torchrl_env", lambda: make_torchrl_env("spread", num_worlds=1, resolution=8)),
    ]:
        try:
            call()
            results[label] = "no error"
        except Exception as error:  # report the error to the parent
            results[label] = f"{type(error).__name__}: {error}"
    queue.put(results)


def test_fork_after_gl_init_is_a_clear_error_for_envs():
    env = make_env("spread", num_worlds=W, resolution=RES, seed=0)
    env.reset()
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_in_forked_child, args=(queue, env))
    child.start()
    try:
        results = queue.get(timeout=120)  # a deadlock in the child fails here instead of hanging
    finally:
        child.join(timeout=30)
        if child.is_alive():
            child.kill()
    for label, message in results.items():
        assert message.startswith("ForkedContextError"), f"{label}: {message}"
        assert "spawn" in message, f"{label}: {message}"
    # The parent is unaffected.
    env.step(torch.zeros(W, env.num_agents, dtype=torch.long))
    env.close()


# ---------------------------------------------------------------------- determinism
ROLLOUT = '''
import hashlib
import torch
from marl_render.envs import list_envs, make_env


def rollout_hash(name, continuous, seed=7):
    """sha256 of observations (pixels, depth, state, masks), rewards and dones of a rollout with
    auto-resets and a partial reset."""
    env = make_env(name, num_worlds=3, resolution=16, seed=seed, continuous=continuous, state_obs=True,
                   depth=True, autoreset=True, max_steps=4)
    g = torch.Generator().manual_seed(seed)
    digest = hashlib.sha256()

    def add(*tensors):
        for t in tensors:
            digest.update(str((t.dtype, tuple(t.shape))).encode())
            digest.update(t.contiguous().numpy().tobytes())

    add(*env.reset().values())
    for step in range(9):
        if continuous:
            actions = torch.rand(3, env.num_agents, env.action_dim, generator=g) * 2 - 1
        else:
            actions = torch.randint(env.num_actions, (3, env.num_agents), generator=g)
        obs, reward, terminated, truncated, info = env.step(actions)
        add(*obs.values(), reward, terminated, truncated, info["done_worlds"])
        if step == 5:
            add(*env.reset_worlds(torch.tensor([True, False, True])).values())
    env.close()
    return digest.hexdigest()


def all_hashes():
    return {f"{name}-{continuous}": rollout_hash(name, continuous) for name in list_envs()
            for continuous in (False, True)}
'''


def _rollout_functions():
    namespace = {}
    exec(compile(ROLLOUT, "rollout", "exec"), namespace)
    return namespace


def test_same_seed_is_bit_identical_in_one_process_and_across_processes():
    script = ROLLOUT + "\nimport json\nprint(json.dumps(all_hashes()))\n"
    # One fresh process (it runs while this one, which has run other tests, makes its two rollouts); a
    # second child compared with the same in-process result took the same path.
    children = [subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True)]
    try:
        first = _rollout_functions()["all_hashes"]()
        second = _rollout_functions()["all_hashes"]()
        outputs = [child.communicate(timeout=300) for child in children]
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
    assert first == second, "two runs in one process differ"
    for child, (stdout, stderr) in zip(children, outputs, strict=True):
        assert child.returncode == 0, stderr
        assert json.loads(stdout.strip().splitlines()[-1]) == first, "a separate process gave another rollout"
    assert len(set(first.values())) == len(first)


@pytest.mark.parametrize("name", ENVS)
def test_reset_with_a_seed_reproduces_an_episode(name):
    env = make_env(name, num_worlds=W, resolution=RES, seed=0, state_obs=True)
    g = torch.Generator().manual_seed(1)
    actions = [env.random_actions(g) for _ in range(6)]

    def episode(seed):
        obs = env.reset(seed=seed)
        trace = [obs["pixels"].clone(), obs["state"].clone()]
        for a in actions:
            obs, reward, terminated, truncated, _ = env.step(a)
            trace += [obs["pixels"], obs["state"], reward, terminated, truncated]
        return trace

    first = episode(5)
    for _ in range(3):  # move the generator and the worlds on
        env.step(env.random_actions(g))
    again = episode(5)
    other = episode(6)
    assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True)), \
        "reset(seed=5) did not reproduce the episode"
    assert not torch.equal(first[1], other[1]), "another seed gave the same episode"
    env.close()


def test_pettingzoo_reset_with_a_seed_reproduces_an_episode():
    env = make_parallel_env("tag", resolution=RES, state_obs=True)

    def episode(seed):
        observations, _ = env.reset(seed=seed)
        for space in env.action_spaces.values():
            space.seed(seed)
        trace = [observations]
        for _ in range(5):
            if not env.agents:
                break
            trace.append(env.step({a: env.action_space(a).sample() for a in env.agents})[:2])
        return json.dumps(trace, default=lambda x: hashlib.sha256(x.tobytes()).hexdigest(), sort_keys=True)

    first = episode(11)
    episode(12)
    assert episode(11) == first
    env.close()


# ---------------------------------------------------------------------- copies
def test_copies_of_gl_owning_objects_are_refused_and_the_original_keeps_working():
    """copy.copy(env) used to share the renderer; collecting the copy closed the original's."""
    import copy

    env = make_env("spread", num_worlds=1, resolution=8, seed=0)
    env.reset()
    renderer = mr.BatchRenderer(mr.Scene(num_worlds=1, agents_per_world=1, resolution=8))
    for original, words in ((env, r"BatchedEnv \('spread'\)"), (renderer, "BatchRenderer"),
                            (mr.backend.context(), "GLContext")):
        for duplicate in (copy.copy, copy.deepcopy):
            with pytest.raises(TypeError, match=f"{words} cannot be pickled or copied"):
                duplicate(original)
    gc.collect()
    env.step(env.random_actions())  # the original still renders
    assert renderer.render().rgb.shape == (1, 1, 8, 8, 3)
    renderer.close()
    env.close()
