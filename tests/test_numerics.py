"""Numerical robustness of rendering: far from the origin, extreme near/far ratios,
extreme scales, and depth accuracy.

Camera frame: +Y forward, +Z up, X right. Small resolutions and one renderer per test
keep this file fast on 2 CPU cores.
"""
from __future__ import annotations

import math
import warnings

import pytest
import torch

import marl_render as mr
from marl_render import transforms as T

warnings.filterwarnings("ignore", message="The given NumPy array is not writable")

F64 = torch.float64
IDENTITY = torch.tensor([1.0, 0.0, 0.0, 0.0])
# A plane (facing +Z) turned +90 degrees about X faces -Y: towards a camera looking +Y.
FACING_CAMERA = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])


def background_rgb(scene: mr.Scene) -> torch.Tensor:
    return torch.round(torch.tensor(scene.background[:3], dtype=F64) * 255).to(torch.uint8)


def max_channel_diff(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a.int() - b.int()).abs().amax(-1)


def ones(*shape) -> torch.Tensor:
    return torch.ones(*shape, dtype=torch.bool)


# ----------------------------------------------------------------------------- far from the origin
def render_street(offset, res=(48, 64)):
    """Floor + two static pillars + three rotated dynamic boxes, two cameras, all moved by `offset`."""
    off = torch.tensor(offset, dtype=F64)
    scene = mr.Scene(num_worlds=1, agents_per_world=2, resolution=res, effects=("lighting", "depth", "segmentation"))
    scene.add_static("floor", "plane", position=torch.tensor([[0.0, 0.0, 0.0]], dtype=F64) + off,
                     scale=[[20, 20, 1]], color=[[0.3, 0.6, 0.3]])
    scene.add_static("pillars", "box", position=torch.tensor([[3.0, 4.0, 1.0], [-3.0, 6.0, 0.5]], dtype=F64) + off,
                     rotation=[[1, 0, 0, 0], [0.9, 0, 0, 0.3]], scale=[[0.5, 0.5, 2], [1, 1, 1]],
                     color=[[0.9, 0.9, 0.2], [0.2, 0.9, 0.9]])
    scene.add_group("boxes", "box", capacity=3)
    renderer = mr.BatchRenderer(scene)
    position = torch.tensor([[[0.0, 0.0, 0.5], [1.3, 2.1, 0.25], [-1.7, 1.1, 0.3]]], dtype=F64) + off
    rotation = mr.quat_from_yaw_pitch_roll(torch.tensor([[0.3, 1.0, -0.5]], dtype=F64))
    renderer.update("boxes", position=position, rotation=rotation,
                    scale=torch.tensor([[[1, 1, 1], [0.5, 0.5, 0.5], [0.6, 0.3, 0.6]]]),
                    color=torch.tensor([[[1, 0.2, 0.2], [0.2, 0.2, 1], [0.8, 0.5, 0.1]]]), active=ones(1, 3))
    eye = torch.tensor([[[0.0, -5.0, 1.5], [4.0, -3.0, 2.0]]], dtype=F64) + off
    target = torch.tensor([[[0.0, 0.0, 0.5], [0.0, 2.0, 0.3]]], dtype=F64) + off
    renderer.set_cameras(position=eye, look_at=target)
    frame = renderer.render()
    ids = {name: scene.segment_ids(name) for name in ("floor", "pillars", "boxes")}
    renderer.close()
    return frame, ids


@pytest.fixture(scope="module")
def street_at_origin():
    return render_street((0.0, 0.0, 0.0))


