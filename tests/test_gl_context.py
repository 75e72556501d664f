"""The shared GL context: use from other threads, the EGL device it runs on, and other
native libraries loaded next to it."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
import threading

import pytest
import torch

import marl_render as mr
from marl_render import backend
from marl_render.envs import make_env

RED, BLUE = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]


def in_thread(function, *args):
    """function(*args) run in a new thread: (result, None) or (None, exception)."""
    outcome = {}

    def target():
        try:
            outcome["result"] = function(*args)
        except BaseException as error:  # handed back to the test
            outcome["error"] = error

    thread = threading.Thread(target=target)
    thread.start()
    thread.join(timeout=120)
    assert not thread.is_alive(), "the call did not return"
    return outcome.get("result"), outcome.get("error")


def box_renderer(colour, x=0.0):
    """One world, one agent at the origin looking along +y at a box 2 m ahead."""
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=16, effects=(), background=(0, 0, 0))
    scene.add_group("box", "box", capacity=1)
    renderer = mr.BatchRenderer(scene)
    renderer.set_cameras(position=torch.zeros(1, 1, 3), rotation=torch.tensor([[[1.0, 0, 0, 0]]]))
    renderer.update("box", position=[[[x, 2, 0]]], active=[[True]], color=[[colour]])
    return renderer


def windows() -> int:
    return backend.context().engine.get_num_windows()


# ---------------------------------------------------------------------- threads
def test_render_from_another_thread_draws_the_current_state():
    with box_renderer(RED) as renderer:
        first = renderer.render().rgb
        assert first[0, 0, 8, 8].tolist() == [255, 0, 0]
        renderer.update("box", color=[[BLUE]], position=[[[0.4, 2, 0]]])
        frame, error = in_thread(renderer.render)
        assert error is None, repr(error)
        again = renderer.render().rgb  # the main thread, same state
    assert frame.rgb[0, 0, 8, 8].tolist() == [0, 0, 255], "the thread got a stale frame"
    assert torch.equal(frame.rgb, again)
    assert not torch.equal(frame.rgb, first)


def test_env_stepped_from_another_thread_matches_the_main_thread():
    env, twin = (make_env("cartpole", num_worlds=2, resolution=32, seed=3) for _ in range(2))
    start = env.reset()["pixels"].clone()
    twin.reset()
    actions = [torch.full((2, 1), i % 2, dtype=torch.long) for i in range(20)]

    def rollout(which):
        return [which.step(a)[0]["pixels"].clone() for a in actions]

    threaded, error = in_thread(rollout, env)
    assert error is None, repr(error)
    expected = rollout(twin)
    same = all(torch.equal(a, b) for a, b in zip(threaded, expected, strict=True))
    assert same, "pixels differ from the main thread's"
    assert not torch.equal(threaded[-1], start), "the pole should have moved in 20 steps"
    state, twin_state = env.get_state(), twin.get_state()
    assert all(torch.equal(state[k], twin_state[k]) for k in state if k != "rng")
    env.close()
    twin.close()


def test_renderers_drawn_by_several_threads_at_once_keep_their_own_pixels():
    renderers = [box_renderer(RED), box_renderer(BLUE)]
    results = [[] for _ in renderers]
    barrier = threading.Barrier(len(renderers))

    def draw(index):
        barrier.wait()
        for step in range(15):
            x = 0.02 * step * (1 if index == 0 else -1)
            renderers[index].update("box", position=[[[x, 2, 0]]])
            results[index].append((x, renderers[index].render().rgb))

    threads = [threading.Thread(target=draw, args=(i,)) for i in range(len(renderers))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    for index, renderer in enumerate(renderers):
        assert len(results[index]) == 15, "a drawing thread failed"
        for x, rgb in results[index]:
            renderer.update("box", position=[[[x, 2, 0]]])
            assert torch.equal(rgb, renderer.render().rgb), f"renderer {index} at x={x} differs when drawn alone"
        renderer.close()


def test_close_from_another_thread_frees_the_framebuffer():
    baseline = windows()
    renderer = box_renderer(RED)
    renderer.render()
    _, error = in_thread(renderer.close)
    assert error is None, repr(error)
    assert windows() == baseline
    with box_renderer(BLUE) as other:  # the context still works in this thread
        assert other.render().rgb[0, 0, 8, 8].tolist() == [0, 0, 255]


def test_a_renderer_built_in_another_thread_renders_in_this_one():
    renderer, error = in_thread(box_renderer, RED)
    assert error is None, repr(error)
    with renderer:
        assert renderer.render().rgb[0, 0, 8, 8].tolist() == [255, 0, 0]


# ---------------------------------------------------------------------- EGL device
def test_a_second_egl_device_index_is_an_error():
    backend.context()  # the process's context exists (on the default display or $MARL_RENDER_EGL_DEVICE)
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8)
    with pytest.raises(ValueError, match=r"egl_device_index=99 was given, but this process's GL context already "
                                         r"uses (the default EGL display|EGL device \d+) \(egl_device_index=\w+\)"):
        mr.BatchRenderer(scene, egl_device_index=99)
    in_use = backend.context().device_index
    if in_use is not None:  # the index in use is accepted again
        mr.BatchRenderer(scene, egl_device_index=in_use).close()
    with pytest.raises(TypeError, match=r"egl_device_index must be an int >= 0 or None, got str '0'"):
        mr.BatchRenderer(scene, egl_device_index="0")
    with pytest.raises(ValueError, match=r"egl_device_index must be an int >= 0 or None, got -1"):
        mr.BatchRenderer(scene, egl_device_index=-1)


# ---------------------------------------------------------------------- other LLVMs in the process
TRITON_AFTER_THE_FIRST_ENV = textwrap.dedent("""
    import sys
    import torch
    from marl_render.envs import make_env

    env = make_env("cartpole", num_worlds=2, resolution=32, seed=0)
    first = env.reset()["pixels"].clone()
    assert "triton" not in sys.modules, "triton was loaded before anyone imported it"
    import triton
    import triton.language
    import torch._dynamo  # what torch.compile imports
    for _ in range(20):
        pixels = env.step(torch.ones(2, 1, dtype=torch.long))[0]["pixels"]
    assert not torch.equal(pixels, first), "rendering stopped after triton was imported"
    print("rendered after importing triton", triton.__version__)
""")


@pytest.mark.skipif(importlib.util.find_spec("triton") is None,
                    reason="triton is not installed (the CUDA builds of torch ship it)")
def test_importing_triton_after_the_first_env_does_not_crash():
    """triton carries its own LLVM; Mesa's llvmpipe loads another one globally. In a child
    process, so that a segmentation fault fails this test instead of ending pytest."""
    out = subprocess.run([sys.executable, "-c", TRITON_AFTER_THE_FIRST_ENV], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, f"exit status {out.returncode} (-11: segmentation fault)\n{out.stderr[-3000:]}"
    assert "rendered after importing triton" in out.stdout
