"""Bad input to the scene and renderer: a clear error naming the argument, and no change of state."""
import math

import numpy as np
import pytest
import torch

import marl_render as mr

W, A, C = 2, 2, 3


@pytest.fixture(scope="module")
def renderer():
    scene = mr.Scene(num_worlds=W, agents_per_world=A, resolution=(16, 24), effects=("lighting",))
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[10, 10, 1])
    scene.add_group("boxes", "box", capacity=C)
    r = mr.BatchRenderer(scene)
    position = torch.zeros(W, C, 3)
    position[..., 1] = torch.arange(C) + 2.0
    r.update("boxes", position=position, active=torch.ones(W, C, dtype=torch.bool))
    r.set_cameras(position=torch.zeros(W, A, 3) + torch.tensor([0, 0, 1.0]),
                  look_at=torch.zeros(W, A, 3) + torch.tensor([0, 3, 0.0]))
    yield r
    r.close()


GOOD = {
    "position": torch.zeros(W, C, 3),
    "rotation": torch.tensor([1.0, 0, 0, 0]).repeat(W, C, 1),
    "scale": torch.ones(W, C, 3),
    "color": torch.ones(W, C, 4),
    "active": torch.ones(W, C, dtype=torch.bool),
    "owner": torch.full((W, C), -1),
}

BAD_UPDATES = [
    ("position", torch.zeros(W, C, 2), ValueError, r"position must have shape \[2, 3, 3\], got \[2, 3, 2\]"),
    ("position", torch.zeros(W, C + 1, 3), ValueError,
     r"position must have shape \[2, 3, 3\], got \[2, 4, 3\]"),  # over capacity
    ("position", torch.zeros(W, C, 3, dtype=torch.bool), TypeError,
     r"position must have a floating dtype, got torch.bool"),
    ("position", torch.full((W, C, 3), float("nan")), ValueError, r"position must be finite"),
    ("position", torch.full((W, C, 3), float("inf")), ValueError, r"position must be finite"),
    ("position", torch.zeros(W, C, 3, device="meta"), ValueError, r"position must be a CPU tensor.*meta"),
    ("position", "left", TypeError, r"position must be a torch.Tensor or array-like, got str"),
    ("rotation", torch.zeros(W, C, 4), ValueError, r"rotation must be non-zero quaternions"),
    ("rotation", torch.ones(W, C, 3), ValueError, r"rotation must have shape \[2, 3, 4\]"),
    ("scale", torch.full((W, C, 3), float("nan")), ValueError, r"scale must be finite"),
    ("color", torch.full((W, C, 4), 2.0), ValueError, r"color must be <= 1.0, got maximum 2.0"),
    ("color", torch.full((W, C, 4), -0.5), ValueError, r"color must be >= 0.0"),
    ("active", torch.ones(W, C), TypeError, r"active must have dtype torch.bool, got torch.float32"),
    ("active", torch.ones(W, C + 1, dtype=torch.bool), ValueError, r"active must have shape \[2, 3\]"),
    ("owner", torch.full((W, C), A), ValueError, rf"owner must be <= {A - 1}"),
    ("owner", torch.full((W, C), 0.5), TypeError, r"owner must have an integer dtype"),
]


@pytest.mark.parametrize("argument,value,error,message", BAD_UPDATES,
                         ids=[f"{a}-{i}" for i, (a, *_ ) in enumerate(BAD_UPDATES)])
def test_bad_update_raises_and_changes_nothing(renderer, argument, value, error, message):
    before_state = renderer.instance_state("boxes")
    before_image = renderer.render().rgb
    kwargs = {"position": GOOD["position"] + 1.0, argument: value}  # a valid argument alongside must not land either
    if argument == "position":
        kwargs = {"color": GOOD["color"] * 0.5, argument: value}
    with pytest.raises(error, match=message):
        renderer.update("boxes", **kwargs)
    after_state = renderer.instance_state("boxes")
    for key in before_state:
        assert torch.equal(before_state[key], after_state[key]), f"{key} changed by a rejected call"
    assert torch.equal(before_image, renderer.render().rgb)