@pytest.mark.parametrize("offset", [(1e6, -1e6, 0.0), (-2.5e7, 1e7, 300.0)])
def test_far_from_origin_renders_like_the_origin(street_at_origin, offset):
    """Asserted tolerance: mean |diff| < 0.5 per channel, at most 0.5% of pixels differ by
    more than 1 in any channel, segmentation equal on >= 99.5% of pixels, depth within 1e-3
    relative. Static groups (hi/lo split) and dynamic groups (per-world origin) both appear."""
    ref, ids = street_at_origin
    far, _ = render_street(offset)
    seg = ref.segmentation
    for name, r in ids.items():  # every kind of geometry is actually on screen
        assert ((seg >= r.start) & (seg < r.stop)).sum() > 20, name
    diff = (ref.rgb.int() - far.rgb.int()).abs()
    assert diff.float().mean() < 0.5
    assert (diff.amax(-1) > 1).float().mean() <= 0.005
    assert (ref.segmentation == far.segmentation).float().mean() >= 0.995
    both = torch.isfinite(ref.depth) & torch.isfinite(far.depth)
    assert (torch.isfinite(ref.depth) == torch.isfinite(far.depth)).float().mean() >= 0.995
    rel = ((ref.depth - far.depth).abs() / ref.depth)[both]
    assert torch.quantile(rel, 0.99) < 1e-3


@pytest.mark.parametrize("kind", ["static", "dynamic"])
def test_close_up_far_from_origin_keeps_sub_centimetre_precision(kind):
    """A post 3 cm off a float32-representable coordinate, seen from 30 cm (1 px ~ 1.3 cm):
    plain float32 positions at 1e6 m (ulp 6 cm) would move its edges by ~2 px on every row.
    Same tolerance as above: at most 0.5% of pixels differ by more than 1."""
    images = []
    for offset in ((0.0, 0.0, 0.0), (1e6, -1e6, 0.0)):
        off = torch.tensor(offset, dtype=F64)
        post = torch.tensor([[0.03, 0.4, 0.0]], dtype=F64) + off
        scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=(32, 32), effects=(), near=0.01)
        if kind == "static":
            scene.add_static("post", "box", position=post, scale=[[0.1, 0.1, 2.0]], color=[[0.9, 0.2, 0.2]])
        else:
            scene.add_group("post", "box", capacity=1)
        r = mr.BatchRenderer(scene)
        if kind == "dynamic":
            r.update("post", position=post[None], scale=torch.tensor([[[0.1, 0.1, 2.0]]]),
                     color=torch.tensor([[[0.9, 0.2, 0.2]]]), active=ones(1, 1))
        r.set_cameras(position=off.expand(1, 1, 3), rotation=IDENTITY.expand(1, 1, 4))
        images.append(r.render().rgb[0, 0])
        r.close()
    covered = (images[0] != background_rgb(scene)).any(-1)
    assert 4 * 32 <= covered.sum() <= 16 * 32  # the post is on screen, edges inside the view
    assert (max_channel_diff(images[0], images[1]) > 1).float().mean() <= 0.005


def test_per_world_origins_and_recentring_between_renders():
    """World 0 at the origin and world 1 a million metres away render the same image in one
    renderer; swapping them between renders (the world origins move) changes nothing."""
    scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=(32, 40), effects=("lighting",))
    scene.add_group("boxes", "box", capacity=3)
    r = mr.BatchRenderer(scene)
    local = torch.tensor([[0.0, 3.0, 0.0], [1.0, 5.0, 0.5], [-1.2, 4.0, -0.4]], dtype=F64)
    eye_local = torch.tensor([0.3, 0.0, 0.8], dtype=F64)
    far = torch.tensor([1e6, -1e6, 20.0], dtype=F64)
    rotation = mr.quat_from_yaw_pitch_roll(torch.tensor([0.2, 0.9, -0.7])).expand(2, 3, 4)
    r.update("boxes", rotation=rotation,
             color=torch.tensor([[1, 0.2, 0.2], [0.2, 0.2, 1], [0.9, 0.8, 0.1]]).expand(2, 3, 3),
             active=ones(2, 3))

    def place(offsets):
        r.update("boxes", position=torch.stack([local + o for o in offsets]))
        eyes = torch.stack([eye_local + o for o in offsets])[:, None]
        r.set_cameras(position=eyes, look_at=eyes + torch.tensor([0.0, 1.0, -0.1], dtype=F64))
        return r.render().rgb[:, 0]

    zero = torch.zeros(3, dtype=F64)
    first = place([zero, far])
    assert (first[0] != background_rgb(scene)).any(-1).sum() > 50
    assert (max_channel_diff(first[0], first[1]) > 1).float().mean() <= 0.005
    second = place([far, zero])
    assert (max_channel_diff(second[0], first[0]) > 1).float().mean() <= 0.005
    assert (max_channel_diff(second[1], first[0]) > 1).float().mean() <= 0.005
    r.close()


