"""Sphere impostors (marl_render/render/impostors.py, shaders/impostor.*): the ray-cast sphere's pixels,
depth and segmentation against the analytic sphere, and what they refuse."""
import math

import numpy as np
import pytest
import torch

import marl_render as mr
from marl_render.envs import make_env
from marl_render.render import impostors

RES = 32
CAMERA = (0.0, -4.0, 1.0)  # looking along +y at the sphere's centre
CENTRE = (0.0, 0.0, 1.0)
RADIUS = 0.75  # scale 1.5 of the unit-diameter sphere
RED = (0.9, 0.2, 0.2)


def _render(impostor_mode, effects=("lighting", "depth", "segmentation"), **kwargs):
    scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=RES, effects=effects)
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[10, 10, 1], color=[0.3, 0.5, 0.3])
    scene.add_group("balls", mr.sphere(segments=10, rings=5), capacity=2)
    renderer = mr.BatchRenderer(scene, impostors=impostor_mode, **kwargs)
    try:
        # world 0 sees instance 0 and world 1 instance 1; the other instance is behind the camera
        renderer.update("balls", position=torch.tensor([[CENTRE, (5.0, -8.0, 1.0)], [(0.0, -8.0, 1.0), CENTRE]],
                                                       dtype=torch.float64),
                        scale=torch.full((2, 2, 3), 2 * RADIUS), color=torch.tensor(RED + (1.0,)).expand(2, 2, 4),
                        active=torch.ones(2, 2, dtype=torch.bool))
        renderer.set_cameras(position=torch.tensor([[CAMERA]] * 2, dtype=torch.float64),
                             look_at=torch.tensor([[CENTRE]] * 2, dtype=torch.float64))
        return renderer.impostor_groups, renderer.render(), scene
    finally:
        renderer.close()


def _analytic_depth(scene) -> np.ndarray:
    """[RES, RES] distance along the view axis where each pixel centre's ray meets the sphere (inf: misses)."""
    half = math.tan(scene.fov_y / 2)
    centres = (np.arange(RES) + 0.5) / RES * 2 - 1
    x = centres[None, :] * half  # right: +x
    z = -centres[:, None] * half  # rows top first: +z up
    direction = np.stack(np.broadcast_arrays(x, np.ones_like(x), z), -1)  # forward +y, per unit of view depth
    eye = np.subtract(CAMERA, CENTRE)
    a = (direction ** 2).sum(-1)
    b = (direction * eye).sum(-1)
    disc = b * b - a * (eye @ eye - RADIUS ** 2)
    t = (-b - np.sqrt(np.maximum(disc, 0))) / a
    return np.where(disc >= 0, t, np.inf)  # t is the depth: direction has unit forward component


