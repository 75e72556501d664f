"""Skinned meshes: forward kinematics, GPU skinning against a CPU reference, per-world
joints, joint validation, and no skinning code without skinned groups.

Frame: +Y forward, +Z up, X right. A pitch (rotation about +X) by +90 degrees turns +Z
into -Y.
"""
from __future__ import annotations

import base64
import dataclasses
import json
import math
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import marl_render as mr
from marl_render import layout, shaders, skinning
from marl_render.transforms import quat_from_yaw_pitch_roll
from test_effects import preprocess

warnings.filterwarnings("ignore", message="The given NumPy array is not writable")

IDENTITY = torch.tensor([1.0, 0.0, 0.0, 0.0])


def pitch_quat(angle) -> torch.Tensor:
    angle = torch.as_tensor(angle, dtype=torch.float64)
    return quat_from_yaw_pitch_roll(torch.zeros_like(angle), angle)


def random_poses(mesh: skinning.SkinnedMesh, shape, seed: int, spread: float = 0.9) -> torch.Tensor:
    """Joint rotations [*shape, J, 4]: random axes, angles up to `spread` radians."""
    generator = torch.Generator().manual_seed(seed)
    axis = torch.randn(*shape, mesh.num_joints, 3, generator=generator, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = (torch.rand(*shape, mesh.num_joints, 1, generator=generator, dtype=torch.float64) * 2 - 1) * spread
    return torch.cat((torch.cos(angle / 2), torch.sin(angle / 2) * axis), -1)


# ----------------------------------------------------------------------------- joint maths
def test_forward_kinematics_bends_a_limb_about_its_pivots():
    limb = mr.skinned_limb(bones=2, radius=0.1, length=1.0)
    np.testing.assert_allclose(limb.pivots, [[0, 0, 0.1], [0, 0, 0.5]], atol=1e-7)
    tip = torch.tensor([0.0, 0.0, 0.9, 1.0], dtype=torch.float64)
    quarter = pitch_quat(math.pi / 2)
    cases = [((IDENTITY, quarter), (0.0, -0.4, 0.5)),  # the elbow turns the tip about (0, 0, 0.5)
             ((quarter, IDENTITY), (0.0, -0.8, 0.1)),  # the shoulder turns the whole limb about (0, 0, 0.1)
             ((quarter, quarter), (0.0, -0.4, -0.3))]  # the elbow's turn happens in the turned upper bone
    for rotations, expected in cases:
        transforms = skinning.joint_transforms(limb, torch.stack(rotations).to(torch.float64))
        np.testing.assert_allclose((transforms[1] @ tip).numpy(), expected, atol=1e-12)


def test_forward_kinematics_is_batched_over_leading_dimensions():
    mesh = mr.skinned_character()
    poses = random_poses(mesh, (3, 2), seed=1)
    batched = skinning.joint_transforms(mesh, poses)
    assert batched.shape == (3, 2, mesh.num_joints, 3, 4)
    for w in range(3):
        for c in range(2):
            torch.testing.assert_close(batched[w, c], skinning.joint_transforms(mesh, poses[w, c]))


def test_pose_radius_holds_every_pose():
    mesh = mr.skinned_character()
    poses = random_poses(mesh, (64,), seed=2, spread=math.pi)
    furthest = max(skinning.skin_vertices(mesh, t)[0].norm(dim=-1).max().item()
                   for t in skinning.joint_transforms(mesh, poses))
    assert furthest <= mesh.pose_radius
    assert mesh.pose_radius > np.linalg.norm(mesh.positions, axis=1).max()  # more than the bind pose alone


def test_skinned_mesh_refuses_inconsistent_skeletons():
    limb = mr.skinned_limb(bones=3)
    fields = dict(joint_names=limb.joint_names, parents=limb.parents, pivots=limb.pivots,
                  skin_joints=limb.skin_joints, skin_weights=limb.skin_weights)
    arrays = (limb.name, limb.positions, limb.normals, limb.uvs, limb.triangles)
    for change, message in [(dict(parents=np.array([-1, 2, 1], np.int32)), "cycle"),
                            (dict(parents=np.array([-1, 0, 3], np.int32)), "parents"),
                            (dict(skin_weights=limb.skin_weights * 2), "sum to 1"),
                            (dict(skin_joints=limb.skin_joints + 3), "skin_joints"),
                            (dict(pivots=limb.pivots[:2]), "pivots"),
                            (dict(joint_names=("a", "a", "b")), "distinct")]:
        with pytest.raises(ValueError, match=message):
            skinning.SkinnedMesh(*arrays, **{**fields, **change})


# ----------------------------------------------------------------------------- pixels
RESOLUTION = 96


def _mask_scene(worlds: int, groups: dict) -> mr.Scene:
    """One agent per world looking at the origin from the front-left, a little above."""
    scene = mr.Scene(num_worlds=worlds, agents_per_world=1, resolution=RESOLUTION, effects=("segmentation",))
    for name, (mesh, capacity) in groups.items():
        scene.add_group(name, mesh, capacity=capacity)
    return scene


def _look(renderer, worlds):
    renderer.set_cameras(position=torch.tensor([-0.5, -1.5, 0.9], dtype=torch.float64).repeat(worlds, 1, 1),
                         look_at=torch.tensor([0.0, 0.0, 0.55], dtype=torch.float64).repeat(worlds, 1, 1))


def _within_one_pixel(mask: torch.Tensor, reference: torch.Tensor) -> bool:
    """Every pixel set in one mask and not the other touches (8-neighbourhood) the other mask."""
    def grow(m):
        return F.max_pool2d(m.float()[:, None], 3, stride=1, padding=1)[:, 0] > 0

    return bool((mask & ~grow(reference)).sum() == 0 and (reference & ~grow(mask)).sum() == 0)


# Instance poses of the pixel tests: two characters per world, turned, scaled, off-centre.
PLACES = torch.tensor([[-0.45, 0.1, 0.0], [0.5, -0.2, 0.05]], dtype=torch.float64)
YAWS = torch.tensor([0.4, -0.7])
SCALES = torch.tensor([[1.0, 1.0, 1.0], [0.8, 1.1, 0.9]])


def _limb_with_skin_slots_reversed() -> skinning.SkinnedMesh:
    """A three-bone limb whose influences sit in the last skin slots (the first ones weigh 0)."""
    limb = mr.skinned_limb(bones=3, radius=0.12, length=1.0)
    return dataclasses.replace(limb, skin_joints=limb.skin_joints[:, ::-1].copy(),
                               skin_weights=limb.skin_weights[:, ::-1].copy())


def write_strip_gltf(path, skin: bool = True) -> None:
    """A glTF (Y up) strip 1 m wide and 2 m tall, two-sided, on joints "lower" (at the origin)
    and "upper" (its child, 1 m up): rows at y <= 0.5 follow lower, y = 1 both halves, y >= 1.5 upper."""
    ys = np.repeat(np.arange(5) * 0.5, 2)
    positions = np.stack((np.tile([-0.5, 0.5], 5), ys, np.zeros(10)), 1).astype(np.float32)
    upper = np.clip(ys - 0.5, 0, 1)
    joints = np.tile(np.array([0, 1, 0, 0], np.uint16), (10, 1))
    weights = np.stack((1 - upper, upper, np.zeros(10), np.zeros(10)), 1).astype(np.float32)
    front = [i for r in range(4) for i in (2 * r, 2 * r + 1, 2 * r + 3, 2 * r, 2 * r + 3, 2 * r + 2)]
    indices = np.array(front + front[::-1], np.uint16)  # both windings: seen from both sides
    inverse_bind = np.stack((np.eye(4), np.eye(4))).astype(np.float32)
    inverse_bind[1, 1, 3] = -1.0  # upper's bind pose is 1 m up
    blobs = [positions, joints, weights, indices, inverse_bind.transpose(0, 2, 1)]  # matrices column-major
    data = b"".join(b.tobytes() for b in blobs)
    offsets = np.cumsum([0] + [b.nbytes for b in blobs])
    accessors = [{"bufferView": k, "componentType": component, "count": count, "type": kind}
                 for k, (component, count, kind) in enumerate([(5126, 10, "VEC3"), (5123, 10, "VEC4"),
                                                                (5126, 10, "VEC4"), (5123, len(indices), "SCALAR"),
                                                                (5126, 2, "MAT4")])]
    accessors[0].update(min=positions.min(0).tolist(), max=positions.max(0).tolist())
    attributes = {"POSITION": 0, **({"JOINTS_0": 1, "WEIGHTS_0": 2} if skin else {})}
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"name": "strip", "mesh": 0, **({"skin": 0} if skin else {})}, {"name": "lower", "children": [2]},
                  {"name": "upper", "translation": [0.0, 1.0, 0.0]}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": 3}]}],
        "buffers": [{"byteLength": len(data),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": int(o), "byteLength": b.nbytes}
                        for o, b in zip(offsets[:-1], blobs, strict=True)],  # the last offset is the end of the data
        "accessors": accessors,
    }
    if skin:
        document["skins"] = [{"joints": [1, 2], "inverseBindMatrices": 4}]
    with open(path, "w") as file:
        json.dump(document, file)


