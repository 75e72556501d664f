"""The batch renderer draws the right pixels in the right tiles."""
import ctypes
import ctypes.util
import math

import numpy as np
import pytest
import torch

import marl_render as mr
from marl_render.bench.naive import NaiveRenderer

BACKGROUND = (0.2, 0.4, 0.6)
BACKGROUND_U8 = torch.tensor([round(c * 255) for c in BACKGROUND], dtype=torch.uint8)


def box_scene(worlds=1, agents=1, resolution=(48, 64), capacity=1, effects=(), **kw):
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=resolution, effects=effects,
                     background=BACKGROUND, **kw)
    scene.add_group("boxes", "box", capacity=capacity)
    return scene


def cameras_at_origin(renderer, worlds, agents):
    """Every camera at the origin looking down +Y."""
    renderer.set_cameras(position=torch.zeros(worlds, agents, 3),
                         rotation=torch.tensor([1.0, 0, 0, 0]).repeat(worlds, agents, 1))


def is_background(image):
    return (image == BACKGROUND_U8).all(dim=-1)


def test_box_projects_where_a_pinhole_camera_puts_it():
    H, W = 48, 64
    fov = math.radians(60)
    scene = box_scene(worlds=2, agents=3, resolution=(H, W), fov_y=fov)
    with mr.BatchRenderer(scene) as renderer:
        cameras_at_origin(renderer, 2, 3)
        position = torch.zeros(2, 1, 3)
        position[1, 0] = torch.tensor([0.3, 4.0, -0.2])  # only world 1 has a visible box ...
        position[0, 0] = torch.tensor([0.0, -10.0, 0.0])  # ... world 0's is behind its cameras
        renderer.update("boxes", position=position, color=torch.tensor([[[1.0, 0.0, 0.0]]]).repeat(2, 1, 1),
                        active=torch.ones(2, 1, dtype=torch.bool))
        rgb = renderer.render().rgb

    # Analytic projection of the front face (y = 3.5) of the unit box centred at (0.3, 4, -0.2).
    focal = (H / 2) / math.tan(fov / 2)
    depth = 3.5
    left, right = W / 2 + (0.3 - 0.5) / depth * focal, W / 2 + (0.3 + 0.5) / depth * focal
    top, bottom = H / 2 - (-0.2 + 0.5) / depth * focal, H / 2 - (-0.2 - 0.5) / depth * focal
    cols = torch.arange(W) + 0.5
    rows = torch.arange(H) + 0.5
    inside = ((cols >= left + 1) & (cols <= right - 1))[None, :] & ((rows >= top + 1) & (rows <= bottom - 1))[:, None]
    near_columns = (cols >= left - 1) & (cols <= right + 1)
    near_rows = (rows >= top - 1) & (rows <= bottom + 1)
    outside = ~(near_columns[None, :] & near_rows[:, None])
    for agent in range(3):
        image = rgb[1, agent]
        red = (image == torch.tensor([255, 0, 0], dtype=torch.uint8)).all(-1)
        assert red[inside].all(), f"agent {agent}: box pixels missing inside the projected rectangle"
        assert is_background(image)[outside].all(), f"agent {agent}: colour outside the projected rectangle"
        assert red.sum() > 0.8 * inside.sum()
    assert is_background(rgb[0]).all(), "world 0 sees nothing, its tiles must be pure background"


def clip_distances_enabled_while_drawing(root) -> tuple:
    """(seen, probe): `seen` fills, at each render, with GL_CLIP_DISTANCE0..3 as the GL has them while
    `root`'s draws run (a draw callback under it); remove `probe` (a NodePath) when done."""
    from panda3d.core import CallbackNode, OmniBoundingVolume, PythonCallbackObject

    egl = ctypes.CDLL(ctypes.util.find_library("EGL"))
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    is_enabled = ctypes.CFUNCTYPE(ctypes.c_ubyte, ctypes.c_uint)(egl.eglGetProcAddress(b"glIsEnabled"))
    seen = []

    def probe(data):
        seen.append([bool(is_enabled(0x3000 + plane)) for plane in range(4)])  # GL_CLIP_DISTANCE0 + plane
        data.upcall()

    node = CallbackNode("clip_probe")
    node.set_draw_callback(PythonCallbackObject(probe))
    node.set_bounds(OmniBoundingVolume())
    probe_path = root.attach_new_node(node)
    probe_path.set_bin("fixed", 1 << 20)  # after the batch's own draws, in their state
    return seen, probe_path


