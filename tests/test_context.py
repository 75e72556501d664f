"""An explicit GL context (marl_render.GLContext): it owns the renderers made on it and
releases them in one place; process-wide settings can be switched off (configure)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch

import marl_render as mr
from marl_render import backend
from marl_render.envs import make_env


def box_renderer(context=None, **options):
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=16, effects=(), background=(0, 0, 0))
    scene.add_group("box", "box", capacity=1)
    renderer = mr.BatchRenderer(scene, context=context, **options)
    renderer.set_cameras(position=torch.zeros(1, 1, 3), rotation=torch.tensor([[[1.0, 0, 0, 0]]]))
    renderer.update("box", position=[[[0, 2, 0]]], active=[[True]], color=[[[1.0, 0, 0]]])
    return renderer


def test_a_context_releases_its_renderers_at_the_end_of_its_with_block():
    engine = backend.context().engine
    windows = engine.get_num_windows()
    with mr.GLContext() as ctx:
        first, second = box_renderer(ctx), box_renderer(ctx)
        assert first.render().rgb[0, 0, 8, 8].tolist() == [255, 0, 0]
        assert second.render().rgb[0, 0, 8, 8].tolist() == [255, 0, 0]
        assert engine.get_num_windows() == windows + 3  # its host buffer and one framebuffer per renderer
    assert ctx.closed and engine.get_num_windows() == windows  # every buffer of the context is gone
    for renderer in (first, second):
        with pytest.raises(RuntimeError, match="this BatchRenderer is closed"):
            renderer.render()
    ctx.close()  # twice is fine
    # The default context is untouched, and a new context works after a closed one.
    with box_renderer() as renderer:
        assert renderer.render().rgb[0, 0, 8, 8].tolist() == [255, 0, 0]
    with mr.GLContext() as again, box_renderer(again) as renderer:
        assert renderer.render().rgb[0, 0, 8, 8].tolist() == [255, 0, 0]


def test_a_closed_context_raises_a_clear_error():
    ctx = mr.GLContext()
    ctx.close()
    with pytest.raises(RuntimeError, match="this GLContext is closed"):
        box_renderer(ctx)
    with pytest.raises(RuntimeError, match="this GLContext is closed"):
        with ctx.current():
            pass
    with pytest.raises(RuntimeError, match="this GLContext is closed"):
        make_env("cartpole", num_worlds=1, context=ctx)


def test_bad_context_arguments_are_refused():
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=())
    with pytest.raises(TypeError, match=r"context must be a marl_render.GLContext or None, got 'gpu'"):
        mr.BatchRenderer(scene, context="gpu")
    with pytest.raises(TypeError, match=r"context must be a marl_render.GLContext or None, got 0"):
        make_env("cartpole", num_worlds=1, context=0)
    with mr.GLContext() as ctx:
        other = 1 if ctx.device_index != 1 else 0
        with pytest.raises(ValueError, match=rf"egl_device_index={other} was given with a context on EGL device"):
            mr.BatchRenderer(scene, context=ctx, egl_device_index=other)
        assert engine_windows(ctx) == 1  # nothing was made on it


def engine_windows(ctx) -> int:
    return sum(1 for i in range(ctx.engine.get_num_windows()) if ctx.engine.get_window(i).get_gsg() == ctx.gsg)


def test_an_env_renders_on_the_given_context_and_closes_with_it():
    with mr.GLContext() as ctx:
        env = make_env("cartpole", num_worlds=2, context=ctx)
        env.reset()
        pixels = env.step(torch.zeros(2, 1, dtype=torch.int64))[0]["pixels"]
        assert pixels.shape == (2, 1, *env.resolution, 3) and int(pixels.float().std()) > 0
        assert env.renderer._context is ctx
    with pytest.raises(RuntimeError, match="closed"):
        env.renderer.render()


def run_python(code: str, env_vars: dict) -> dict:
    """Run `code` in a fresh interpreter (the settings are process-wide); it prints JSON."""
    environment = {k: v for k, v in os.environ.items() if k != "LP_NUM_THREADS"}
    environment.update(env_vars)
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                            timeout=300, env=environment)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


PROBE = """
    import json, os, torch
    from panda3d.core import Notify
    import marl_render as mr
    stream = Notify.out().this
    {configure}
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=())
    scene.add_group("box", "box", capacity=1)
    with mr.BatchRenderer(scene) as renderer:
        renderer.render()
    try:
        mr.configure(set_lp_num_threads=True, capture_panda_log=True)
        late = None
    except RuntimeError as error:
        late = str(error)
    print(json.dumps({{"lp": os.environ.get("LP_NUM_THREADS"), "log_redirected": Notify.out().this != stream,
                      "late": late}}))
"""


def test_by_default_llvmpipe_threads_are_set_and_panda3d_log_is_captured():
    result = run_python(PROBE.format(configure=""), {})
    assert result["lp"] == str(min(16, 2 * (os.cpu_count() or 1)))
    assert result["log_redirected"] is True
    assert result["late"] is None  # asking for what is already in effect is no change


def test_a_value_the_user_set_is_kept():
    assert run_python(PROBE.format(configure=""), {"LP_NUM_THREADS": "3"})["lp"] == "3"


def test_both_process_wide_settings_can_be_switched_off():
    result = run_python(PROBE.format(configure="mr.configure(set_lp_num_threads=False, capture_panda_log=False)"), {})
    assert result["lp"] is None  # os.environ untouched
    assert result["log_redirected"] is False  # Panda3D's log stream untouched
    assert "must be called before the first GL context" in result["late"]


def test_configure_checks_its_arguments():
    with pytest.raises(TypeError, match=r"set_lp_num_threads must be a bool or None, got int 0"):
        mr.configure(set_lp_num_threads=0)
    with pytest.raises(TypeError, match=r"capture_panda_log must be a bool or None, got str 'no'"):
        mr.configure(capture_panda_log="no")
    assert mr.configure() == backend.Settings(set_lp_num_threads=True, capture_panda_log=True)