# The same strip as a Panda3D character (.egg, Z up, one-sided: it faces -Y).
STRIP_EGG = """<CoordinateSystem> { Z-up }
<Group> strip {
  <Dart> { 1 }
  <VertexPool> strip.verts {
""" + "".join(f"    <Vertex> {2 * r + k} {{ {x} 0 {0.5 * r} }}\n"
              for r in range(5) for k, x in enumerate((-0.5, 0.5))) + """  }
""" + "".join(f"  <Polygon> {{ <VertexRef> {{ {2 * r} {2 * r + 1} {2 * r + 3} {2 * r + 2} "
              f"<Ref> {{ strip.verts }} }} }}\n" for r in range(4)) + """  <Joint> lower {
    <Transform> { <Translate> { 0 0 0 } }
    <VertexRef> { 0 1 2 3 <Ref> { strip.verts } }
    <VertexRef> { 4 5 <Scalar> membership { 0.5 } <Ref> { strip.verts } }
    <Joint> upper {
      <Transform> { <Translate> { 0 0 1 } }
      <VertexRef> { 6 7 8 9 <Ref> { strip.verts } }
      <VertexRef> { 4 5 <Scalar> membership { 0.5 } <Ref> { strip.verts } }
    }
  }
}
"""


def strip_file(kind: str, folder) -> str:
    """The strip written as a .gltf (needs the optional panda3d-gltf to load) or an .egg."""
    path = folder / f"strip.{kind}"
    if kind == "gltf":
        pytest.importorskip("gltf", reason="glTF skins need the optional panda3d-gltf package (the gltf extra)")
        write_strip_gltf(path)
    else:
        path.write_text(STRIP_EGG)
    return path