def test_the_tiles_clip_distances_are_enabled_in_the_gl():
    """The shaders clip each view to its tile with gl_ClipDistance, which the GL applies only where
    GL_CLIP_DISTANCEi is enabled: llvmpipe clips regardless, the NVIDIA driver does not (every
    world's tiles showed world 1's huge box there). Asked of the GL itself, since llvmpipe's pixels
    cannot tell."""
    scene = box_scene(worlds=2, agents=1, resolution=(16, 16), effects=("lighting", "shadows"),
                      shadows=mr.Shadows(resolution=64, bounds=((-4.0, -4.0, 0.0), (4.0, 4.0, 2.0))))
    with mr.BatchRenderer(scene) as renderer:
        cameras_at_origin(renderer, 2, 1)
        renderer.update("boxes", position=[[[0.0, 4.0, 0.0]]] * 2, active=[[True]] * 2)
        (views, view_probe), (shadows, shadow_probe) = (clip_distances_enabled_while_drawing(renderer._passes[0].root),
                                                        clip_distances_enabled_while_drawing(renderer.shadow_pass.root))
        renderer.render()
        view_probe.remove_node()
        shadow_probe.remove_node()
    assert views == [[True, True, False, False]], "views: the tile's top and bottom planes"
    assert shadows == [[True, True, True, True]], "shadow atlas: all four sides of each world's square"


def render_leak_scene(resolution, worlds, agents):
    """RGB of the scenes below (tools/gpu_kit/renderer_probe.py measures the same scenes on a GPU)."""
    scene = box_scene(worlds=worlds, agents=agents, resolution=resolution, capacity=1)
    with mr.BatchRenderer(scene) as renderer:
        assert renderer.layout.columns * renderer.layout.rows >= worlds * agents
        cameras_at_origin(renderer, worlds, agents)
        # Each world's box sits behind all of its cameras, except in world 1 where it is
        # enormous and straddles the cameras' frusta in every direction.
        position = torch.zeros(worlds, 1, 3)
        position[:, 0, 1] = -50.0
        position[1, 0] = torch.tensor([0.0, 30.0, 0.0])
        scale = torch.ones(worlds, 1, 3)
        scale[1, 0] = torch.tensor([400.0, 2.0, 400.0])
        renderer.update("boxes", position=position, scale=scale, active=torch.ones(worlds, 1, dtype=torch.bool),
                        color=torch.tensor([0.0, 1.0, 0.0]).repeat(worlds, 1, 1))
        return renderer.render().rgb


@pytest.mark.parametrize("resolution,worlds,agents", [((24, 40), 3, 2), ((40, 24), 2, 3), ((32, 32), 5, 1)])
def test_geometry_never_leaks_into_neighbouring_tiles(resolution, worlds, agents):
    """A huge box right in front of one camera fills that view only."""
    rgb = render_leak_scene(resolution, worlds, agents)
    green = (rgb == torch.tensor([0, 255, 0], dtype=torch.uint8)).all(-1)
    assert green[1].all(), "the huge box must fill every view of world 1"
    others = [w for w in range(worlds) if w != 1]
    assert is_background(rgb[others]).all(), "another world's tile was coloured"


def test_aspect_ratio_follows_the_tile():
    """A sphere seen head-on is as wide as it is tall in pixels, in a non-square tile."""
    H, W = 40, 80
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=(H, W), effects=(), background=BACKGROUND)
    scene.add_group("ball", mr.sphere(segments=48, rings=24), capacity=1)
    with mr.BatchRenderer(scene) as renderer:
        cameras_at_origin(renderer, 1, 1)
        renderer.update("ball", position=[[[0.0, 3.0, 0.0]]], scale=[[[1.5, 1.5, 1.5]]],
                        active=[[True]], color=[[[1.0, 1.0, 0.0]]])
        mask = ~is_background(renderer.render().rgb[0, 0])
    rows = mask.any(dim=1).nonzero()
    cols = mask.any(dim=0).nonzero()
    height = rows.max() - rows.min() + 1
    width = cols.max() - cols.min() + 1
    assert abs(int(height) - int(width)) <= 1, (height, width)