def test_unknown_group(renderer):
    with pytest.raises(ValueError, match=r"group must be one of this scene's instance groups \['boxes'\], got 'ball'"):
        renderer.update("ball", position=GOOD["position"])
    with pytest.raises(ValueError, match=r"group must be one of this scene's instance groups \['boxes'\], got 'floor'"):
        renderer.instance_state("floor")


BAD_CAMERAS = [
    ({"position": torch.zeros(W, A + 1, 3)}, ValueError, r"position must have shape \[2, 2, 3\]"),
    ({"look_at": torch.full((W, A, 3), float("nan"))}, ValueError, r"look_at must be finite"),
    ({"fov_y": 4.0}, ValueError, r"fov_y must be <= "),
    ({"fov_y": torch.zeros(W, A)}, ValueError, r"fov_y must be >= "),
    ({"near": 10.0, "far": 5.0}, ValueError, r"far must be greater than near"),
    ({"near": torch.ones(3)}, ValueError, r"near must have shape \[2, 2\]"),
    ({"rotation": torch.ones(W, A, 4), "look_at": torch.ones(W, A, 3)}, ValueError, r"either rotation or look_at"),
]


@pytest.mark.parametrize("kwargs,error,message", BAD_CAMERAS)
def test_bad_cameras_raise_and_change_nothing(renderer, kwargs, error, message):
    before = renderer.render().rgb
    state = (renderer.camera_position.clone(), renderer.camera_rotation.clone(), renderer.fov_y.clone(),
             renderer.near.clone(), renderer.far.clone())
    with pytest.raises(error, match=message):
        renderer.set_cameras(**kwargs)
    after = (renderer.camera_position, renderer.camera_rotation, renderer.fov_y, renderer.near, renderer.far)
    assert all(torch.equal(x, y) for x, y in zip(state, after, strict=True))
    assert torch.equal(before, renderer.render().rgb)


@pytest.mark.parametrize("kwargs,error,message", [
    ({"num_worlds": 0}, ValueError, r"num_worlds must be an int >= 1, got 0"),
    ({"num_worlds": 2.5}, TypeError, r"num_worlds must be an int >= 1, got 2.5"),
    ({"agents_per_world": -1}, ValueError, r"agents_per_world must be an int >= 1, got -1"),
    ({"resolution": 0}, ValueError, r"resolution must be >= 1 pixel on each side, got \(0, 0\)"),
    ({"resolution": (32, 32, 3)}, TypeError, r"resolution must be an int or a pair of ints"),
    ({"effects": ("lighting", "bloom")}, ValueError, r"effects must be drawn from .*got unknown \['bloom'\]"),
    ({"effects": "lighting"}, TypeError, r"effects must be a collection of names"),
    ({"near": 0.0}, ValueError, r"near must be a finite number > 0, got 0.0"),
    ({"near": 1.0, "far": 0.5}, ValueError, r"far must be greater than near"),
    ({"fov_y": math.pi}, ValueError, r"fov_y must be in \(0, pi\) radians"),
    ({"background": (2, 0, 0)}, ValueError, r"background must be 3 or 4 numbers in \[0, 1\]"),
    ({"effects": None}, TypeError, r"effects must be a collection of names .*got None"),
    ({"effects": ["lighting", 3]}, TypeError, r"effects must be names \(str\) .*got \[3\]"),
    ({"effects": [["lighting"]]}, TypeError, r"effects must be names \(str\) .*got \[\['lighting'\]\]"),
    ({"background": "red"}, TypeError, r"background must be a sequence of 3 or 4 numbers, got 'red'"),
    ({"background": None}, TypeError, r"background must be a sequence of 3 or 4 numbers, got None"),
    ({"background": ("r", "g", "b")}, TypeError, r"background must be array-like of numbers"),
    ({"background": (0.1, 0.2)}, ValueError, r"background must be 3 or 4 numbers, got \(0.1, 0.2\)"),
    ({"fov_y": "1"}, TypeError, r"fov_y must be a number, got '1'"),
    ({"fov_y": True}, TypeError, r"fov_y must be a number, got True"),
    ({"fov_y": float("nan")}, ValueError, r"fov_y must be a finite number, got nan"),
    ({"far": "100"}, TypeError, r"far must be a number, got '100'"),
    ({"lighting": None}, TypeError, r"lighting must be a marl_render.Lighting, got None"),
    ({"fog": {"density": 1.0}}, TypeError, r"fog must be a marl_render.Fog, got \{'density': 1.0\}"),
])
def test_bad_scene_arguments(kwargs, error, message):
    arguments = dict(num_worlds=1, agents_per_world=1, resolution=16)
    arguments.update(kwargs)
    with pytest.raises(error, match=message):
        mr.Scene(**arguments)