def test_renderer_normalises_quaternions_and_rejects_zero_ones():
    """k * q renders exactly like q (instances and cameras); a zero quaternion raises a
    ValueError naming `rotation` and leaves the stored state unchanged."""
    scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=(24, 24), effects=("lighting",))
    scene.add_group("boxes", "box", capacity=1)
    r = mr.BatchRenderer(scene)
    q_box = mr.quat_from_yaw_pitch_roll(torch.tensor(0.5), torch.tensor(0.3), torch.tensor(-0.2))
    q_cam = mr.quat_from_yaw_pitch_roll(torch.tensor(0.1), torch.tensor(-0.15))
    r.update("boxes", position=torch.tensor([[[0.2, 3.0, -0.3]]] * 2),
             rotation=torch.stack((q_box, -3.7 * q_box))[:, None],
             color=torch.tensor([0.9, 0.5, 0.1]).expand(2, 1, 3), active=ones(2, 1))
    r.set_cameras(position=torch.zeros(2, 1, 3), rotation=torch.stack((q_cam, 0.02 * q_cam))[:, None])
    rgb = r.render().rgb
    assert (rgb[0] != background_rgb(scene)).any(-1).sum() > 20
    assert torch.equal(rgb[0], rgb[1])

    before = r.instance_state("boxes")
    bad = torch.stack((q_box, torch.zeros(4)))[:, None]
    with pytest.raises(ValueError, match="rotation"):
        r.update("boxes", rotation=bad, position=torch.ones(2, 1, 3))
    with pytest.raises(ValueError, match="rotation"):
        r.set_cameras(rotation=bad)
    after = r.instance_state("boxes")
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert torch.equal(r.render().rgb, rgb)
    r.close()


# ----------------------------------------------------------------------------- near / far
RED, BLUE = torch.tensor([255, 0, 0], dtype=torch.uint8), torch.tensor([0, 0, 255], dtype=torch.uint8)


def render_quad_pairs(effects, distances, near, far, separation=1e-3, per_camera=False):
    """World i: a camera at the origin looking +Y; a large blue quad at d * (1 + separation),
    drawn first, and a small red quad at d in front of it. The red must cover the centre."""
    W = len(distances)
    scene_near, scene_far = (0.05, 100.0) if per_camera else (near[0], far[0])
    scene = mr.Scene(num_worlds=W, agents_per_world=1, resolution=(16, 16), effects=effects,
                     near=scene_near, far=scene_far)
    scene.add_group("quads", "plane", capacity=2)
    r = mr.BatchRenderer(scene)
    d = torch.tensor(distances, dtype=F64)
    position = torch.zeros(W, 2, 3, dtype=F64)
    position[:, 0, 1] = d * (1 + separation)  # far quad is instance 0: drawn before the near one
    position[:, 1, 1] = d
    scale = torch.stack((2.0 * d, 0.5 * d), -1)[..., None].expand(W, 2, 3)
    r.update("quads", position=position, rotation=FACING_CAMERA.expand(W, 2, 4), scale=scale,
             color=torch.tensor([[0.0, 0, 1], [1, 0, 0]]).expand(W, 2, 3), active=ones(W, 2))
    r.set_cameras(position=torch.zeros(W, 1, 3), rotation=IDENTITY.expand(W, 1, 4))
    if per_camera:
        r.set_cameras(near=torch.tensor(near, dtype=F64)[:, None], far=torch.tensor(far, dtype=F64)[:, None])
    frame = r.render()
    r.close()
    return frame


def assert_near_quad_wins(frame, distances):
    rgb = frame.rgb[:, 0]
    for i, d in enumerate(distances):
        centre = rgb[i, 6:10, 6:10]
        assert (centre == RED).all(), f"distance {d}: near quad lost the depth test: {centre.reshape(-1, 3).tolist()}"
        corners = rgb[i, [0, 0, -1, -1], [0, -1, 0, -1]]
        assert (corners == BLUE).all(), f"distance {d}: far quad missing (clipped?): {corners.tolist()}"
        if frame.depth is not None:
            assert torch.allclose(frame.depth[i, 0, 6:10, 6:10], torch.tensor(float(d)), rtol=0.01)