@pytest.mark.parametrize("kind", ["gltf", "egg"])
def test_skinned_model_files_load_their_joints_pivots_and_weights(kind, tmp_path):
    mesh = skinning.load_skinned_model(strip_file(kind, tmp_path), name="strip")
    assert mesh.joint_names == ("lower", "upper") and mesh.parents.tolist() == [-1, 0]
    np.testing.assert_allclose(mesh.pivots, [[0, 0, 0], [0, 0, 1]], atol=1e-6)  # glTF's +Y up is Panda3D's +Z
    np.testing.assert_allclose(np.abs(mesh.positions[:, 0]), 0.5, atol=1e-6)
    np.testing.assert_allclose(mesh.positions[:, 1], 0.0, atol=1e-6)
    height = mesh.positions[:, 2]
    assert sorted(set(np.round(height, 3).tolist())) == [0.0, 0.5, 1.0, 1.5, 2.0]
    upper_weight = np.where(mesh.skin_joints == 1, mesh.skin_weights, 0).sum(1)
    np.testing.assert_allclose(upper_weight, np.clip(height - 0.5, 0, 1), atol=1e-6)
    # Bending "upper" a quarter turn forward lays the top edge 1 m in front of its pivot.
    pose = torch.stack((IDENTITY.double(), pitch_quat(math.pi / 2)))
    posed, _ = skinning.skin_vertices(mesh, skinning.joint_transforms(mesh, pose))
    top = torch.from_numpy(height > 1.99)
    torch.testing.assert_close(posed[top, 1:],
                               torch.tensor([[-1.0, 1.0]], dtype=torch.float64).expand(int(top.sum()), 2),
                               atol=1e-6, rtol=0)