def random_scene_inputs(generator, worlds, agents, capacity):
    position = torch.rand(worlds, capacity, 3, generator=generator) * 4 - 2
    position[..., 1] += 3
    position[..., 2] = torch.rand(worlds, capacity, generator=generator) + 0.2
    rotation = mr.quat_from_yaw_pitch_roll(*(torch.rand(3, worlds, capacity, generator=generator) * 3))
    scale = torch.rand(worlds, capacity, 3, generator=generator) * 0.8 + 0.3
    color = torch.rand(worlds, capacity, 3, generator=generator)
    active = torch.rand(worlds, capacity, generator=generator) > 0.2
    camera = torch.zeros(worlds, agents, 3)
    camera[..., 0] = torch.linspace(-1.5, 1.5, agents)
    camera[..., 2] = 1.0 + torch.rand(worlds, agents, generator=generator)
    target = torch.zeros(worlds, agents, 3)
    target[..., 1] = 3.0
    return dict(position=position, rotation=rotation, scale=scale, color=color, active=active), camera, target


def render_batched_and_plain(seed):
    """RGB of one random lit scene, drawn by the batch renderer and by the plain Panda3D way."""
    worlds, agents, capacity = 2, 3, 5
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=(36, 48), effects=("lighting",),
                     background=BACKGROUND)
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[30, 30, 1], color=[0.3, 0.6, 0.3])
    scene.add_group("boxes", "box", capacity=capacity)
    instances, camera, target = random_scene_inputs(torch.Generator().manual_seed(seed), worlds, agents, capacity)
    images = []
    for cls in (mr.BatchRenderer, NaiveRenderer):
        renderer = cls(scene)
        renderer.update("boxes", **instances)
        renderer.set_cameras(position=camera, look_at=target)
        images.append(renderer.render().rgb)
        renderer.close()
    return images


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_the_plain_panda3d_way(seed):
    images = [image.float() for image in render_batched_and_plain(seed)]
    error = (images[0] - images[1]).abs().mean(dim=(0, 1, 2, 3))
    assert (error < 1.0).all(), f"mean absolute error per channel {error.tolist()}"
    assert not is_background(images[0].to(torch.uint8)).all(), "nothing was drawn"