def _across(near, far):
    return [2 * near, 30 * near, math.sqrt(near * far), far / 30, 0.9 * far]


@pytest.mark.parametrize("near,far", [(0.1, 100.0), (1e-2, 1e3), (1e-3, 1e4)], ids=["1e3", "1e5", "1e7"])
def test_log_depth_orders_quads_a_thousandth_apart_across_the_range(near, far):
    """far/near from 1e3 to 1e7 with log_depth: quads a 1e-3 fraction of their distance apart
    (1e-3 ... ~10 metres) are ordered correctly at 5 distances from 2*near to 0.9*far."""
    distances = _across(near, far)
    frame = render_quad_pairs(("log_depth", "depth"), distances, [near], [far])
    assert_near_quad_wins(frame, distances)


def test_log_depth_uses_each_cameras_own_near_far():
    """near/far set per camera (set_cameras) reach the log-depth shader per view."""
    near = [1e-3, 0.1, 1.0]
    far = [1e4, 100.0, 1e4]
    distances = [5e-3, 90.0, 5000.0]
    frame = render_quad_pairs(("log_depth",), distances, near, far, per_camera=True)
    assert_near_quad_wins(frame, distances)


def test_without_log_depth_moderate_ratio_is_correct():
    """Plain 24-bit depth at near 0.05, far 100 (ratio 2e3) resolves a 1e-3 relative gap
    from 0.1 m to 90 m. (At ratio 1e7 it cannot beyond ~100 m: that is what log_depth is for.)"""
    distances = [0.1, 1.0, 10.0, 50.0, 90.0]
    frame = render_quad_pairs(("depth",), distances, [0.05], [100.0])
    assert_near_quad_wins(frame, distances)


# ----------------------------------------------------------------------------- extreme scales
def test_zero_tiny_and_huge_scales():
    """One box per world, 5 m ahead (its near face at 5 m for the huge one), over a huge
    static floor: zero and 1e-6 scales are invisible (pixels identical to a render with no
    instances), a 1e6 box covers the whole view in its face colour, nothing is NaN."""
    scales = [[0.0, 0.0, 0.0], [1e-6] * 3, [1.0, 1.0, 1.0], [1e6] * 3]
    centres = [[0.0, 5.0, 0.0], [0.0, 5.0, 0.0], [0.0, 5.5, 0.0], [0.0, 5.0 + 5e5, 0.0]]
    W = len(scales)
    scene = mr.Scene(num_worlds=W, agents_per_world=1, resolution=(32, 32), effects=("lighting", "depth"))
    scene.add_static("floor", "plane", position=[[0.0, 0.0, -10.0]], scale=[[1e6, 1e6, 1.0]], color=[[0.3, 0.6, 0.3]])
    scene.add_group("boxes", "box", capacity=1)
    r = mr.BatchRenderer(scene)
    r.set_cameras(position=torch.zeros(W, 1, 3), rotation=IDENTITY.expand(W, 1, 4))
    r.update("boxes", position=torch.tensor(centres, dtype=F64)[:, None], scale=torch.tensor(scales)[:, None],
             color=torch.tensor([0.9, 0.1, 0.1]).expand(W, 1, 3), active=ones(W, 1))
    empty = None
    frame = r.render()
    r.update("boxes", active=torch.zeros(W, 1, dtype=torch.bool))
    empty = r.render()
    r.close()
    assert not frame.depth.isnan().any() and not empty.depth.isnan().any()
    assert (frame.depth > 0).all()

    # The huge floor 10 m below: upper half background (inf); from row 18 down (ray hits it
    # closer than far = 100 m) floor, all the way to the tile's edges.
    bg = background_rgb(scene)
    assert (empty.rgb[:, 0, :16] == bg).all() and torch.isinf(empty.depth[:, 0, :16]).all()
    assert (empty.rgb[:, 0, 18:] != bg).any(-1).all() and torch.isfinite(empty.depth[:, 0, 18:]).all()

    for i in (0, 1):  # zero and tiny: invisible
        assert torch.equal(frame.rgb[i], empty.rgb[i]), scales[i]
        assert torch.equal(frame.depth[i], empty.depth[i]), scales[i]
    unit_face = frame.rgb[2, 0, 16, 16]
    assert (frame.rgb[2] == unit_face).all(-1).sum() >= 16  # the unit box is visible
    assert (frame.rgb[3, 0] == unit_face).all(), "huge box must cover the view in its face colour"
    assert torch.allclose(frame.depth[3, 0], torch.tensor(5.0), rtol=0.01)