def test_a_model_without_skin_is_refused(tmp_path):
    (tmp_path / "rigid.egg").write_text(STRIP_EGG[:STRIP_EGG.index("  <Joint>")] + "}\n")
    with pytest.raises(ValueError, match="strip: model file .*rigid.egg.* has no skin"):
        skinning.load_skinned_model(tmp_path / "rigid.egg", name="strip")


def test_geometry_without_skin_follows_an_extra_root_joint(tmp_path):
    plate = """  <Group> plate {
    <VertexPool> plate.verts { <Vertex> 0 { 1 0 0 } <Vertex> 1 { 2 0 0 } <Vertex> 2 { 2 0 1 } }
    <Polygon> { <VertexRef> { 0 1 2 <Ref> { plate.verts } } }
  }
"""
    (tmp_path / "plate.egg").write_text(STRIP_EGG.replace("  <Joint> lower", plate + "  <Joint> lower", 1))
    mesh = skinning.load_skinned_model(tmp_path / "plate.egg")
    assert mesh.joint_names == ("lower", "upper", "(model)") and mesh.parents.tolist() == [-1, 0, -1]
    on_plate = mesh.positions[:, 0] > 0.9
    assert on_plate.sum() == 3
    assert (mesh.skin_joints[on_plate, 0] == 2).all() and (mesh.skin_weights[on_plate, 0] == 1).all()
    assert (mesh.skin_weights[~on_plate][mesh.skin_joints[~on_plate] == 2] == 0).all()  # the strip never follows it


def _gltf_strip(tmp_path) -> skinning.SkinnedMesh:
    return skinning.load_skinned_model(strip_file("gltf", tmp_path))


def _egg_strip(tmp_path) -> skinning.SkinnedMesh:
    return skinning.load_skinned_model(strip_file("egg", tmp_path))


@pytest.mark.parametrize("make_mesh", [mr.skinned_character, _limb_with_skin_slots_reversed, _gltf_strip, _egg_strip])
def test_gpu_skinning_matches_cpu_reference_within_one_pixel(make_mesh, tmp_path):
    mesh = make_mesh(tmp_path) if make_mesh in (_gltf_strip, _egg_strip) else make_mesh()
    worlds, capacity = 3, 2
    poses = random_poses(mesh, (worlds, capacity), seed=3)
    poses[0] = IDENTITY  # world 0: the bind pose
    instance = dict(position=PLACES.repeat(worlds, 1, 1), rotation=quat_from_yaw_pitch_roll(YAWS).repeat(worlds, 1, 1),
                    scale=SCALES.repeat(worlds, 1, 1))

    skinned_scene = _mask_scene(worlds, {"people": (mesh, capacity)})
    with mr.BatchRenderer(skinned_scene) as renderer:
        _look(renderer, worlds)
        renderer.update("people", joints=poses, active=torch.ones(worlds, capacity, dtype=torch.bool), **instance)
        skinned = renderer.render().segmentation[:, 0] > 0

    # The reference: each (world, instance) pose skinned on the CPU, drawn as a rigid mesh
    # of its own group that is active in its world and slot only.
    groups = {f"pose{w}_{c}": (skinning.posed_mesh(mesh, poses[w, c]), capacity)
              for w in range(worlds) for c in range(capacity)}
    reference_scene = _mask_scene(worlds, groups)
    with mr.BatchRenderer(reference_scene) as renderer:
        _look(renderer, worlds)
        for name in groups:
            w, c = map(int, name[4:].split("_"))
            active = torch.zeros(worlds, capacity, dtype=torch.bool)
            active[w, c] = True
            renderer.update(name, active=active, **instance)
        reference = renderer.render().segmentation[:, 0] > 0

    assert all(reference[w].sum() > 400 for w in range(worlds))  # the meshes fill part of every view
    for w in range(worlds):
        assert _within_one_pixel(skinned[w], reference[w]), (
            f"world {w}: {(skinned[w] ^ reference[w]).sum()} pixels differ")
    for w in (1, 2):  # the poses really change the silhouette: the bind pose is no match for them
        assert not _within_one_pixel(reference[0], reference[w])