def test_owner_is_hidden_from_its_own_camera_only():
    scene = mr.Scene(num_worlds=1, agents_per_world=2, resolution=(32, 32), effects=(), background=BACKGROUND)
    scene.add_group("bodies", "box", capacity=2)
    scene.mount_cameras("bodies", [0, 1], offset=(0.0, 0.0, 0.0))
    with mr.BatchRenderer(scene) as renderer:
        # Two big bodies face each other 3 m apart: each camera sits inside its own body.
        renderer.update("bodies", position=[[[0.0, 0.0, 0.0], [0.0, 3.0, 0.0]]],
                        rotation=mr.quat_from_yaw_pitch_roll(torch.tensor([[0.0, math.pi]])),
                        scale=torch.full((1, 2, 3), 1.5), active=torch.ones(1, 2, dtype=torch.bool),
                        color=[[[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])
        rgb = renderer.render().rgb
        red = torch.tensor([255, 0, 0], dtype=torch.uint8)
        blue = torch.tensor([0, 0, 255], dtype=torch.uint8)
        # Agent 0 sees agent 1's blue body in the middle and none of its own red.
        assert (rgb[0, 0, 16, 16] == blue).all()
        assert not (rgb[0, 0] == red).all(-1).any()
        assert (rgb[0, 1, 16, 16] == red).all()
        assert not (rgb[0, 1] == blue).all(-1).any()
        # Without owner hiding agent 0's view is filled by the inside of its own body (culled
        # back faces leave background) -- so make the owners explicit to check the switch.
        renderer.update("bodies", owner=torch.tensor([[1, 0]]))
        swapped = renderer.render().rgb
        assert not (swapped[0, 0] == blue).all(-1).any(), "agent 0 now owns the blue body and must not see it"


def test_depth_is_linear_metres_within_one_percent():
    scene = box_scene(resolution=(32, 32), effects=("depth",))
    with mr.BatchRenderer(scene) as renderer:
        cameras_at_origin(renderer, 1, 1)
        renderer.update("boxes", position=[[[0.0, 5.5, 0.0]]], scale=[[[3.0, 1.0, 3.0]]], active=[[True]])
        frame = renderer.render()
    depth = frame.depth[0, 0]
    assert frame.depth.dtype == torch.float32 and frame.depth.shape == (1, 1, 32, 32)
    face = depth[12:20, 12:20]
    assert torch.allclose(face, torch.full_like(face, 5.0), rtol=0.01)
    assert torch.isinf(depth[0, 0]) and depth[0, 0] > 0, "background depth is +inf"


def render_segmentation_scene():
    """(segmentation, the boxes' ids, the floor's id, which boxes are active, the boxes' centre columns)."""
    scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=(32, 64), effects=("segmentation",),
                     background=BACKGROUND)
    scene.add_static("floor", "plane", position=[0, 0, -1], scale=[50, 50, 1])
    scene.add_group("boxes", "box", capacity=3)
    ids = list(scene.segment_ids("boxes"))
    floor_id = scene.segment_ids("floor")[0]
    with mr.BatchRenderer(scene) as renderer:
        cameras_at_origin(renderer, 2, 1)
        position = torch.tensor([[-1.2, 4.0, 0.0], [0.0, 4.0, 0.0], [1.2, 4.0, 0.0]]).repeat(2, 1, 1)
        active = torch.tensor([[True, True, True], [True, False, True]])
        renderer.update("boxes", position=position, scale=torch.full((2, 3, 3), 0.8), active=active)
        seg = renderer.render().segmentation
    centre_cols = [64 // 2 + round(x / 3.6 * (16 / math.tan(scene.fov_y / 2))) for x in (-1.2, 0.0, 1.2)]
    return seg, ids, floor_id, active, centre_cols


def test_segmentation_ids_are_exact():
    seg, ids, floor_id, active, centre_cols = render_segmentation_scene()
    assert seg.dtype == torch.int32 and seg.shape == (2, 1, 32, 64)
    for world in range(2):
        for index, col in enumerate(centre_cols):
            expected = ids[index] if bool(active[world, index]) else 0
            assert int(seg[world, 0, 16, col]) == expected
    assert int(seg[0, 0, 0, 0]) == 0, "sky is background"
    assert int(seg[0, 0, 31, 0]) == floor_id, "floor below the horizon"
    assert set(seg.unique().tolist()) <= {0, floor_id, *ids}


def render_in_one_pass_and_split(effects, supersample):
    """[(passes, frame)] of one scene drawn in one pass and with its views split over five."""
    worlds, agents, capacity = 3, 3, 4
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=(20, 30), effects=effects,
                     background=BACKGROUND)
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[30, 30, 1], color=[0.3, 0.6, 0.3])
    scene.add_group("boxes", "box", capacity=capacity)
    scene.add_group("balls", "sphere", capacity=1)  # smooth normals: per-fragment lighting
    instances, camera, target = random_scene_inputs(torch.Generator().manual_seed(5), worlds, agents, capacity)
    frames = []
    for max_size in (None, 40 * supersample):
        with mr.BatchRenderer(scene, max_framebuffer_size=max_size, supersample=supersample) as renderer:
            renderer.update("boxes", **instances)
            renderer.update("balls", position=torch.tensor([0.3, 2.5, 0.6]).expand(worlds, 1, 3),
                            active=torch.ones(worlds, 1, dtype=torch.bool))
            renderer.set_cameras(position=camera, look_at=target)
            frames.append((renderer.layout.num_passes, renderer.render()))
    return frames


@pytest.mark.parametrize("effects, supersample", [(("lighting", "depth", "segmentation"), 1),
                                                  (("lighting", "fog", "depth", "log_depth"), 1),
                                                  (("depth",), 2)])