def test_flattened_box_is_lit_like_a_very_thin_one():
    W = 2
    scene = mr.Scene(num_worlds=W, agents_per_world=1, resolution=(16, 16), effects=("lighting",))
    scene.add_group("boxes", "box", capacity=1)
    r = mr.BatchRenderer(scene)
    r.set_cameras(position=torch.zeros(W, 1, 3), rotation=IDENTITY.expand(W, 1, 4))
    r.update("boxes", position=torch.tensor([[[0.0, 3.0, 0.0]]] * W, dtype=F64),
             scale=torch.tensor([[[1.0, 0.0, 1.0]], [[1.0, 1e-6, 1.0]]]),
             color=torch.tensor([0.9, 0.5, 0.1]).expand(W, 1, 3), active=ones(W, 1))
    rgb = r.render().rgb[:, 0, 8, 8]
    r.close()
    assert (rgb[1] != background_rgb(scene)).any()
    assert max_channel_diff(rgb[0], rgb[1]) <= 1, rgb.tolist()


def test_negative_scale_is_rejected_and_changes_nothing():
    """A mirrored instance would reverse its winding and be culled inside out, so negative
    scales are refused (naming the argument) instead of rendering the wrong faces."""
    W = 2
    scene = mr.Scene(num_worlds=W, agents_per_world=1, resolution=(16, 16), effects=("lighting", "depth"))
    scene.add_group("boxes", "box", capacity=1)
    r = mr.BatchRenderer(scene)
    before = r.instance_state("boxes")
    with pytest.raises(ValueError, match=r"scale must be >= 0.0, got minimum -1.0"):
        r.update("boxes", position=torch.tensor([[[0.0, 3.0, 0.0]]] * W, dtype=F64),
                 scale=torch.tensor([[[1.0, -1.0, 1.0]], [[1.0, 1.0, 1.0]]]), active=ones(W, 1))
    after = r.instance_state("boxes")
    r.close()
    assert all(torch.equal(before[k], after[k]) for k in before)
    with pytest.raises(ValueError, match=r"scale must be >= 0"):
        scene.add_static("mirrored", "box", position=[[0, 0, 0]], scale=[[1, -1, 1]])


# ----------------------------------------------------------------------------- depth accuracy
def test_depth_of_a_box_face_at_a_known_distance():
    """Depth is metres along the view axis: a face perpendicular to it reads its distance on
    every pixel (to 1%; llvmpipe gets ~1e-6), and the background reads +inf."""
    distances = [0.5, 3.0, 40.0]
    W = len(distances)
    scene = mr.Scene(num_worlds=W, agents_per_world=1, resolution=(24, 32), effects=("depth",))
    scene.add_group("boxes", "box", capacity=1)
    r = mr.BatchRenderer(scene)
    r.set_cameras(position=torch.zeros(W, 1, 3), rotation=IDENTITY.expand(W, 1, 4))
    d = torch.tensor(distances, dtype=F64)
    # Box face at y = d, 0.4 d wide: well inside the view, not touching the tile edge.
    size = 0.4 * d
    position = torch.stack((torch.zeros_like(d), d + size / 2, torch.zeros_like(d)), -1)[:, None]
    r.update("boxes", position=position, scale=size[:, None, None].expand(W, 1, 3),
             color=torch.tensor([0.9, 0.1, 0.1]).expand(W, 1, 3), active=ones(W, 1))
    frame = r.render()
    r.close()
    bg = (frame.rgb == background_rgb(scene)).all(-1)
    for i, dist in enumerate(distances):
        covered = ~bg[i, 0]
        assert covered.sum() >= 16
        assert torch.allclose(frame.depth[i, 0][covered], torch.tensor(dist, dtype=torch.float32), rtol=0.01)
        assert torch.equal(frame.depth[i, 0][~covered], torch.full_like(frame.depth[i, 0][~covered], math.inf))
        assert bool(covered[12, 16]) and not bool(covered[0, 0])


