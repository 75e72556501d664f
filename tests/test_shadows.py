"""Shadows on demand: each world's shadow falls where the analytic projection puts it, in
that world's views only, and scenes without the effect have no shadow code or pass.

Frame: Z up. A box standing on the floor (z = 0) under a directional light d casts the
convex hull of its corners projected along d onto the floor: p - d * p_z / d_z.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import marl_render as mr
from marl_render import backend, shaders

F64 = torch.float64
LIGHT = mr.Lighting(direction=(-0.5, 0.35, -1.0), color=(0.6, 0.6, 0.6), ambient=(0.3, 0.3, 0.3))
FLOOR_COLOR = 0.8
BOUNDS = ((-4.0, -4.0, 0.0), (4.0, 4.0, 2.0))
H, W = 80, 96
FOV = math.radians(60.0)
EYES = [(-1.5, 3.0, 2.5), (-3.0, -1.0, 2.5)]  # two views per world, both looking at the origin
# One box per world: centre, size, yaw. World 2 has none (inactive).
BOXES = [((-1.0, 0.5), (0.8, 0.6, 0.8), 0.0), ((1.2, -0.8), (0.5, 1.0, 1.2), 0.5)]


def smooth_floor() -> mr.MeshData:
    """A floor whose normals differ by 1e-3 between corners: not flat, so it takes the
    per-fragment lighting path (the plane takes the per-vertex one)."""
    plane = mr.plane()
    normals = plane.normals.copy()
    normals[0] = (1e-3, 0.0, 1.0)
    return mr.MeshData("smooth_floor", plane.positions, normals / np.linalg.norm(normals, axis=1, keepdims=True),
                       plane.uvs, plane.triangles)


def shadow_scene(*, pcf=False, floor="plane", effects=("lighting", "shadows", "segmentation"), worlds=3,
                 resolution=1024):
    scene = mr.Scene(num_worlds=worlds, agents_per_world=len(EYES), resolution=(H, W), effects=effects,
                     lighting=LIGHT, fov_y=FOV, shadows=mr.Shadows(resolution=resolution, pcf=pcf, bounds=BOUNDS))
    scene.add_static("floor", floor, position=[0.0, 0.0, 0.0], scale=[12.0, 12.0, 1.0], color=[FLOOR_COLOR] * 3)
    scene.add_group("box", "box", capacity=1)
    return scene


def place_boxes(renderer, boxes, worlds=3):
    position = torch.zeros(worlds, 1, 3, dtype=F64)
    scale = torch.ones(worlds, 1, 3)
    yaw = torch.zeros(worlds, 1)
    active = torch.zeros(worlds, 1, dtype=torch.bool)
    for w, ((x, y), size, angle) in enumerate(boxes):
        position[w, 0] = torch.tensor([x, y, size[2] / 2])
        scale[w, 0] = torch.tensor(size)
        yaw[w, 0] = angle
        active[w, 0] = True
    renderer.update("box", position=position, scale=scale, rotation=mr.quat_from_yaw_pitch_roll(yaw), active=active,
                    color=torch.tensor([0.9, 0.2, 0.2]).repeat(worlds, 1, 1))


def look(renderer, eyes, worlds=3):
    position = torch.tensor(eyes, dtype=F64).expand(worlds, len(eyes), 3)
    renderer.set_cameras(position=position, look_at=torch.zeros(worlds, len(eyes), 3, dtype=F64))


# ----------------------------------------------------------------------------- analytic shadow
def shadow_polygon(box) -> np.ndarray:
    """[K, 2] floor points (z = 0), counter-clockwise: the box's shadow under LIGHT."""
    (x, y), size, yaw = box
    d = np.array(LIGHT.direction)
    corners = np.array([[sx, sy, sz] for sx in (-0.5, 0.5) for sy in (-0.5, 0.5) for sz in (0.0, 1.0)]) * size
    c, s = math.cos(yaw), math.sin(yaw)
    corners = corners @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) + [x, y, 0.0]
    floor = corners - d * (corners[:, 2:] / d[2])
    return convex_hull(floor[:, :2])


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Andrew's monotone chain, counter-clockwise."""
    points = sorted(map(tuple, points))

    def half(sequence):
        chain = []
        for p in sequence:
            while len(chain) >= 2 and cross(chain[-2], chain[-1], p) <= 0:
                chain.pop()
            chain.append(p)
        return chain[:-1]

    return np.array(half(points) + half(points[::-1]))