def test_views_split_over_several_passes_match_one_pass(effects, supersample):
    (passes_one, one), (passes_many, many) = render_in_one_pass_and_split(effects, supersample)
    assert passes_one == 1 and passes_many == 5  # 1 x 2 tiles of 30x20 fit in 40x40
    assert torch.equal(one.rgb, many.rgb)
    # Bit for bit: depth comes from each triangle's plane at the pixel's place in its tile,
    # not from values interpolated at absolute framebuffer positions.
    assert torch.isfinite(one.depth).float().mean() > 0.5
    assert torch.equal(one.depth, many.depth)
    if "segmentation" in effects:
        assert torch.equal(one.segmentation, many.segmentation)


@pytest.mark.parametrize("mesh", [mr.meshes.box(), mr.sphere(segments=10, rings=5), mr.meshes.plane()])
def test_every_triangle_gets_its_own_provoking_vertex_carrying_its_corners(mesh):
    from marl_render.triangle_corners import with_triangle_corners

    columns = with_triangle_corners(mesh)
    triangles = columns["triangles"].astype(np.int64)
    last = triangles[:, 2]
    assert len(np.unique(last)) == len(triangles), "two triangles share a provoking vertex"
    positions = columns["vertex"]
    assert np.array_equal(columns["corner_a"][last], positions[triangles[:, 0]])
    assert np.array_equal(columns["corner_b"][last], positions[triangles[:, 1]])
    # The same triangles with the same winding: each one only rotated.
    original = mesh.positions[mesh.triangles]
    for t, triangle in enumerate(positions[triangles]):
        assert any(np.array_equal(np.roll(triangle, shift, axis=0), original[t]) for shift in range(3))
    assert len(positions) <= len(mesh.positions) + len(mesh.triangles)
    for name in ("normal", "texcoord"):
        assert columns[name].shape == (len(positions), 3 if name == "normal" else 2)


CUBE_EGG = """<CoordinateSystem> { Z-up }
<VertexPool> cube {
""" + "".join(f"  <Vertex> {i} {{ {x} {y} {z} }}\n" for i, (x, y, z) in enumerate(
    (x, y, z) for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5))) + """}
""" + "".join(f"<Polygon> {{ <VertexRef> {{ {face} <Ref> {{ cube }} }} }}\n" for face in (
    "0 1 3 2", "4 6 7 5", "0 4 5 1", "2 3 7 6", "0 2 6 4", "1 5 7 3"))


def test_model_file_depth_is_the_same_whatever_the_layout(tmp_path):
    """Meshes from model files take their triangle planes from a geometry shader (procedural
    meshes carry them as vertex attributes): depth is bit-identical too, and agrees with
    the procedural box's."""
    path = tmp_path / "cube.egg"
    path.write_text(CUBE_EGG)
    worlds, agents, capacity = 3, 3, 4
    instances, camera, target = random_scene_inputs(torch.Generator().manual_seed(2), worlds, agents, capacity)
    depths = {}
    for mesh in ("box", str(path)):
        scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=(20, 30), effects=("depth",),
                         background=BACKGROUND)
        scene.add_group("cubes", mesh, capacity=capacity)
        for max_size in (None, 40):
            with mr.BatchRenderer(scene, max_framebuffer_size=max_size) as renderer:
                renderer.update("cubes", **instances)
                renderer.set_cameras(position=camera, look_at=target)
                depths[mesh, max_size] = renderer.render().depth
    model, box = depths[str(path), None], depths["box", None]
    assert torch.equal(model, depths[str(path), 40])
    assert torch.equal(box, depths["box", 40])
    both = torch.isfinite(model)
    assert torch.equal(both, torch.isfinite(box)) and both.float().mean() > 0.05  # the same cube
    assert torch.allclose(model[both], box[both], rtol=1e-4, atol=0)