def test_joints_of_one_world_move_only_that_worlds_instances():
    mesh = mr.skinned_character()
    worlds, capacity = 3, 2
    scene = mr.Scene(num_worlds=worlds, agents_per_world=1, resolution=64, effects=("lighting",))
    scene.add_group("people", mesh, capacity=capacity)
    with mr.BatchRenderer(scene) as renderer:
        _look(renderer, worlds)
        renderer.update("people", position=PLACES.repeat(worlds, 1, 1),
                        active=torch.ones(worlds, capacity, dtype=torch.bool))
        before = renderer.render().rgb
        joints = IDENTITY.repeat(worlds, capacity, mesh.num_joints, 1)
        joints[1, 0, mesh.joint_index("right_shoulder")] = pitch_quat(2.0)  # raise one arm, world 1, instance 0
        renderer.update("people", joints=joints)
        after = renderer.render().rgb
    assert torch.equal(before[0], after[0]) and torch.equal(before[2], after[2])
    changed = (before[1] != after[1]).any(-1)[0]
    assert changed.sum() > 20
    # ... and only around instance 0 of that world, which stands on the left of the view.
    columns = changed.any(0).nonzero()[:, 0]
    assert columns.max() < 40


# ----------------------------------------------------------------------------- depth and shadows
SHADOW_LIGHT = mr.Lighting(direction=(-0.5, 0.35, -1.0), color=(0.6, 0.6, 0.6), ambient=(0.3, 0.3, 0.3))


def _bent_limb_frames(effects):
    """(skinned frame, reference frame) of a three-bone limb on a floor, in the bind pose
    (world 0) and bent forward and sideways (world 1), seen from above; the reference draws
    each world's pose skinned on the CPU as a rigid mesh, active in that world only."""
    limb = mr.skinned_limb(bones=3, radius=0.15, length=1.2)
    poses = IDENTITY.double().repeat(2, 1, limb.num_joints, 1)
    angles = torch.ones(3, dtype=torch.float64)
    poses[1, 0] = quat_from_yaw_pitch_roll(0 * angles, 0.45 * angles, 0.3 * angles)  # every joint pitched and rolled
    instance = dict(position=torch.tensor([0.3, -0.2, 0.0], dtype=torch.float64).repeat(2, 1, 1),
                    color=torch.tensor([0.9, 0.2, 0.2]).repeat(2, 1, 1), active=torch.ones(2, 1, dtype=torch.bool))

    def scene_with(groups):
        scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=RESOLUTION, effects=effects,
                         lighting=SHADOW_LIGHT,
                         shadows=mr.Shadows(resolution=512, bounds=((-2.0, -2.0, 0.0), (2.0, 2.0, 1.5))))
        scene.add_static("floor", "plane", position=[0.0, 0.0, 0.0], scale=[8.0, 8.0, 1.0], color=[0.8] * 3)
        for name, mesh in groups.items():
            scene.add_group(name, mesh, capacity=1)
        return scene

    def draw(scene, updates):
        with mr.BatchRenderer(scene) as renderer:
            renderer.set_cameras(position=torch.tensor([0.4, -1.5, 1.9], dtype=torch.float64).repeat(2, 1, 1),
                                 look_at=torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64).repeat(2, 1, 1))
            for name, kwargs in updates.items():
                renderer.update(name, **kwargs)
            return renderer.render()

    skinned = draw(scene_with({"limb": limb}), {"limb": dict(joints=poses, **instance)})
    posed = {f"pose{w}": skinning.posed_mesh(limb, poses[w, 0]) for w in range(2)}
    reference = draw(scene_with(posed), {name: dict(instance, active=torch.arange(2)[:, None] == int(name[4:]))
                                         for name in posed})
    return skinned, reference


@pytest.mark.parametrize("effects", [("depth", "segmentation"), ("lighting", "shadows", "depth", "segmentation")])
def test_depth_of_a_skinned_group_matches_the_cpu_skinned_reference(effects):
    # Skinned meshes take their depth planes from the geometry shader, which sees the skinned
    # corners; the corner attributes of procedural meshes would give the bind pose's planes.
    skinned, reference = _bent_limb_frames(effects)
    limb = (skinned.segmentation[:, 0] > 1) & (reference.segmentation[:, 0] > 1)  # 1: the floor
    interior = -F.max_pool2d(-limb.float()[:, None], 3, stride=1, padding=1)[:, 0] > 0  # away from silhouettes
    for w in range(2):
        assert interior[w].sum() > 150
        difference = (skinned.depth[w, 0] - reference.depth[w, 0]).abs()[interior[w]]
        assert float(difference.max()) < 1e-3, f"world {w}: depth differs by up to {float(difference.max()):.4f} m"
    floor = (skinned.segmentation[:, 0] == 1) & (reference.segmentation[:, 0] == 1)
    assert torch.equal(skinned.depth[:, 0][floor], reference.depth[:, 0][floor])
    # The bent pose is no bind pose: its depth differs where both show the limb.
    both = interior[0] & interior[1]
    assert float((reference.depth[0, 0] - reference.depth[1, 0]).abs()[both].max()) > 0.05