def test_impostor_depth_and_silhouette_are_the_analytic_sphere():
    chosen, frame, scene = _render(True)
    assert chosen == {"balls"}
    expected = _analytic_depth(scene)
    for world in (0, 1):
        depth = frame.depth[world, 0].numpy()
        sphere = frame.segmentation[world, 0].numpy() == scene.groups["balls"].segment_base + world
        hit = np.isfinite(expected)
        assert (sphere != hit).sum() <= 2  # a pixel centre within float rounding of the silhouette
        both = sphere & hit
        assert both.sum() > 40  # about 4.4 px of radius
        np.testing.assert_allclose(depth[both], expected[both], atol=2e-4)
    # the four centre pixels, half a pixel off the axis: a little beyond the nearest point, 4 - 0.75 m away
    centre = frame.depth[0, 0, RES // 2 - 1:RES // 2 + 1, RES // 2 - 1:RES // 2 + 1]
    assert torch.all(centre > 4 - RADIUS) and torch.all(centre < 4 - RADIUS + 0.01)


def test_impostor_segmentation_colour_and_background():
    _, frame, scene = _render(True)
    seg = frame.segmentation
    base = scene.groups["balls"].segment_base
    assert int(seg[0, 0, RES // 2, RES // 2]) == base + 0  # world 0 sees instance 0
    assert int(seg[1, 0, RES // 2, RES // 2]) == base + 1  # world 1 sees instance 1 (0 is behind its camera)
    assert int(seg[0, 0, 0, 0]) == 0 and torch.isinf(frame.depth[0, 0, 0, 0])  # sky: background
    assert int(seg[0, 0, RES - 1, RES // 2]) == scene.static["floor"].segment_base  # the floor below
    centre = frame.rgb[0, 0, RES // 2, RES // 2].int()
    assert centre[0] > 2 * centre[1] and centre[0] > 2 * centre[2]  # red, lit


@pytest.mark.parametrize("effects", [("lighting",), ("lighting", "depth", "segmentation"),
                                     ("lighting", "appearance"), ("lighting", "fog")])
def test_impostor_is_within_a_level_of_the_fine_mesh(effects):
    """Against a 64-segment sphere mesh: the same picture but for the mesh's facets at the silhouette."""
    def fine(mode):
        scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=RES, effects=effects)
        scene.add_group("balls", mr.sphere(segments=64, rings=32), capacity=1)
        renderer = mr.BatchRenderer(scene, impostors=mode)
        try:
            renderer.update("balls", position=torch.tensor([[CENTRE]], dtype=torch.float64),
                            scale=torch.tensor([[[1.5, 1.5, 2.0]]]), color=torch.tensor([[RED + (1.0,)]]),
                            active=torch.ones(1, 1, dtype=torch.bool))
            renderer.set_cameras(position=torch.tensor([[CAMERA]], dtype=torch.float64),
                                 look_at=torch.tensor([[CENTRE]], dtype=torch.float64))
            return renderer.render()
        finally:
            renderer.close()
    mesh, impostor = fine(False), fine(True)
    error = (mesh.rgb.float() - impostor.rgb.float()).abs()
    assert error.mean() < 0.5 and (error > 8).float().mean() < 0.02
    if mesh.depth is not None:
        both = torch.isfinite(mesh.depth) & torch.isfinite(impostor.depth)
        assert (mesh.depth[both] - impostor.depth[both]).abs().max() < 5e-3


def test_gray_and_supersample_draw_the_impostor():
    _, gray, _ = _render(True, effects=("lighting",), color="gray")
    _, rgb, _ = _render(True, effects=("lighting",), supersample=2)
    assert gray.rgb.shape == (2, 1, RES, RES, 1) and rgb.rgb.shape == (2, 1, RES, RES, 3)
    luma = (rgb.rgb[0, 0, RES // 2, RES // 2].float() * torch.tensor([0.299, 0.587, 0.114])).sum()
    assert abs(float(gray.rgb[0, 0, RES // 2, RES // 2, 0]) - float(luma)) <= 2


@pytest.mark.parametrize("effects, kwargs, reason", [
    (("lighting", "shadows"), {}, "'shadows'"),
    (("lighting",), {"multisamples": 4}, "multisamples"),
    (("lighting",), {"exact_tiles": True}, "exact_tiles"),
])
def test_impostors_true_refuses_what_they_cannot_draw_and_auto_draws_meshes(effects, kwargs, reason):
    with pytest.raises(ValueError, match=f"impostors=True cannot draw the sphere group 'balls': .*{reason}"):
        _render(True, effects=effects, **kwargs)
    chosen, frame, _ = _render("auto", effects=effects, **kwargs)
    assert chosen == frozenset() and frame.rgb.shape[:2] == (2, 1)


def test_textured_spheres_are_refused():
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=("lighting", "texture"))
    scene.add_group("balls", "sphere", capacity=1, texture=np.full((4, 4, 3), 200, np.uint8))
    with pytest.raises(ValueError, match="'texture' effect needs the mesh's uvs"):
        mr.BatchRenderer(scene, impostors=True)


@pytest.mark.parametrize("bad", ["yes", 1, None])
def test_bad_impostors_argument(bad):
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8)
    with pytest.raises(ValueError, match=r"impostors must be one of \[False, True, 'auto'\], got"):
        mr.BatchRenderer(scene, impostors=bad)


def test_only_spheres_are_impostors():
    assert impostors.is_sphere(mr.sphere(segments=10, rings=5)) and impostors.is_sphere(mr.sphere())
    assert not impostors.is_sphere(mr.capsule()) and not impostors.is_sphere(mr.box())
    squashed = mr.sphere()
    squashed = mr.MeshData("sphere", squashed.positions * np.float32([1, 1, 0.5]), squashed.normals, squashed.uvs,
                           squashed.triangles)
    assert not impostors.is_sphere(squashed)


def test_envs_draw_spheres_as_impostors_by_default():
    env = make_env("commons", num_worlds=1, resolution=16)
    meshes = make_env("commons", num_worlds=1, resolution=16, impostors=False)
    try:
        assert env.renderer.impostor_groups == {"apples"} and meshes.renderer.impostor_groups == frozenset()
    finally:
        env.close()
        meshes.close()
    with pytest.raises(ValueError, match="impostors must be one of"):
        make_env("commons", num_worlds=1, resolution=16, impostors="sometimes")


def test_log_depth_impostor_depth_is_the_analytic_sphere():
    chosen, frame, scene = _render(True, effects=("lighting", "depth", "segmentation", "log_depth"))
    assert chosen == {"balls"}
    expected = _analytic_depth(scene)
    sphere = frame.segmentation[0, 0].numpy() == scene.groups["balls"].segment_base
    assert (sphere != np.isfinite(expected)).sum() <= 2
    np.testing.assert_allclose(frame.depth[0, 0].numpy()[sphere], expected[sphere], atol=2e-4)


def test_a_sphere_with_a_floor_role_under_appearance_is_refused():
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=("lighting", "appearance"))
    scene.add_static("dome", "sphere", position=[0, 0, 0], role="floor")
    with pytest.raises(ValueError, match="'dome': floor and wall roles"):
        mr.BatchRenderer(scene, impostors=True)


def test_envs_refuse_impostors_true_with_shadows_and_fall_back_with_auto():
    with pytest.raises(ValueError, match="impostors=True cannot draw the sphere group 'apples': the 'shadows'"):
        make_env("commons", num_worlds=1, resolution=16, shadows=True, impostors=True)
    with make_env("commons", num_worlds=1, resolution=16, shadows=True) as env:
        assert env.renderer.impostor_groups == frozenset()


def _grid_of_spheres(monkeypatch, quads_per_instance):
    """37 spheres (two batches of 16 and 5 more) in a 7 x 6 grid facing each of 3 worlds' cameras."""
    monkeypatch.setattr(impostors, "QUADS_PER_INSTANCE", quads_per_instance)
    scene = mr.Scene(num_worlds=3, agents_per_world=1, resolution=64, effects=("lighting", "segmentation"))
    scene.add_group("balls", mr.sphere(segments=10, rings=5), capacity=37)
    column, row = np.meshgrid(np.arange(7) - 3.0, np.arange(6) - 2.5)
    grid = np.stack([0.6 * column.ravel(), np.zeros(42), 1.0 + 0.6 * row.ravel()], -1)[:37]
    renderer = mr.BatchRenderer(scene, impostors=True)
    try:
        renderer.update("balls", position=torch.tensor(grid, dtype=torch.float64).expand(3, -1, -1),
                        scale=torch.full((3, 37, 3), 0.4), color=torch.tensor(RED + (1.0,)).expand(3, 37, 4),
                        active=torch.ones(3, 37, dtype=torch.bool))
        renderer.set_cameras(position=torch.tensor([[(0.0, -7.0, 1.0)]] * 3, dtype=torch.float64),
                             look_at=torch.tensor([[(0.0, 0.0, 1.0)]] * 3, dtype=torch.float64))
        frame = renderer.render()
        (node, _, drawn, pair_count, batch), = renderer._groups["balls"].pass_nodes
        return frame, scene, (node.get_instance_count(), drawn, pair_count[0], batch)
    finally:
        renderer.close()


def test_impostor_batches_draw_every_pair_and_nothing_past_the_last(monkeypatch):
    """Each GL instance draws QUADS_PER_INSTANCE impostors: every one of 37 spheres (3 worlds) is seen,
    and the frame is the one of a quad per instance, byte for byte."""
    batched, scene, draws = _grid_of_spheres(monkeypatch, 16)
    assert draws == (-(-3 * 37 // 16), 3 * 37, 3 * 37, 16)  # 7 instances for 111 pairs
    ids = batched.segmentation.numpy() - scene.groups["balls"].segment_base
    for world in range(3):
        assert set(np.unique(ids[world, 0])) - {-1 - scene.groups["balls"].segment_base} >= set(range(37))
    single, _, draws = _grid_of_spheres(monkeypatch, 1)
    assert draws == (111, 111, 111, 1)
    assert torch.equal(batched.rgb, single.rgb) and torch.equal(batched.segmentation, single.segmentation)