@pytest.mark.parametrize("options", [{}, {"supersample": 2}])
def test_channels_first_is_a_transpose(options):
    scene = box_scene(resolution=(16, 24))
    frames = []
    for channels_first in (False, True):
        with mr.BatchRenderer(scene, channels_first=channels_first, **options) as renderer:
            cameras_at_origin(renderer, 1, 1)
            renderer.update("boxes", position=[[[0.2, 3.0, 0.1]]], active=[[True]], color=[[[0.9, 0.5, 0.1]]])
            frames.append(renderer.render().rgb)
    assert frames[1].shape == (1, 1, 3, 16, 24)
    assert torch.equal(frames[0].permute(0, 1, 4, 2, 3), frames[1])


def test_returned_frames_are_owned_by_the_caller():
    scene = box_scene()
    with mr.BatchRenderer(scene) as renderer:
        cameras_at_origin(renderer, 1, 1)
        renderer.update("boxes", position=[[[0.0, 3.0, 0.0]]], active=[[True]], color=[[[1.0, 0.0, 0.0]]])
        first = renderer.render().rgb
        kept = first.clone()
        renderer.update("boxes", color=[[[0.0, 0.0, 1.0]]])
        second = renderer.render().rgb
    assert torch.equal(first, kept), "a later render overwrote an earlier frame"
    assert not torch.equal(first, second)


def test_only_changed_groups_are_uploaded_again():
    scene = mr.Scene(num_worlds=2, agents_per_world=2, resolution=16, effects=())
    scene.add_group("a", "box", capacity=2)
    scene.add_group("b", "box", capacity=2)
    with mr.BatchRenderer(scene) as renderer:
        renderer.render()
        stamps = {name: renderer._groups[name].instances.get_image_modified() for name in ("a", "b")}
        renderer.update("a", position=torch.ones(2, 2, 3))
        renderer.render()
        assert renderer._groups["a"].instances.get_image_modified() != stamps["a"]
        assert renderer._groups["b"].instances.get_image_modified() == stamps["b"]


def test_static_geometry_is_stored_once_for_all_worlds():
    scene = mr.Scene(num_worlds=16, agents_per_world=2, resolution=16)
    scene.add_static("pillars", "cylinder", position=[[0, 2, 0], [1, 2, 0], [2, 2, 0]])
    scene.add_group("boxes", "box", capacity=5)
    with mr.BatchRenderer(scene) as renderer:
        texels = {name: draw.instances.get_x_size() for name, draw in renderer._groups.items()}
    assert texels["pillars"] == 3 * 5  # 3 instances x 5 texels, independent of the 16 worlds
    assert texels["boxes"] == 16 * 5 * 4  # one row per world instance, shared by both agents' views


def test_mounted_camera_follows_its_instance():
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=(24, 24), effects=(), background=BACKGROUND)
    scene.add_group("body", "box", capacity=1)
    scene.add_group("target", "box", capacity=1)
    scene.mount_cameras("body", [0], offset=(0.0, 0.0, 0.5))
    with mr.BatchRenderer(scene) as renderer:
        renderer.update("target", position=[[[5.0, 0.0, 0.5]]], active=[[True]], color=[[[1.0, 0.0, 0.0]]])
        renderer.update("body", position=[[[0.0, 0.0, 0.0]]], active=[[True]])
        facing_y = renderer.render().rgb[0, 0]
        # Turn the body -90 degrees (yaw): its +Y axis now points along +X, at the target.
        renderer.update("body", rotation=mr.quat_from_yaw_pitch_roll(torch.tensor([[-math.pi / 2]])))
        facing_x = renderer.render().rgb[0, 0]
    red = torch.tensor([255, 0, 0], dtype=torch.uint8)
    assert not (facing_y == red).all(-1).any()
    assert (facing_x[12, 12] == red).all()


def test_one_buffer_per_view_baseline_matches_the_tiled_one():
    scene = mr.Scene(num_worlds=2, agents_per_world=2, resolution=(16, 24), effects=("lighting",),
                     background=BACKGROUND)
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[30, 30, 1], color=[0.3, 0.6, 0.3])
    scene.add_group("boxes", "box", capacity=3)
    instances, camera, target = random_scene_inputs(torch.Generator().manual_seed(3), 2, 2, 3)
    images = []
    for tiled in (True, False):
        renderer = NaiveRenderer(scene, tiled=tiled)
        renderer.update("boxes", **instances)
        renderer.set_cameras(position=camera, look_at=target)
        images.append(renderer.render().rgb)
        renderer.close()
    assert torch.equal(images[0], images[1])


