"""The raw OpenGL floor (marl_render.rawgl) draws what BatchRenderer draws."""
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

moderngl = pytest.importorskip("moderngl", reason="the raw OpenGL floor needs moderngl (marl-render[bench])")
try:
    moderngl.create_context(standalone=True, backend="egl", require=410).release()
except Exception as exc:  # no EGL / no GL 4.1 driver on this machine
    pytest.skip(f"moderngl cannot create an OpenGL 4.1 EGL context here: {exc}", allow_module_level=True)

from marl_render import BatchRenderer, Scene  # noqa: E402
from marl_render.rawgl import RawGLRenderer, boxes_scene, measure_floor  # noqa: E402

FLOOR = (0.4, 0.5, 0.3)


def random_scene(seed: int, *, mounted: bool = False, effects=("lighting",)):
    """Floor + boxes + spheres in 2 worlds x 2 agents, 32x48 views; returns (scene, pose)."""
    g = torch.Generator().manual_seed(seed)
    W, A = 2, 2
    scene = Scene(W, A, resolution=(32, 48), effects=effects)
    scene.add_static("floor", "plane", [0.0, 0.0, 0.0], scale=[30.0, 30.0, 1.0], color=FLOOR)
    scene.add_group("boxes", "box", 4)
    scene.add_group("balls", "sphere", 3)
    if mounted:
        scene.mount_cameras("boxes", [0, 1], offset=(0.0, 0.6, 0.3), pitch=-0.2)
    updates = {}
    for name, C in (("boxes", 4), ("balls", 3)):
        size = 0.3 + 0.9 * torch.rand(W, C, 1, generator=g)
        position = (torch.rand(W, C, 3, generator=g) * 2 - 1) * torch.tensor([3.0, 3.0, 0.0])
        position[..., 2] = size[..., 0] / 2
        updates[name] = dict(position=position, rotation=torch.randn(W, C, 4, generator=g),
                             scale=size.expand(W, C, 3) * torch.tensor([1.0, 1.3, 0.8]),
                             color=torch.rand(W, C, 3, generator=g), active=torch.rand(W, C, generator=g) > 0.2)
    angle = torch.rand(W, A, generator=g) * 2 * np.pi
    eye = torch.stack((6 * angle.cos(), 6 * angle.sin(), 1 + 2 * torch.rand(W, A, generator=g)), -1)
    target = (torch.rand(W, A, 3, generator=g) * 2 - 1) * torch.tensor([1.0, 1.0, 0.3])

    def pose(renderer):
        for name, kwargs in updates.items():
            renderer.update(name, **kwargs)
        if not mounted:
            renderer.set_cameras(position=eye, look_at=target)

    return scene, pose


def render_with(cls, scene, pose, **kwargs):
    renderer = cls(scene, **kwargs)
    try:
        pose(renderer)
        return renderer.render().rgb
    finally:
        renderer.close()


@pytest.mark.parametrize("seed, mounted, effects", [
    (0, False, ("lighting",)), (1, False, ("lighting",)), (2, True, ("lighting",)), (3, False, ("fog", "lighting")),
])
def test_matches_batch_renderer(seed, mounted, effects):
    scene, pose = random_scene(seed, mounted=mounted, effects=effects)
    raw = render_with(RawGLRenderer, scene, pose)
    panda = render_with(BatchRenderer, scene, pose)
    assert raw.shape == panda.shape == (2, 2, 32, 48, 3) and raw.dtype == torch.uint8
    assert panda.float().std() > 10, "the scene should not be blank"
    error = (raw.float() - panda.float()).abs().mean(dim=(0, 1, 2, 3))
    assert bool((error < 1.0).all()), f"mean absolute error per channel {error.tolist()} >= 1"


