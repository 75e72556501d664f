"""Headless GL backend: diagnostics, model files, several renderers, fork safety."""
import multiprocessing
import os
import subprocess
import sys

import pytest
import torch

import marl_render as mr
from marl_render import backend


def test_info_reports_a_gl_4_context():
    info = backend.gl_info()
    assert info.vendor and info.renderer
    assert int(info.glsl_version.split(".")[0]) >= 4
    assert info.max_framebuffer_size >= 4096


def test_info_command_prints_json():
    out = subprocess.run([sys.executable, "-m", "marl_render.info", "--json"], capture_output=True, text=True,
                         check=True)
    assert '"renderer"' in out.stdout and '"glsl_version"' in out.stdout


def test_missing_gl_gives_one_clear_error():
    env = dict(os.environ, __EGL_VENDOR_LIBRARY_FILENAMES="/nonexistent/vendor.json")
    out = subprocess.run([sys.executable, "-m", "marl_render.info"], capture_output=True, text=True, env=env)
    assert out.returncode == 1
    assert "no EGL display could be initialised" in out.stderr
    assert "apt-get install libegl1" in out.stderr


QUAD_EGG = """<CoordinateSystem> { Z-up }
<VertexPool> quad {
  <Vertex> 0 { -0.5 0 -0.5 <Normal> { 0 -1 0 } }
  <Vertex> 1 { 0.5 0 -0.5 <Normal> { 0 -1 0 } }
  <Vertex> 2 { 0.5 0 0.5 <Normal> { 0 -1 0 } }
  <Vertex> 3 { -0.5 0 0.5 <Normal> { 0 -1 0 } }
}
<Polygon> { <VertexRef> { 0 1 2 3 <Ref> { quad } } }
"""


def test_a_model_file_renders_as_an_instance_group(tmp_path):
    path = tmp_path / "quad.egg"
    path.write_text(QUAD_EGG)
    scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=(20, 20), effects=(), background=(0, 0, 0))
    scene.add_group("quads", str(path), capacity=1)
    with mr.BatchRenderer(scene) as renderer:
        renderer.set_cameras(position=torch.zeros(2, 1, 3), rotation=torch.tensor([1.0, 0, 0, 0]).repeat(2, 1, 1))
        renderer.update("quads", position=[[[0, 3, 0]], [[0, 3, 0]]], active=[[True], [False]],
                        color=[[[0, 1, 0]], [[0, 1, 0]]])
        rgb = renderer.render().rgb
    assert (rgb[0, 0, 10, 10] == torch.tensor([0, 255, 0], dtype=torch.uint8)).all()
    assert (rgb[1] == 0).all(), "inactive instance must not be drawn"


def test_several_renderers_in_one_process_work_independently():
    renderers, colours = [], ([1.0, 0, 0], [0, 0, 1.0])
    for colour in colours:
        scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=16, effects=(), background=(0, 0, 0))
        scene.add_group("box", "box", capacity=1)
        renderer = mr.BatchRenderer(scene)
        renderer.set_cameras(position=torch.zeros(1, 1, 3), rotation=torch.tensor([[[1.0, 0, 0, 0]]]))
        renderer.update("box", position=[[[0, 2, 0]]], active=[[True]], color=[[colour]])
        renderers.append(renderer)
    frames = [r.render().rgb[0, 0, 8, 8].tolist() for r in renderers]
    assert frames == [[255, 0, 0], [0, 0, 255]]
    for r in renderers:
        r.close()


def _render_in_child(queue):
    try:
        scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8)
        mr.BatchRenderer(scene).render()
        queue.put("rendered")
    except Exception as error:  # report the error text to the parent
        queue.put(f"{type(error).__name__}: {error}")


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method is Linux-only")
def test_fork_after_gl_init_is_a_clear_error():
    backend.context()  # GL initialised in this (parent) process
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_render_in_child, args=(queue,))
    child.start()
    message = queue.get(timeout=60)
    child.join(timeout=60)
    assert message.startswith("ForkedContextError")
    assert "spawn" in message


def test_a_shader_that_fails_to_compile_raises_with_the_gl_log():
    from panda3d.core import Shader

    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=16)
    scene.add_group("box", "box", capacity=1)
    with mr.BatchRenderer(scene) as renderer:
        broken = Shader.make(Shader.SL_GLSL, "#version 410\nvoid main() { gl_Position = vec4(0.0); }",
                             "#version 410\nout vec4 c;\nvoid main() { c = undefined_colour; }")
        renderer._groups["box"].node.set_shader(broken)
        renderer.update("box", position=[[[0, 2, 0]]], active=[[True]])
        with pytest.raises(backend.ShaderCompileError, match=r"(?s)group\(s\) \['box'\] failed.*undefined_colour"):
            renderer.render()


def test_copy_readback_gives_the_same_pixels():
    scene = mr.Scene(num_worlds=2, agents_per_world=2, resolution=(12, 20))
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[10, 10, 1])
    scene.add_group("box", "box", capacity=1)
    frames = []
    for readback in ("host", "copy"):
        with mr.BatchRenderer(scene, readback=readback) as renderer:
            renderer.set_cameras(position=torch.tensor([0, 0, 1.0]).repeat(2, 2, 1),
                                 look_at=torch.tensor([0, 3, 0.0]).repeat(2, 2, 1))
            renderer.update("box", position=[[[0, 3, 0.5]], [[1, 3, 0.5]]], active=[[True], [True]])
            frames.append(renderer.render().rgb)
            assert set(renderer.last_timings) == {"pack", "cull", "draw", "read", "copy"}
    assert torch.equal(frames[0], frames[1])
    with pytest.raises(ValueError, match=r"readback must be one of \['auto', 'gpu', 'host', 'pbo', 'copy'\], got "
                                         r"'zero_copy'"):
        mr.BatchRenderer(scene, readback="zero_copy")