@pytest.mark.parametrize("effects", [("lighting", "shadows"), ("lighting", "shadows", "depth", "segmentation")])
def test_a_skinned_group_casts_its_posed_shadow(effects):
    skinned, reference = _bent_limb_frames(effects)

    def shadowed_floor(rgb):
        image = rgb[:, 0].int()
        gray = (image.amax(-1) - image.amin(-1)) <= 3  # the floor is gray, the limb red
        return gray & (image[..., 0] < 255 * 0.8 * 0.45)  # darker than lit floor (ambient 0.3 + direct)

    mask, expected = shadowed_floor(skinned.rgb), shadowed_floor(reference.rgb)
    for w in range(2):
        assert expected[w].sum() > 100, f"world {w}: the reference shadow must be in view"
        assert _within_one_pixel(mask[w], expected[w]), f"world {w}: {(mask[w] ^ expected[w]).sum()} pixels differ"
    assert not _within_one_pixel(expected[0], expected[1])  # the bent pose casts another shadow


# ----------------------------------------------------------------------------- validation
def _skinned_renderer(worlds=2, capacity=2):
    scene = mr.Scene(num_worlds=worlds, agents_per_world=1, resolution=16)
    scene.add_group("people", mr.skinned_character(), capacity=capacity)
    scene.add_group("boxes", "box", capacity=1)
    return mr.BatchRenderer(scene)


@pytest.mark.parametrize("bad, error, message", [
    (torch.ones(2, 2, 9, 4), ValueError, r"joints must have shape \[2, 2, 10, 4\], got \[2, 2, 9, 4\]"),
    (torch.ones(2, 2, 10, 3), ValueError, r"joints must have shape \[2, 2, 10, 4\]"),
    (torch.ones(2, 10, 4), ValueError, r"joints must have shape"),
    (torch.ones(2, 2, 10, 4).index_fill_(2, torch.tensor([3]), float("nan")), ValueError, "joints must be finite"),
    (torch.ones(2, 2, 10, 4).index_fill_(2, torch.tensor([0]), float("inf")), ValueError, "joints must be finite"),
    (torch.ones(2, 2, 10, 4).index_fill_(2, torch.tensor([5]), 0.0), ValueError, "joints must be non-zero quaternions"),
    (torch.ones(2, 2, 10, 4, dtype=torch.bool), TypeError, "joints must have a floating dtype"),
    ("up", TypeError, "joints must be a torch.Tensor or array-like"),
])
def test_bad_joints_are_refused_and_change_nothing(bad, error, message):
    with _skinned_renderer() as renderer:
        good = random_poses(renderer.scene.groups["people"].mesh, (2, 2), seed=4)
        renderer.update("people", joints=good, active=torch.ones(2, 2, dtype=torch.bool))
        state = renderer.instance_state("people")
        frame = renderer.render().rgb
        with pytest.raises(error, match=message):
            renderer.update("people", joints=bad, position=torch.ones(2, 2, 3))  # nothing is stored, not even position
        after = renderer.instance_state("people")
        assert state.keys() == after.keys() and all(torch.equal(state[k], after[k]) for k in state)
        assert torch.equal(renderer.render().rgb, frame)


def test_joints_are_normalised_and_stored_per_instance():
    with _skinned_renderer() as renderer:
        joints = IDENTITY.repeat(2, 2, 10, 1) * 3.0
        joints[1, 1, 2] = torch.tensor([-3.0, 0.0, 0.0, 4.0])
        renderer.update("people", joints=joints.double())
        stored = renderer.instance_state("people")["joints"]
    assert stored.shape == (2, 2, 10, 4) and stored.dtype == torch.float32
    expected = IDENTITY.repeat(2, 2, 10, 1)
    expected[1, 1, 2] = torch.tensor([0.6, 0.0, 0.0, -0.8])  # unit length, w >= 0 (q and -q: one rotation)
    torch.testing.assert_close(stored, expected)