@pytest.mark.parametrize("antialiasing", [{"supersample": 4}, {"multisamples": 4}])
def test_antialiasing_blends_edges_and_keeps_flat_colours(antialiasing):
    scene = mr.Scene(num_worlds=1, agents_per_world=2, resolution=(24, 32), effects=(), background=(0.0, 0.0, 0.0))
    scene.add_group("box", "box", capacity=1)
    frames = []
    for kwargs in ({}, antialiasing):
        with mr.BatchRenderer(scene, **kwargs) as renderer:
            cameras_at_origin(renderer, 1, 2)
            renderer.update("box", position=[[[0.1, 4.0, 0.05]]], active=[[True]], color=[[[1.0, 1.0, 1.0]]],
                            rotation=mr.quat_from_yaw_pitch_roll(torch.tensor([[0.4]]), torch.tensor([[0.3]])))
            frames.append(renderer.render().rgb[0])
    aliased, smooth = frames
    assert smooth.shape == aliased.shape and smooth.dtype == torch.uint8

    def levels(image):
        return set(image[..., 0].flatten().tolist())

    assert levels(aliased) <= {0, 255}
    assert len(levels(smooth) - {0, 255}) >= 3, "anti-aliased edges must have intermediate values"
    assert torch.equal(smooth[:, 12, 16], aliased[:, 12, 16]), "flat interior unchanged"
    assert (smooth[:, 0, 0] == 0).all(), "background corner unchanged"
    differ = (smooth.int() - aliased.int()).abs().amax(-1) > 0
    assert differ.float().mean() < 0.2, "only edge pixels may change"


def test_supersampled_depth_and_segmentation_take_the_centre_sample():
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=16, effects=("depth", "segmentation"))
    scene.add_group("box", "box", capacity=1)
    with mr.BatchRenderer(scene, supersample=2) as renderer:
        cameras_at_origin(renderer, 1, 1)
        renderer.update("box", position=[[[0.0, 3.5, 0.0]]], active=[[True]])
        frame = renderer.render()
    assert frame.depth.shape == (1, 1, 16, 16) and frame.segmentation.shape == (1, 1, 16, 16)
    assert torch.allclose(frame.depth[0, 0, 8, 8], torch.tensor(3.0), rtol=0.01)
    assert int(frame.segmentation[0, 0, 8, 8]) == scene.segment_ids("box")[0]
    with pytest.raises(ValueError, match="multisamples cannot be combined with the depth"):
        mr.BatchRenderer(scene, multisamples=4)
    with pytest.raises(ValueError, match="supersample must be an int >= 1, got 0"):
        mr.BatchRenderer(scene, supersample=0)


@pytest.mark.parametrize("effects", [("lighting", "fog", "depth", "segmentation"), ("lighting", "log_depth", "depth")])
def test_exact_tiles_draw_every_world_alike_in_any_tile(effects):
    """exact_tiles=True: 20 worlds holding the same scene (a floor under the cameras, which the near
    plane clips; boxes; a ball lit per fragment) give bit-identical colour, depth and segmentation in
    every world's tiles, in one framebuffer and split over several; and the picture is the default
    renderer's (the option changes rounding, not what is drawn)."""
    worlds, agents, capacity = 20, 3, 4
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=(20, 30), effects=effects,
                     background=BACKGROUND)
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[30, 30, 1], color=[0.3, 0.6, 0.3])
    scene.add_group("boxes", "box", capacity=capacity)
    scene.add_group("balls", "sphere", capacity=1)
    instances, camera, target = random_scene_inputs(torch.Generator().manual_seed(7), 1, agents, capacity)
    frames = []
    for exact, max_size in ((True, None), (True, 7 * 20), (False, None)):
        with mr.BatchRenderer(scene, max_framebuffer_size=max_size, exact_tiles=exact) as renderer:
            renderer.update("boxes", **{k: v.expand(worlds, *v.shape[1:]) for k, v in instances.items()})
            renderer.update("balls", position=torch.tensor([0.3, 2.5, 0.6]).expand(worlds, 1, 3),
                            active=torch.ones(worlds, 1, dtype=torch.bool))
            renderer.set_cameras(position=camera.expand(worlds, agents, 3), look_at=target.expand(worlds, agents, 3))
            frames.append((renderer.layout.num_passes, renderer.render()))
    (passes_one, one), (passes_many, many), (_, default) = frames
    assert passes_one == 1 and passes_many == 9  # 7 tiles of 20 rows a framebuffer
    for frame in (one, many):
        for output in ("rgb", "depth", "segmentation"):
            value = getattr(frame, output)
            if value is None:
                continue
            assert torch.equal(value, getattr(one, output)), output
            assert all(torch.equal(value[w], value[0]) for w in range(1, worlds)), output
    assert one.rgb.float().std() > 0 and torch.isfinite(one.depth).float().mean() > 0.3
    differing = (one.rgb != default.rgb).any(-1).float().mean()
    assert differing < 0.01, float(differing)