def test_depth_of_a_tilted_floor_matches_ray_intersection_per_pixel():
    """Camera 2 m above a floor, pitched 15 degrees down: each pixel's depth equals the analytic
    ray-plane intersection (along the view axis) within 1%; rows above the horizon are +inf.
    Also pins the pixel layout: row 0 is the top of the image, column 0 the left."""
    H, Wpx = 24, 32
    fov = math.radians(60.0)
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=(H, Wpx), effects=("depth",), fov_y=fov, far=1000.0)
    scene.add_static("floor", "plane", position=[[0.0, 0.0, 0.0]], scale=[[2000.0, 2000.0, 1.0]])
    r = mr.BatchRenderer(scene)
    eye = torch.tensor([[[0.0, 0.0, 2.0]]], dtype=F64)
    rotation = mr.quat_from_yaw_pitch_roll(torch.tensor(0.4, dtype=F64), torch.tensor(math.radians(-15.0), dtype=F64))
    r.set_cameras(position=eye, rotation=rotation.expand(1, 1, 4))
    depth = r.render().depth[0, 0].double()
    r.close()

    tan = math.tan(fov / 2)
    x = ((torch.arange(Wpx, dtype=F64) + 0.5) / Wpx * 2 - 1) * tan * Wpx / H
    z = (1 - (torch.arange(H, dtype=F64) + 0.5) / H * 2) * tan
    rays = torch.stack(torch.broadcast_tensors(x[None, :], torch.ones(H, Wpx, dtype=F64), z[:, None]), -1)
    world = rays @ T.quat_to_matrix(rotation).T
    t = -2.0 / world[..., 2]  # depth along the view axis: the camera-frame ray has y = 1
    hit = (world[..., 2] < 0) & (t < 900)
    clear = (world[..., 2] > 0.02) | ((world[..., 2] < 0) & (t < 500))  # away from the horizon
    assert hit.sum() > H * Wpx // 3 and (~hit).sum() > H * Wpx // 10
    assert torch.allclose(depth[hit & clear], t[hit & clear], rtol=0.01)
    assert torch.isinf(depth[~hit & clear]).all()


def test_look_at_straight_down_renders_with_world_y_up_in_the_image():
    """A camera looking exactly down (look_at degenerate case) is a valid view: the target is in
    the centre, +Y world is image-up (limit of yaw 0), and a nearly-straight-down view matches."""
    scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=(32, 32), effects=())
    scene.add_group("boxes", "box", capacity=3)
    r = mr.BatchRenderer(scene)
    r.update("boxes",
             position=torch.tensor([[0.0, 0.0, 0.0], [0.0, 2.5, 0.0], [2.5, 0.0, 0.0]], dtype=F64).expand(2, 3, 3),
             color=torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).expand(2, 3, 3), active=ones(2, 3))
    eye = torch.tensor([0.0, 0.0, 10.0], dtype=F64).expand(2, 1, 3)
    target = torch.tensor([[[0.0, 0.0, 0.0]], [[0.0, 1e-4, 0.0]]], dtype=F64)
    r.set_cameras(position=eye, look_at=target)
    rgb = r.render().rgb[:, 0]
    r.close()
    green, red, blue = (torch.tensor(c, dtype=torch.uint8) for c in ([0, 255, 0], [255, 0, 0], [0, 0, 255]))
    image = rgb[0]
    assert (image[15:17, 15:17] == green).all()
    red_rows = (image == red).all(-1).nonzero()[:, 0]
    blue_cols = (image == blue).all(-1).nonzero()[:, 1]
    assert len(red_rows) and red_rows.float().mean() < 12, "world +Y should be towards the top of the image"
    assert len(blue_cols) and blue_cols.float().mean() > 20, "world +X should be to the right"
    assert (max_channel_diff(rgb[0], rgb[1]) > 0).float().mean() <= 0.01