@pytest.mark.parametrize("make,error,message", [
    (lambda: mr.Lighting(direction=(0, 0, 0)), ValueError, r"lighting.direction must be a non-zero vector"),
    (lambda: mr.Lighting(direction="down"), TypeError,
     r"lighting.direction must be a sequence of 3 numbers, got 'down'"),
    (lambda: mr.Lighting(color=(1, 1)), ValueError, r"lighting.color must be 3 numbers, got \(1, 1\)"),
    (lambda: mr.Lighting(ambient=(-0.1, 0, 0)), ValueError, r"lighting.ambient must be 3 numbers >= 0"),
    (lambda: mr.Fog(density=-1.0), ValueError, r"fog.density must be a finite number >= 0, got -1.0"),
    (lambda: mr.Fog(density="thick"), TypeError, r"fog.density must be a number, got 'thick'"),
    (lambda: mr.Fog(color=(2, 0, 0)), ValueError, r"fog.color must be 3 numbers in \[0, 1\], got \(2, 0, 0\)"),
])
def test_bad_lighting_and_fog(make, error, message):
    with pytest.raises(error, match=message):
        make()


def test_lighting_may_be_brighter_than_one():
    assert mr.Lighting(color=[2, 2, 2]).color == (2.0, 2.0, 2.0)


def mount_scene():
    scene = mr.Scene(num_worlds=1, agents_per_world=2, resolution=16)
    scene.add_group("bodies", "box", capacity=3)
    return scene


@pytest.mark.parametrize("kwargs,error,message", [
    ({"pitch": "x"}, TypeError, r"pitch must be a number, got 'x'"),
    ({"pitch": float("inf")}, ValueError, r"pitch must be a finite number, got inf"),
    ({"pitch": None}, TypeError, r"pitch must be a number, got None"),
    ({"instance": [1.7, 0]}, TypeError, r"instance must have an integer dtype, got torch.float64"),
    ({"instance": [1.0, 0.0]}, TypeError, r"instance must have an integer dtype, got torch.float64"),
    ({"instance": [True, False]}, TypeError, r"instance must have an integer dtype, got torch.bool"),
    ({"instance": ["0", "1"]}, TypeError, r"instance must be array-like of numbers"),
    ({"instance": "01"}, TypeError, r"instance must be a torch.Tensor or array-like, got str"),
    ({"instance": [0, 2 ** 70]}, TypeError, r"instance must be array-like of numbers"),
    ({"instance": torch.zeros(2, dtype=torch.int64, device="meta")}, ValueError, r"instance must be a CPU tensor"),
    ({"offset": "abc"}, TypeError, r"offset must be a sequence of 3 numbers, got 'abc'"),
    ({"offset": 0.5}, TypeError, r"offset must be a sequence of 3 numbers, got 0.5"),
    ({"offset": (0, 0)}, ValueError, r"offset must be 3 numbers, got \(0, 0\)"),
    ({"offset": (0, 0, float("nan"))}, ValueError, r"offset must be finite"),
    ({"hide_owner": "no"}, TypeError, r"hide_owner must be a bool, got 'no'"),
    ({"hide_owner": 0}, TypeError, r"hide_owner must be a bool, got 0"),
    ({"group": ["bodies"]}, TypeError, r"group must be the name \(str\) of an instance group, got \['bodies'\]"),
])
def test_bad_camera_mounts_raise_and_change_nothing(kwargs, error, message):
    scene = mount_scene()
    arguments = {"group": "bodies", "instance": [0, 1], **kwargs}
    with pytest.raises(error, match=message):
        scene.mount_cameras(**arguments)
    assert scene.camera_mount is None