def test_exact_tiles_must_be_a_bool():
    with pytest.raises(TypeError, match="exact_tiles must be a bool, got"):
        mr.BatchRenderer(mr.Scene(num_worlds=1, agents_per_world=1, resolution=8), exact_tiles="yes")


@pytest.mark.parametrize("impostors", [False, True])
@pytest.mark.parametrize("effects", [("lighting", "fog", "depth", "segmentation"), ("lighting", "log_depth", "depth")])
def test_layered_views_draw_every_world_alike_in_any_slot(effects, impostors):
    """layered=True: every view in its own layer of an array texture. 20 worlds holding the same
    scene (a floor the near plane clips, boxes, a ball lit per fragment, as a mesh or an impostor)
    give bit-identical colour, depth and segmentation in every world, and the same as a batch of 3
    worlds; the column of tiles does not (its world 0 differs from another world in this scene);
    the picture is the column's but for rounding."""
    agents, capacity = 3, 4
    instances, camera, target = random_scene_inputs(torch.Generator().manual_seed(7), 1, agents, capacity)
    frames = {}
    for worlds, layered in ((20, True), (3, True), (20, False)):
        scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=(20, 30), effects=effects,
                         background=BACKGROUND)
        scene.add_static("floor", "plane", position=[0, 0, 0], scale=[30, 30, 1], color=[0.3, 0.6, 0.3])
        scene.add_group("boxes", "box", capacity=capacity)
        scene.add_group("balls", "sphere", capacity=1)
        with mr.BatchRenderer(scene, layered=layered, impostors=impostors) as renderer:
            assert renderer.impostor_groups == (frozenset({"balls"}) if impostors else frozenset())
            renderer.update("boxes", **{k: v.expand(worlds, *v.shape[1:]) for k, v in instances.items()})
            renderer.update("balls", position=torch.tensor([0.3, 2.5, 0.6]).expand(worlds, 1, 3),
                            active=torch.ones(worlds, 1, dtype=torch.bool))
            renderer.set_cameras(position=camera.expand(worlds, agents, 3), look_at=target.expand(worlds, agents, 3))
            frames[worlds, layered] = renderer.render()
    many, few, tiles = frames[20, True], frames[3, True], frames[20, False]
    for output in ("rgb", "depth", "segmentation"):
        value = getattr(many, output)
        if value is None:
            continue
        assert all(torch.equal(value[w], value[0]) for w in range(1, 20)), output
        assert torch.equal(getattr(few, output), value[:3]), output
    assert not all(torch.equal(tiles.rgb[w], tiles.rgb[0]) for w in range(1, 20))
    assert many.rgb.float().std() > 0 and torch.isfinite(many.depth).float().mean() > 0.3
    differing = (many.rgb != tiles.rgb).any(-1).float().mean()
    assert differing < 0.01, float(differing)


def test_layered_must_be_a_bool_and_not_combined_with_exact_tiles():
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8)
    with pytest.raises(TypeError, match="layered must be a bool, got"):
        mr.BatchRenderer(scene, layered="yes")
    with pytest.raises(ValueError, match="layered=True cannot be combined with exact_tiles"):
        mr.BatchRenderer(scene, layered=True, exact_tiles=True)