def test_joints_on_a_rigid_group_are_refused():
    with _skinned_renderer() as renderer:
        assert "joints" not in renderer.instance_state("boxes")
        with pytest.raises(ValueError, match="joints can only be set on a group whose mesh is a SkinnedMesh; "
                                             "group 'boxes'"):
            renderer.update("boxes", joints=IDENTITY.repeat(2, 1, 1, 1))


# ----------------------------------------------------------------------------- shader variants
SKINNING_MARKERS = ["skin_joints", "skin_weights", "JOINT_TEXELS", "blend0"]


def test_without_skinned_groups_the_shader_has_no_skinning_code():
    for effects in [(), ("lighting",), tuple(shaders.EFFECTS)]:
        for static in (False, True):
            defines = shaders.defines_for(frozenset(effects), static=static, textured=False)
            assert "SKINNING" not in defines
            code = preprocess(shaders.variant_source("vert", defines))
            assert not [m for m in SKINNING_MARKERS if m in code]
        skinned = shaders.defines_for(frozenset(effects), static=False, textured=False, joints=10)
        code = preprocess(shaders.variant_source("vert", skinned))
        assert all(m in code for m in SKINNING_MARKERS)
        assert f"ROW_TEXELS {layout.INSTANCE.texels + 10 * layout.JOINT_TEXELS}" in skinned
    with pytest.raises(ValueError, match="static groups cannot be skinned"):
        shaders.defines_for(frozenset(), static=True, textured=False, joints=2)


def test_renderer_compiles_skinning_only_for_skinned_groups(monkeypatch):
    seen = {}
    original = shaders.compiled

    def recording(defines):
        seen[defines] = seen.get(defines, 0) + 1
        return original(defines)

    monkeypatch.setattr(shaders, "compiled", recording)
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8)
    scene.add_static("floor", "plane", position=[0, 0, 0])
    scene.add_static("statue", mr.skinned_limb(), position=[0, 0, 0])  # static: drawn in its bind pose
    scene.add_group("boxes", "box", capacity=2)
    with mr.BatchRenderer(scene) as renderer:
        renderer.render()
    assert not any("SKINNING" in defines for defines in seen)
    scene.add_group("limbs", mr.skinned_limb(bones=3), capacity=2)
    seen.clear()
    with mr.BatchRenderer(scene) as renderer:
        renderer.render()
    skinned = [defines for defines in seen if "SKINNING" in defines]
    assert len(skinned) == 1 and f"ROW_TEXELS {layout.INSTANCE.texels + 3 * layout.JOINT_TEXELS}" in skinned[0]
    assert "joints" not in renderer.instance_state("boxes")


def _edited_strip(tmp_path, edit) -> str:
    """The glTF strip with its JSON changed by edit(document)."""
    path = strip_file("gltf", tmp_path)
    document = json.loads(open(path).read())
    edit(document)
    with open(path, "w") as file:
        json.dump(document, file)
    return path


def test_gltf_skins_that_would_load_wrong_are_refused(tmp_path):
    """Both loaded silently wrong before: more than 4 influences bound every vertex to joint 0 with
    weight 1; a joint the skin does not list was dropped or bound to another joint."""
    def more_influences(document):
        document["meshes"][0]["primitives"][0]["attributes"].update(JOINTS_1=1, WEIGHTS_1=2)

    with pytest.raises(ValueError, match=r"strip\.gltf' gives vertices more than 4 joint influences "
                                         r"\(\['JOINTS_1', 'WEIGHTS_1'\]\)"):
        skinning.load_skinned_model(_edited_strip(tmp_path, more_influences))

    def unlisted_joint(document):
        document["skins"][0]["joints"] = [1]  # vertices still name joint 1 of the skin ("upper")

    with pytest.raises(ValueError, match=r"strip\.gltf' has vertices that follow a joint its skin does not list"):
        skinning.load_skinned_model(_edited_strip(tmp_path, unlisted_joint))
    assert skinning.load_skinned_model(strip_file("gltf", tmp_path)).num_joints >= 2  # the intact file still loads