def test_matches_over_several_passes_channels_first():
    scene, pose = random_scene(5)
    kwargs = dict(max_framebuffer_size=64, channels_first=True)  # one 48x32 tile column of 2 views per pass
    raw = render_with(RawGLRenderer, scene, pose, **kwargs)
    panda = render_with(BatchRenderer, scene, pose, **kwargs)
    assert raw.shape == panda.shape == (2, 2, 3, 32, 48)
    error = (raw.float() - panda.float()).abs().mean(dim=(0, 1, 3, 4))
    assert bool((error < 1.0).all()), f"mean absolute error per channel {error.tolist()} >= 1"


def test_floor_only_bottom_is_floor_top_is_background():
    W = 5  # 5 views of 32x48: a 2 x 3 grid with a partly used last row
    scene = Scene(W, 1, resolution=(32, 48))
    scene.add_static("floor", "plane", [0.0, 0.0, 0.0], scale=[200.0, 200.0, 1.0], color=FLOOR)
    renderer = RawGLRenderer(scene)
    yaw = torch.linspace(0, 2 * np.pi, W + 1)[:W]
    rotation = torch.stack(((yaw / 2).cos(), torch.zeros(W), torch.zeros(W), (yaw / 2).sin()), -1)[:, None]
    renderer.set_cameras(position=torch.tensor([0.0, 0.0, 1.5]).expand(W, 1, 3), rotation=rotation)
    rgb = renderer.render().rgb.float()
    renderer.close()
    light = scene.lighting
    direction = np.asarray(light.direction) / np.linalg.norm(light.direction)
    lambert = max(-direction[2], 0.0)  # floor normal is +Z
    shade = np.asarray(light.ambient) + np.asarray(light.color) * lambert
    floor = torch.tensor(np.clip(np.asarray(FLOOR) * shade, 0, 1) * 255)
    background = torch.tensor(scene.background[:3]) * 255
    assert (rgb[:, 0, -1] - floor).abs().max() <= 2, "bottom row of every tile should be the lit floor"
    assert (rgb[:, 0, 0] - background).abs().max() <= 2, "top row of every tile should be the background"


def test_output_is_owned_and_inputs_are_validated():
    scene, pose = random_scene(4)
    renderer = RawGLRenderer(scene)
    pose(renderer)
    first = renderer.render().rgb
    kept = first.clone()
    renderer.update("boxes", active=torch.zeros(2, 4, dtype=torch.bool))
    second = renderer.render().rgb
    assert torch.equal(first, kept) and not torch.equal(first, second)
    with pytest.raises(ValueError, match="position"):
        renderer.update("boxes", position=torch.zeros(2, 5, 3))
    renderer.close()
    renderer.close()
    with pytest.raises(RuntimeError, match="closed"):
        renderer.render()


def test_unsupported_effect_is_rejected():
    scene = Scene(1, 1, effects=("lighting", "depth"))
    with pytest.raises(ValueError, match="depth"):
        RawGLRenderer(scene)


def test_raw_path_does_not_load_panda3d():
    code = textwrap.dedent("""
        import sys
        from marl_render.rawgl import RawGLRenderer, cartpole_scene
        scene, pose = cartpole_scene(4, resolution=16)
        renderer = RawGLRenderer(scene)
        pose(renderer, 0)
        frame = renderer.render()
        assert frame.rgb.shape == (4, 1, 16, 16, 3), frame.rgb.shape
        assert "panda3d" not in sys.modules, "panda3d was imported"
        print("ok")
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "ok" in done.stdout, done.stderr[-2000:]


def test_measure_floor_reports_both_renderers():
    result = measure_floor(lambda: boxes_scene(4, 2, 16, 3), steps=2, warmup=1, repeats=1)
    for key in ("raw", "panda3d"):
        assert result[key]["views_per_s"] > 0 and result[key]["ms_per_frame"] > 0
        assert {"pack", "cull", "gl", "copy"} <= set(result[key]["stages_ms"])
    assert result["ratio"] == pytest.approx(result["raw"]["views_per_s"] / result["panda3d"]["views_per_s"])
    assert result["scene"]["num_views"] == 8 and result["gl"]["renderer"]