def cross(o, a, b) -> float:
    """z of (a - o) x (b - o): > 0 when o, a, b turn counter-clockwise."""
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def to_pixels(points: np.ndarray, eye) -> np.ndarray:
    """Floor points [K, 2] -> (column, row) [K, 2] in a view from `eye` looking at the origin."""
    eye = np.array(eye, dtype=float)
    forward = -eye / np.linalg.norm(eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    relative = np.c_[points, np.zeros(len(points))] - eye
    depth = relative @ forward
    focal = (H / 2) / math.tan(FOV / 2)
    return np.stack((W / 2 + relative @ right / depth * focal, H / 2 - relative @ up / depth * focal), -1)


def outline_distance(polygon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inside [H, W] bool, distance [H, W] of each pixel centre to the outline, in pixels)."""
    columns, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    centres = np.stack((columns, rows), -1)[:, :, None]  # [H, W, 1, 2]
    start, end = polygon, np.roll(polygon, -1, axis=0)
    edge = end - start
    t = np.clip(((centres - start) * edge).sum(-1) / (edge * edge).sum(-1), 0.0, 1.0)
    distance = np.linalg.norm(centres - (start + t[..., None] * edge), axis=-1).min(-1)
    side = edge[:, 0] * (centres[..., 1] - start[:, 1]) - edge[:, 1] * (centres[..., 0] - start[:, 0])
    # Rows grow downwards, so a counter-clockwise floor polygon turns clockwise in pixels.
    inside = (side <= 0).all(-1) | (side >= 0).all(-1)
    return inside, distance


def lit_and_shadowed() -> tuple[float, float]:
    d = np.array(LIGHT.direction) / np.linalg.norm(LIGHT.direction)
    lambert = max(-d[2], 0.0)
    return (255 * FLOOR_COLOR * (LIGHT.ambient[0] + LIGHT.color[0] * lambert), 255 * FLOOR_COLOR * LIGHT.ambient[0])


def near(mask: np.ndarray) -> np.ndarray:
    """mask grown by one pixel (8-neighbourhood)."""
    padded = np.pad(mask, 1)
    return np.any([padded[1 + dy:1 + dy + H, 1 + dx:1 + dx + W] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)


def check_views(frame, scene, boxes, eyes=EYES, *, smooth_floor=False):
    """Every view's floor is dark exactly inside its own world's analytic shadow (1 px slack).

    A smooth (per-fragment lit) floor counts a receiver level with a stored back face as
    lit, so where the box stands on it up to half a shadow texel of floor may be lit: there
    the floor pixels next to the box are not checked either."""
    lit, shadowed = lit_and_shadowed()
    floor_id, box_id = scene.segment_ids("floor")[0], scene.segment_ids("box")[0]
    for w in range(scene.num_worlds):
        for a, eye in enumerate(eyes):
            image = frame.rgb[w, a, ..., 0].to(torch.float64).numpy()
            floor = frame.segmentation[w, a].numpy() == floor_id
            if w < len(boxes):
                inside, distance = outline_distance(to_pixels(shadow_polygon(boxes[w]), eye))
            else:
                inside, distance = np.zeros((H, W), bool), np.full((H, W), np.inf)
            clear = floor & (distance > 1.0)
            if smooth_floor:
                clear &= ~near(frame.segmentation[w, a].numpy() == box_id)
            dark = np.abs(image - shadowed) < np.abs(image - lit)
            wrong = clear & (dark != inside)
            assert not wrong.any(), (f"world {w} view {a}: {wrong.sum()} floor pixels more than 1 px from the "
                                     f"analytic outline are {'dark' if dark[wrong][0] else 'lit'} at "
                                     f"{np.argwhere(wrong)[:5].tolist()}")
            expected = np.where(inside, shadowed, lit)
            assert np.abs(image - expected)[clear].max() <= 1.0, "lit/shadowed floor colours follow Lambert"
            if w < len(boxes):
                assert (clear & inside).sum() > 25, f"world {w} view {a}: the shadow must be in view"


@pytest.mark.parametrize("pcf", [False, True])
@pytest.mark.parametrize("floor", ["plane", "smooth"])
def test_shadow_outline_matches_the_analytic_projection_in_its_own_world_only(pcf, floor):
    scene = shadow_scene(pcf=pcf, floor=smooth_floor() if floor == "smooth" else "plane")
    with mr.BatchRenderer(scene) as renderer:
        place_boxes(renderer, BOXES)
        look(renderer, EYES)
        check_views(renderer.render(), scene, BOXES, smooth_floor=floor == "smooth")


def test_shadows_follow_the_boxes_in_the_same_frame_and_survive_camera_moves():
    scene = shadow_scene()
    moved = [BOXES[1], BOXES[0]]  # the worlds swap their boxes
    with mr.BatchRenderer(scene) as renderer:
        place_boxes(renderer, BOXES)
        look(renderer, EYES)
        renderer.render()
        place_boxes(renderer, moved)
        check_views(renderer.render(), scene, moved)  # no frame of lag
        look(renderer, EYES[::-1])  # only cameras move: the atlas is kept, not redrawn
        assert not renderer.shadow_pass.pending
        check_views(renderer.render(), scene, moved, EYES[::-1])


def test_shadows_are_right_when_views_take_several_passes():
    scene = shadow_scene()
    with mr.BatchRenderer(scene, max_framebuffer_size=W) as renderer:
        assert renderer.layout.num_passes == 6  # one view per pass
        place_boxes(renderer, BOXES)
        look(renderer, EYES)
        check_views(renderer.render(), scene, BOXES)


def test_shadow_atlas_holds_one_tile_per_world():
    scene = shadow_scene(worlds=5, resolution=64)
    with mr.BatchRenderer(scene) as renderer:
        layout = renderer.shadow_pass.layout
        assert (layout.num_views, layout.tile_width, layout.tile_height) == (5, 64, 64)
        assert layout.columns * layout.rows >= 5 and layout.num_passes == 1
        assert renderer.shadow_pass.atlas.get_x_size() == layout.columns * 64


def test_a_caster_wider_than_its_tile_stays_in_its_own_world():
    """The atlas is a grid (world 1's tile is right of world 0's): a caster far wider than
    the bounds is clipped on every side of its tile, so no other world gets its shadow."""
    scene = shadow_scene()
    with mr.BatchRenderer(scene) as renderer:
        assert renderer.shadow_pass.layout.columns >= 2
        place_boxes(renderer, [((0.0, 0.0), (40.0, 40.0, 0.3), 0.0)])  # world 0 only
        look(renderer, EYES)
        frame = renderer.render()
    lit, shadowed = lit_and_shadowed()
    floor_id = scene.segment_ids("floor")[0]
    for w in (1, 2):
        for a in range(len(EYES)):
            floor = frame.segmentation[w, a].numpy() == floor_id
            image = frame.rgb[w, a, ..., 0].to(torch.float64).numpy()
            assert floor.sum() > H * W // 4
            assert np.abs(image - lit)[floor].max() <= 1.0, f"world {w} view {a}: world 0's caster spilled"


# ----------------------------------------------------------------------------- only on demand
def windows() -> int:
    return backend.context().engine.get_num_windows()


def test_without_the_effect_there_is_no_shadow_pass_nor_shadow_code(monkeypatch):
    """(That the shadow blocks vanish from preprocessed source is in test_effects.py.)"""
    seen = []

    def recording(defines):
        seen.append(defines)
        return real(defines)

    real = shaders.compiled
    monkeypatch.setattr(shaders, "compiled", recording)
    monkeypatch.setattr(shaders, "compiled_caster", lambda defines: pytest.fail("a shadow caster was compiled"))
    before = windows()
    scene = shadow_scene(effects=("lighting",))
    with mr.BatchRenderer(scene) as renderer:
        assert windows() == before + 1  # the main buffer only
        assert renderer.shadow_pass is None
        place_boxes(renderer, BOXES)
        renderer.render()
    assert len(seen) == 2  # floor and box
    for defines in seen:
        assert not [d for d in defines if "SHADOW" in d]
    assert windows() == before


def test_with_the_effect_the_atlas_buffer_exists_and_is_released():
    before = windows()
    scene = shadow_scene(pcf=True)
    renderer = mr.BatchRenderer(scene)
    assert windows() == before + 2
    from panda3d.core import Shader

    for group in ("floor", "box"):
        source = renderer._groups[group].node.get_shader().get_text(Shader.ST_fragment).splitlines()
        assert "#define EFFECT_SHADOWS" in source and "#define SHADOW_PCF" in source
    renderer.close()
    assert windows() == before


# ----------------------------------------------------------------------------- settings
@pytest.mark.parametrize("make, error, match", [
    (lambda: mr.Shadows(resolution=0), ValueError, r"shadows.resolution must be an int >= 1, got 0"),
    (lambda: mr.Shadows(resolution=256.0), TypeError, r"shadows.resolution must be an int >= 1, got 256.0"),
    (lambda: mr.Shadows(pcf="yes"), TypeError, r"shadows.pcf must be a bool, got 'yes'"),
    (lambda: mr.Shadows(bounds=(0, 0, 0)), ValueError, r"shadows.bounds must be .*shape \[2, 3\], got shape \[3\]"),
    (lambda: mr.Shadows(bounds="arena"), TypeError, r"shadows.bounds must be \(\(x0, y0, z0\), \(x1, y1, z1\)\)"),
    (lambda: mr.Shadows(bounds=((0, 0, 0), (1, -1, 1))), ValueError, r"shadows.bounds must have min <= max"),
    (lambda: mr.Shadows(bounds=((0, 0, 0), (1, float("nan"), 1))), ValueError, r"shadows.bounds"),
    (lambda: mr.Scene(num_worlds=1, agents_per_world=1, shadows={"resolution": 64}), TypeError,
     r"shadows must be a marl_render.Shadows, got \{'resolution': 64\}"),
    (lambda: mr.Scene(num_worlds=1, agents_per_world=1, effects=("shadows",)), ValueError,
     r"effects: 'shadows' .* needs 'lighting' too, got \['shadows'\]"),
])
def test_bad_settings_are_rejected_naming_the_argument(make, error, match):
    with pytest.raises(error, match=match):
        make()


def test_renderer_rejects_atlases_it_cannot_build_and_leaks_nothing():
    before = windows()
    too_big = mr.Scene(num_worlds=5, agents_per_world=1, effects=("lighting", "shadows"),
                       shadows=mr.Shadows(resolution=backend.gl_info().max_framebuffer_size, bounds=BOUNDS))
    too_big.add_group("box", "box", capacity=1)
    with pytest.raises(ValueError, match=r"shadows.resolution must let 5 shadow maps fit in one"):
        mr.BatchRenderer(too_big)
    no_static = mr.Scene(num_worlds=1, agents_per_world=1, effects=("lighting", "shadows"))
    no_static.add_group("box", "box", capacity=1)
    with pytest.raises(ValueError, match=r"shadows.bounds must be given when the scene has no static geometry"):
        mr.BatchRenderer(no_static)
    edge_on = mr.Scene(num_worlds=1, agents_per_world=1, effects=("lighting", "shadows"),
                       lighting=mr.Lighting(direction=(0, 0, -1)), shadows=mr.Shadows(bounds=((0, 0, 0), (0, 2, 1))))
    edge_on.add_group("box", "box", capacity=1)
    with pytest.raises(ValueError, match=r"shadows.bounds must have an area seen along lighting.direction"):
        mr.BatchRenderer(edge_on)
    assert windows() == before


def test_default_bounds_fit_the_static_geometry():
    from marl_render.shadows import static_bounds

    scene = mr.Scene(num_worlds=1, agents_per_world=1, effects=("lighting", "shadows"))
    scene.add_static("floor", "box", position=[[0.0, 0.0, -0.05], [2.0, 0.0, 0.5]],
                     scale=[[6.0, 4.0, 0.1], [1.0, 1.0, 1.0]],
                     rotation=[[1.0, 0.0, 0.0, 0.0], [math.cos(math.pi / 8), 0.0, 0.0, math.sin(math.pi / 8)]])
    low, high = static_bounds(scene)
    half_diagonal = math.sqrt(0.5)  # the second box turned 45 degrees about Z
    np.testing.assert_allclose(low, (-3.0, -2.0, -0.1), atol=1e-6)
    np.testing.assert_allclose(high, (max(3.0, 2.0 + half_diagonal), 2.0, 1.0), atol=1e-6)


# ----------------------------------------------------------------------------- environments
def test_an_env_switches_shadows_on_and_they_only_darken():
    from marl_render.envs import make_env, scenery

    images = {}
    for shadows in (False, True):
        env = make_env("spread", num_worlds=2, resolution=48, seed=5, shadows=shadows)
        try:
            obs = env.reset(seed=5)
            images[shadows] = (obs["pixels"], env.render_overview(resolution=64))
            assert ("shadows" in env.renderer.scene.effects) == shadows
            assert ("shadows" in env.views.overview_renderer.scene.effects) == shadows
            if shadows:
                assert env.renderer.scene.shadows.bounds == scenery.arena_shadow_bounds(env.arena_half_extent)
        finally:
            env.close()
    for plain, shaded in zip(images[False], images[True], strict=True):
        assert plain.shape == shaded.shape
        assert (shaded <= plain).all(), "a shadow only removes the directional light"
        assert (shaded < plain).any(-1).float().mean() > 0.01, "part of the images is in shadow"


def test_env_shadows_argument_is_checked():
    from marl_render.envs import make_env

    with pytest.raises(TypeError, match=r"shadows must be a bool or a marl_render.Shadows, got 'yes'"):
        make_env("spread", shadows="yes")
    settings = mr.Shadows(resolution=32, pcf=False, bounds=BOUNDS)
    env = make_env("spread", num_worlds=1, resolution=16, shadows=settings)
    try:
        assert env.renderer.scene.shadows is settings
    finally:
        env.close()


def test_shadows_far_from_the_origin_still_match_the_analytic_projection():
    """The scene 1e6 m away: each world's origin is recentred and its light box with it."""
    shift = torch.tensor([1e6, -2e6, 0.0], dtype=F64)
    low, high = (tuple((torch.tensor(b, dtype=F64) + shift).tolist()) for b in BOUNDS)
    scene = mr.Scene(num_worlds=3, agents_per_world=len(EYES), resolution=(H, W),
                     effects=("lighting", "shadows", "segmentation"), lighting=LIGHT, fov_y=FOV,
                     shadows=mr.Shadows(resolution=1024, pcf=False, bounds=(low, high)))
    scene.add_static("floor", "plane", position=shift, scale=[12.0, 12.0, 1.0], color=[FLOOR_COLOR] * 3)
    scene.add_group("box", "box", capacity=1)
    with mr.BatchRenderer(scene) as renderer:
        place_boxes(renderer, [((x + float(shift[0]), y + float(shift[1])), size, yaw) for (x, y), size, yaw in BOXES])
        eyes = torch.tensor(EYES, dtype=F64) + shift
        renderer.set_cameras(position=eyes.expand(3, -1, -1), look_at=shift.expand(3, len(EYES), 3))
        frame = renderer.render()
        assert bool((renderer.world_origin != 0).all(dim=1).any())
    check_views(frame, scene, BOXES)  # the analytic shadow is the same relative to the shift


def test_an_atlas_too_large_for_gl_is_named_before_the_memory_estimate():
    """Shadows(resolution=2**31) used to fail with a memory message blaming num_worlds and resolution."""
    from marl_render.envs import make_env

    scene = mr.Scene(num_worlds=4, agents_per_world=1, resolution=8, effects=("lighting", "shadows"),
                     shadows=mr.Shadows(resolution=2 ** 31))
    with pytest.raises(ValueError, match=r"shadows\.resolution must let 4 shadow maps fit .* got 2147483648"):
        mr.BatchRenderer(scene)
    with pytest.raises(ValueError, match=r"shadows\.resolution must let 2 shadow maps fit"):
        make_env("spread", num_worlds=2, resolution=8, shadows=mr.Shadows(resolution=2 ** 31))