def test_camera_mount_instances_may_be_any_integer_sequence():
    for instance in ([2, 1], (2, 1), range(2, 0, -1), np.array([2, 1], dtype=np.uint8), torch.tensor([2, 1])):
        assert mount_scene().mount_cameras("bodies", instance, pitch=np.float32(0.5)).instance == (2, 1)


@pytest.mark.parametrize("kwargs,error,message", [
    ({"color": [2, 0, 0]}, ValueError, r"color must be <= 1.0, got maximum 2.0"),  # as BatchRenderer.update says
    ({"color": [[0.5, 0, 0], [0, -0.5, 0]]}, ValueError, r"color must be >= 0.0, got minimum -0.5"),
    ({"color": "red"}, TypeError, r"color must be a torch.Tensor or array-like, got str"),
    ({"scale": torch.ones(1, 1, 3)}, ValueError,
     r"scale must have shape \[2, 3\|1\], \[1, 3\|1\] or \[3\|1\], got \[1, 1, 3\]"),
    ({"rotation": torch.ones(1, 1, 1, 4)}, ValueError, r"rotation must have shape \[2, 4\], \[1, 4\] or \[4\]"),
    ({"rotation": [0, 0, 0, 0]}, ValueError, r"rotation must be non-zero quaternions"),
    ({"position": torch.zeros(2, 3, device="meta")}, ValueError, r"position must be a CPU tensor.*meta"),
    ({"color": torch.ones(3).to_sparse()}, TypeError, r"color must be a dense \(strided\) tensor"),
])
def test_bad_static_groups_raise_and_add_nothing(kwargs, error, message):
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=16)
    arguments = {"position": [[0, 0, 0], [1, 0, 0]], **kwargs}
    with pytest.raises(error, match=message):
        scene.add_static("walls", "box", **arguments)
    assert not scene.static


def test_static_groups_take_a_uniform_scale_and_never_keep_a_graph():
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=16)
    position = torch.zeros(2, 3, requires_grad=True)
    group = scene.add_static("walls", "box", position=position * 2, scale=2.0, color=torch.ones(3, requires_grad=True))
    assert group.scale.tolist() == [[2.0, 2.0, 2.0]] * 2
    assert not any(t.requires_grad for t in (group.position, group.rotation, group.scale, group.color))


def test_update_names_a_group_that_is_not_a_str(renderer):
    before = renderer.instance_state("boxes")
    for group in (["boxes"], None, 3):
        with pytest.raises(TypeError, match=r"group must be the name \(str\) of one of this scene's instance groups "
                                            r"\['boxes'\], got "):
            renderer.update(group, position=GOOD["position"] + 7.0)
    after = renderer.instance_state("boxes")
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_update_and_set_cameras_never_keep_an_autograd_graph(renderer):
    before = renderer.instance_state("boxes"), renderer.fov_y.clone()
    position = torch.zeros(W, C, 3, requires_grad=True)
    renderer.update("boxes", position=position + GOOD["position"] + 1.0, color=torch.ones(W, C, 4, requires_grad=True))
    renderer.set_cameras(fov_y=torch.full((W, A), 1.0, requires_grad=True),
                         position=torch.ones(W, A, 3, requires_grad=True))
    tensors = [*renderer.packer.state["boxes"].values(), renderer.camera_position, renderer.fov_y]
    assert not any(t.requires_grad for t in tensors)
    renderer.update("boxes", **{k: v for k, v in before[0].items()})
    renderer.set_cameras(fov_y=before[1], position=torch.zeros(W, A, 3) + torch.tensor([0, 0, 1.0]))


def test_bad_groups_and_meshes(tmp_path):
    scene = mr.Scene(num_worlds=1, agents_per_world=2, resolution=16)
    scene.add_group("boxes", "box", capacity=2)
    with pytest.raises(ValueError, match="group name 'boxes' is already used"):
        scene.add_group("boxes", "sphere", capacity=1)
    with pytest.raises(ValueError, match="capacity must be an int >= 1, got 0"):
        scene.add_group("none", "box", capacity=0)
    with pytest.raises(FileNotFoundError, match="model file .*missing.egg' does not exist"):
        scene.add_group("model", str(tmp_path / "missing.egg"), capacity=1)
    corrupt = tmp_path / "corrupt.egg"
    corrupt.write_text("<Group> { this is not an egg file")
    with pytest.raises(ValueError,
                       match=r"(?s)mesh: model file '.*corrupt.egg' could not be loaded by Panda3D.*syntax error"):
        scene.add_group("model", str(corrupt), capacity=1)
    with pytest.raises(TypeError, match="mesh must be a MeshData"):
        scene.add_group("model", 42, capacity=1)
    with pytest.raises(ValueError, match=r"instance must give one index per agent \(2\), got 1"):
        scene.mount_cameras("boxes", [0])
    with pytest.raises(ValueError, match=r"instance indices must be in \[0, 2\), got \[0, 5\]"):
        scene.mount_cameras("boxes", [0, 5])
    with pytest.raises(ValueError, match="group must name an instance group"):
        scene.mount_cameras("ghosts", [0, 1])
    with pytest.raises(ValueError, match=r"position must be finite"):
        scene.add_static("bad", "box", position=[[float("nan"), 0, 0]])
    assert sorted(scene.groups) == ["boxes"] and not scene.static, "rejected calls must not add groups"


def test_resolution_beyond_the_gl_limit():
    from marl_render import backend

    limit = backend.gl_info().max_framebuffer_size
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=(16, limit + 1))
    with pytest.raises(ValueError, match=rf"resolution must be at most {limit} pixels per side"):
        mr.BatchRenderer(scene)
    with pytest.raises(ValueError, match=r"max_framebuffer_size must be an int in \[1, "):
        mr.BatchRenderer(mr.Scene(num_worlds=1, agents_per_world=1, resolution=16), max_framebuffer_size=0)


def test_use_after_close_is_a_clear_error():
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=16)
    renderer = mr.BatchRenderer(scene)
    renderer.render()
    renderer.close()
    renderer.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        renderer.render()
    with pytest.raises(RuntimeError, match="closed"):
        renderer.set_cameras(fov_y=1.0)


def test_texture_must_be_an_image():
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=16, effects=("texture",))
    with pytest.raises(ValueError, match=r"texture must be a uint8 array \[h, w, 3\|4\] with h, w >= 1, got array "
                                         r"of shape \(4, 4\), dtype uint8"):
        scene.add_group("boxes", "box", capacity=1, texture=np.zeros((4, 4), dtype=np.uint8))
    assert not scene.groups
    # A group made some other way is still checked when the renderer builds its texture.
    from marl_render.panda_buffers import panda_texture

    with pytest.raises(ValueError, match=r"texture of group 'boxes': texture must be a uint8 array"):
        panda_texture(np.zeros((4, 4), dtype=np.uint8), "boxes")


def test_huge_quaternions_are_normalised_not_stored_as_zeros():
    """Quaternions above ~1e154 overflowed the norm, were stored as zeros and jammed every later render."""
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8)
    scene.add_group("box", "box", capacity=1)
    huge = torch.tensor([[[1e200, 0.0, 0.0, 1e200]]], dtype=torch.float64)
    with mr.BatchRenderer(scene) as renderer, mr.BatchRenderer(scene) as twin:
        renderer.update("box", rotation=huge, active=torch.ones(1, 1, dtype=torch.bool))
        twin.update("box", rotation=torch.tensor([[[1.0, 0.0, 0.0, 1.0]]]), active=torch.ones(1, 1, dtype=torch.bool))
        renderer.set_cameras(rotation=huge * 3, position=torch.tensor([[[0.0, -3.0, 0.0]]]))
        twin.set_cameras(rotation=torch.tensor([[[3.0, 0.0, 0.0, 3.0]]]), position=torch.tensor([[[0.0, -3.0, 0.0]]]))
        assert torch.equal(renderer.render().rgb, twin.render().rgb)
        for kwargs in ({"rotation": torch.zeros(1, 1, 4)}, {"rotation": torch.full((1, 1, 4), 1e-300,
                                                                                   dtype=torch.float64)}):
            with pytest.raises(ValueError, match="rotation must be non-zero quaternions"):
                renderer.update("box", **kwargs)
        assert renderer.render().rgb.shape == (1, 1, 8, 8, 3)  # the refused calls changed nothing


@pytest.mark.parametrize("direction", [(0, 0, -1e-310), (1e308, 1e308, -1e308), (0.0, 1e-40, 0.0)])
def test_light_directions_whose_length_cannot_be_normalised_are_refused(direction):
    with pytest.raises(ValueError, match=r"lighting\.direction must have a length in \[1e-30, 1e\+30\]"):
        mr.Lighting(direction=direction)



def test_a_failed_frame_drops_the_cached_shader_variants():
    """A variant whose draw failed keeps Panda3D's error state: handed out again, every later renderer
    with the same effects drew only the background. A failure now drops the cache, so the next
    renderer compiles afresh."""
    from panda3d.core import Shader

    from marl_render import backend, shaders

    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8)
    scene.add_group("box", "box", capacity=1)
    camera = {"position": torch.tensor([[[0.0, -3.0, 0.0]]]), "look_at": torch.tensor([[[0.0, 0.0, 0.0]]])}
    with mr.BatchRenderer(scene) as broken:
        broken.update("box", position=[[[0.0, 0.0, 0.0]]], active=[[True]])
        broken.set_cameras(**camera)
        assert shaders._COMPILED  # the variants of this scene are cached
        broken._groups["box"].node.set_shader(Shader.make(
            Shader.SL_GLSL, "#version 410\nvoid main() { gl_Position = vec4(0.0); }",
            "#version 410\nout vec4 c;\nvoid main() { c = undefined_colour; }"))
        with pytest.raises(backend.ShaderCompileError):
            broken.render()
        assert not shaders._COMPILED
    with mr.BatchRenderer(scene) as fresh:
        fresh.update("box", position=[[[0.0, 0.0, 0.0]]], active=[[True]])
        fresh.set_cameras(**camera)
        assert len(set(map(tuple, fresh.render().rgb.reshape(-1, 3).tolist()))) > 1  # the box is drawn


def test_near_far_ratios_the_depth_buffer_cannot_resolve_are_refused():
    """far=100 with near=1e-8 used to draw nothing in most pixels, near<=1e-10 all background, silently."""
    words = r"far / near must be at most 1e\+06 without the log_depth effect .* got a ratio of 1e\+10"
    with pytest.raises(ValueError, match=words):
        mr.Scene(num_worlds=1, agents_per_world=1, near=1e-8, far=100.0)
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, near=1e-4, far=100.0)  # 1e6: still fine
    scene.add_group("box", "box", capacity=1)
    with mr.BatchRenderer(scene) as renderer:
        with pytest.raises(ValueError, match=words):
            renderer.set_cameras(near=torch.full((1, 1), 1e-8))
        renderer.update("box", position=[[[0.0, 0.0, 0.0]]], scale=[[[20.0, 20.0, 20.0]]], active=[[True]])
        renderer.set_cameras(position=torch.tensor([[[0.0, -50.0, 0.0]]]), look_at=torch.zeros(1, 1, 3))
        rgb = renderer.render().rgb[0, 0]
        assert bool((rgb != rgb[0, 0]).any())  # the box, 50 m away, is drawn at the largest ratio allowed
    far_ok = mr.Scene(num_worlds=1, agents_per_world=1, near=1e-8, far=100.0, effects=("lighting", "log_depth"))
    assert far_ok.near == 1e-8
