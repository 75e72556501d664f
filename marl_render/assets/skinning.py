"""Skinned (articulated) meshes: joints, skin weights and forward kinematics in torch.

A SkinnedMesh is a MeshData whose vertices each follow up to four joints with weights
that sum to 1 (linear-blend skinning). Joint j has a parent (-1: a root) and a pivot,
its position in the mesh's bind pose. A pose gives every joint a rotation about its
pivot, expressed in its parent's frame (at the bind pose every joint frame has the
mesh's axes), so a knee bends the shin and the foot, and a hip the whole leg.

Per instance the renderer packs one 3x4 matrix per joint (3 texels), the transform from
the bind pose to the pose, after the instance's own texels; the vertex shader blends the
matrices of a vertex's joints and applies them once (the `SKINNING` variant). Scenes
without skinned groups compile none of it.

The forward kinematics runs over the joints' depth levels (a skeleton a few levels
deep), each level one batched step over all worlds, instances and joints of that level.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, field

import numpy as np
import torch

from ..util.extras import require
from ..util.transforms import quat_to_matrix
from .meshes import MeshData, lathe, parse_model_file, to_panda_geom

MAX_INFLUENCES = 4  # joints per vertex


@dataclass(frozen=True)
class SkinnedMesh(MeshData):
    """MeshData plus a skeleton: joint_names [J], parents [J] (-1: root), pivots [J, 3]
    (bind pose, mesh frame), skin_joints [N, 4] joint indices and skin_weights [N, 4]
    (each row sums to 1; unused slots have weight 0)."""

    joint_names: tuple = ()
    parents: np.ndarray = field(default=None)
    pivots: np.ndarray = field(default=None)
    skin_joints: np.ndarray = field(default=None)
    skin_weights: np.ndarray = field(default=None)

    def __post_init__(self):
        super().__post_init__()
        name, n = self.name, len(self.positions)
        joints = len(self.joint_names)
        if joints < 1 or not all(isinstance(j, str) and j for j in self.joint_names):
            raise ValueError(f"mesh {name!r}: joint_names must be one or more non-empty names, "
                             f"got {self.joint_names!r}")
        if len(set(self.joint_names)) != joints:
            raise ValueError(f"mesh {name!r}: joint_names must be distinct, got {list(self.joint_names)}")
        for label, arr, shape, kinds in (("parents", self.parents, (joints,), "iu"),
                                         ("pivots", self.pivots, (joints, 3), "f"),
                                         ("skin_joints", self.skin_joints, (n, MAX_INFLUENCES), "iu"),
                                         ("skin_weights", self.skin_weights, (n, MAX_INFLUENCES), "f")):
            if not isinstance(arr, np.ndarray) or arr.dtype.kind not in kinds:
                kind = "floating" if kinds == "f" else "integer"
                raise TypeError(f"mesh {name!r}: {label} must be a numpy array of {kind}"
                                f" dtype, got {type(arr).__name__ if not isinstance(arr, np.ndarray) else arr.dtype}")
            if arr.shape != shape:
                raise ValueError(f"mesh {name!r}: {label} must have shape {list(shape)}, got {list(arr.shape)}")
        if not np.isfinite(self.pivots).all() or not np.isfinite(self.skin_weights).all():
            raise ValueError(f"mesh {name!r}: pivots and skin_weights must be finite")
        if ((self.parents < -1) | (self.parents >= joints) | (self.parents == np.arange(joints))).any():
            raise ValueError(f"mesh {name!r}: parents must be -1 or the index of another joint in [0, {joints}), "
                             f"got {self.parents.tolist()}")
        if n and (self.skin_joints.min() < 0 or self.skin_joints.max() >= joints):
            raise ValueError(f"mesh {name!r}: skin_joints must be joint indices in [0, {joints}), got range "
                             f"[{self.skin_joints.min()}, {self.skin_joints.max()}]")
        if (self.skin_weights < 0).any() or not np.allclose(self.skin_weights.sum(1), 1.0, atol=1e-4):
            raise ValueError(f"mesh {name!r}: skin_weights must be >= 0 and each row must sum to 1")
        _ = self.levels  # computing the levels raises for a cycle

    @property
    def num_joints(self) -> int:
        """The joints of the skeleton (len(joint_names))."""
        return len(self.joint_names)

    @functools.cached_property
    def levels(self) -> tuple:
        """Joint indices grouped by depth, roots first, in the order forward kinematics runs."""
        depth = np.full(self.num_joints, -1)
        depth[self.parents == -1] = 0
        for level in range(1, self.num_joints + 1):
            children = (depth == -1) & (self.parents >= 0)
            ready = children & (depth[np.maximum(self.parents, 0)] == level - 1)
            if not ready.any():
                break
            depth[ready] = level
        if (depth < 0).any():
            raise ValueError(f"mesh {self.name!r}: the joints {np.flatnonzero(depth < 0).tolist()} have no root "
                             "(their parents form a cycle)")
        return tuple(torch.from_numpy(np.flatnonzero(depth == d)) for d in range(depth.max() + 1))

    @functools.cached_property
    def influences(self) -> int:
        """The most joints any vertex follows with a non-zero weight; the shader blends only that many."""
        return max(int((self.skin_weights > 0).sum(1).max(initial=1)), 1)

    @functools.cached_property
    def pose_radius(self) -> float:
        """Radius about the mesh origin of a sphere that holds the mesh in every pose.

        A joint's pivot can be no farther from the origin than its parent's reach plus the
        bone between them; a vertex no farther than its joint's reach plus its distance to
        the pivot. A blended vertex lies between its joints' images, so the largest bound
        of its joints holds it too."""
        reach = np.zeros(self.num_joints)
        for level in self.levels:
            for j in level.tolist():
                p = self.parents[j]
                reach[j] = (np.linalg.norm(self.pivots[j]) if p < 0
                            else reach[p] + np.linalg.norm(self.pivots[j] - self.pivots[p]))
        arm = np.linalg.norm(self.positions[:, None, :] - self.pivots[self.skin_joints], axis=-1)  # [N, 4]
        bound = np.where(self.skin_weights > 0, reach[self.skin_joints] + arm, 0.0)
        return float(bound.max(initial=0.0))

    def joint_index(self, name: str) -> int:
        """The index of joint `name` in joint_names (and in a pose's joint axis); ValueError naming the joints."""
        if name not in self.joint_names:
            raise ValueError(f"mesh {self.name!r} has no joint {name!r}; its joints are {list(self.joint_names)}")
        return self.joint_names.index(name)

    def rigid(self) -> MeshData:
        """The bind pose as a plain MeshData (no skinning code, no joints)."""
        return MeshData(self.name, self.positions, self.normals, self.uvs, self.triangles)


def joint_transforms(mesh: SkinnedMesh, rotations: torch.Tensor) -> torch.Tensor:
    """Forward kinematics: local joint rotations [..., J, 4] (unit quaternions, w x y z)
    -> [..., J, 3, 4] transforms from the bind pose to the pose, in the mesh frame.

    Joint j rotates by R_j about its pivot c_j inside its parent's posed frame:
    M_j(x) = M_parent(c_j + R_j (x - c_j)), M_root(x) = c_j + R_j (x - c_j)."""
    local = quat_to_matrix(rotations)  # [..., J, 3, 3]
    pivots = torch.from_numpy(mesh.pivots).to(local.dtype)
    offset = pivots - (local @ pivots[:, :, None])[..., 0]  # c - R c: [..., J, 3]
    rotation = torch.empty_like(local)
    translation = torch.empty_like(offset)
    parents = torch.from_numpy(mesh.parents.astype(np.int64))
    for depth, joints in enumerate(mesh.levels):
        if depth == 0:
            rotation[..., joints, :, :] = local[..., joints, :, :]
            translation[..., joints, :] = offset[..., joints, :]
            continue
        parent = parents[joints]
        parent_rotation = rotation[..., parent, :, :]
        rotation[..., joints, :, :] = parent_rotation @ local[..., joints, :, :]
        rotated_offset = (parent_rotation @ offset[..., joints, :, None])[..., 0]
        translation[..., joints, :] = rotated_offset + translation[..., parent, :]
    return torch.cat((rotation, translation[..., None]), dim=-1)


def skin_vertices(mesh: SkinnedMesh, transforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """CPU linear-blend skinning of one pose: transforms [J, 3, 4] -> positions [N, 3] and
    unit normals [N, 3] (a reference for the shader, and for posed meshes on the host)."""
    weights = torch.from_numpy(mesh.skin_weights).to(transforms.dtype)
    blended = (weights[:, :, None, None] * transforms[torch.from_numpy(mesh.skin_joints.astype(np.int64))]).sum(1)
    positions = torch.from_numpy(mesh.positions).to(transforms.dtype)
    normals = torch.from_numpy(mesh.normals).to(transforms.dtype)
    posed = (blended[:, :, :3] @ positions[:, :, None])[..., 0] + blended[:, :, 3]
    turned = (blended[:, :, :3] @ normals[:, :, None])[..., 0]
    return posed, turned / turned.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def posed_mesh(mesh: SkinnedMesh, rotations, name: str | None = None) -> MeshData:
    """The mesh in one pose (rotations [J, 4]) as a plain MeshData, skinned on the CPU."""
    positions, normals = skin_vertices(mesh, joint_transforms(mesh, torch.as_tensor(rotations, dtype=torch.float64)))
    return MeshData(name or f"{mesh.name}:posed", positions.numpy().astype(np.float32),
                    normals.numpy().astype(np.float32), mesh.uvs, mesh.triangles)


def panda_geom(mesh: SkinnedMesh):
    """GeomNode with the skin columns beside position, normal and uv (read by the SKINNING
    shader). Each vertex's influences are sorted by weight, heaviest first, so that the
    shader can stop after the first mesh.influences of them."""
    order = np.argsort(-mesh.skin_weights, axis=1, kind="stable")
    return to_panda_geom(mesh, extra={
        "skin_joints": np.take_along_axis(mesh.skin_joints, order, 1).astype(np.float32),
        "skin_weights": np.take_along_axis(mesh.skin_weights, order, 1).astype(np.float32)})


def load_skinned_model(path, *, name: str = "mesh") -> SkinnedMesh:
    """A skinned model file as a SkinnedMesh: glTF (.gltf/.glb) skins through the optional
    panda3d-gltf package (`pip install 'marl-render[gltf]'`), Panda3D characters (.egg,
    .bam) through Panda3D. Parsed in a child process, like load_model.

    Joints are the model's joints that vertices follow, and the joints between them,
    parents first, named as in the file; pivots are their bind-pose positions in the
    model's frame (Panda3D's: Z up; glTF's Y-up files are turned). Joint rotations are then
    given in the model's axes, like every SkinnedMesh's. Vertices of Panda3D characters with
    more than four influences keep their four heaviest (renormalised); glTF files with more
    than four (JOINTS_1 / WEIGHTS_1), or whose vertices name a joint the skin does not list, are
    refused (panda3d-gltf would load them wrong); geometry without skin follows an
    extra root joint "(model)". Errors as load_model's, plus ValueError for a model
    without skin. A glTF file without panda3d-gltf installed raises MissingExtraError at once."""
    if str(path).lower().endswith((".gltf", ".glb")):
        require("gltf", "load_skinned_model of a glTF file", "gltf")
    path, arrays = parse_model_file(path, name, skinned=True)
    return SkinnedMesh(os.path.basename(path), *(np.ascontiguousarray(arrays[key], dtype=dtype) for key, dtype in (
        ("positions", np.float32), ("normals", np.float32), ("uvs", np.float32), ("triangles", np.int32))),
        joint_names=tuple(str(n) for n in arrays["joint_names"]), parents=arrays["parents"].astype(np.int32),
        pivots=arrays["pivots"].astype(np.float32), skin_joints=arrays["skin_joints"].astype(np.int32),
        skin_weights=arrays["skin_weights"].astype(np.float32))


# ---------------------------------------------------------------------- procedural skinned meshes
@dataclass
class _Part:
    """Vertices of one body part with its skin, joint indices already global."""

    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    triangles: np.ndarray
    skin_joints: np.ndarray
    skin_weights: np.ndarray


def _tube(radius: float, length: float, rings_along: int, segments: int) -> MeshData:
    """A capsule along +Z from z = 0 to z = length, with `rings_along` rings on its straight
    part so that it can bend smoothly."""
    straight = length - 2 * radius
    profile = []
    caps = 4
    for j in range(caps + 1):  # bottom hemisphere, centred at z = radius
        phi = -math.pi / 2 + (math.pi / 2) * j / caps
        profile.append((radius * math.cos(phi), radius + radius * math.sin(phi), math.cos(phi), math.sin(phi), 0.0))
    for j in range(1, rings_along):
        profile.append((radius, radius + straight * j / rings_along, 1.0, 0.0, j / rings_along))
    for j in range(caps + 1):  # top hemisphere
        phi = (math.pi / 2) * j / caps
        profile.append((radius * math.cos(phi), length - radius + radius * math.sin(phi), math.cos(phi), math.sin(phi),
                        1.0))
    return lathe("tube", profile, segments)


def _chain_weights(z: np.ndarray, bones: np.ndarray, blend: float) -> tuple[np.ndarray, np.ndarray]:
    """Two influences per vertex along a chain whose joint k starts at height bones[k]:
    the joint of the bone a vertex lies on, blended smoothly with the next one within
    `blend` of each joint."""
    if len(bones) == 1:
        return np.zeros((len(z), 2), np.int64), np.stack((np.ones_like(z), np.zeros_like(z)), 1)
    inner = bones[1:]  # joints 1.. start where the previous bone ends
    nearest = np.abs(z[:, None] - inner[None]).argmin(1) + 1  # the joint whose start is closest
    u = np.clip((z - bones[nearest]) / (2 * blend) + 0.5, 0.0, 1.0)
    smooth = u * u * (3 - 2 * u)
    return np.stack((nearest - 1, nearest), 1), np.stack((1 - smooth, smooth), 1)


def _limb_part(joints: list[int], start, radius: float, length: float, down: bool, segments: int = 12,
               rings_per_bone: int = 6) -> tuple[_Part, np.ndarray]:
    """A capsule limb from `start` along +Z (or -Z when `down`), its vertices bound to
    `joints`: equal bones between the centres of its two end caps, joint k at the start of
    bone k. Returns the part and the joints' pivots [len(joints), 3]."""
    bones = len(joints)
    tube = _tube(radius, length, rings_per_bone * bones, segments)
    starts = radius + np.arange(bones) * ((length - 2 * radius) / bones)
    blend = min(radius, (length - 2 * radius) / bones / 3)
    local, weights = _chain_weights(tube.positions[:, 2].astype(np.float64), starts, blend)
    positions, normals = tube.positions.astype(np.float64), tube.normals.astype(np.float64)
    pivots = np.stack((np.zeros(bones), np.zeros(bones), starts), 1)
    if down:  # half a turn about X keeps the winding (a rotation, not a mirror)
        flip = np.array([1.0, -1.0, -1.0])
        positions, normals, pivots = positions * flip, normals * flip, pivots * flip
    skin_joints = np.zeros((len(positions), MAX_INFLUENCES), np.int64)
    skin_weights = np.zeros((len(positions), MAX_INFLUENCES))
    skin_joints[:, :2] = np.asarray(joints)[local]
    skin_weights[:, :2] = weights
    start = np.asarray(start, float)
    return _Part(positions + start, normals, tube.uvs, tube.triangles, skin_joints, skin_weights), pivots + start


def _rigid_part(mesh: MeshData, joint: int, scale, offset) -> _Part:
    """A procedural mesh scaled and moved into place, bound wholly to one joint."""
    scale = np.asarray(scale, float)
    normals = mesh.normals / scale  # normals scale inversely
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    n = len(mesh.positions)
    skin_joints = np.zeros((n, MAX_INFLUENCES), np.int64)
    skin_joints[:, 0] = joint
    skin_weights = np.zeros((n, MAX_INFLUENCES))
    skin_weights[:, 0] = 1.0
    return _Part(mesh.positions * scale + np.asarray(offset, float), normals, mesh.uvs, mesh.triangles, skin_joints,
                 skin_weights)


def _assemble(name: str, joint_names, parents, pivots, parts: list[_Part]) -> SkinnedMesh:
    offsets = np.cumsum([0] + [len(p.positions) for p in parts[:-1]])
    return SkinnedMesh(
        name,
        np.concatenate([p.positions for p in parts]).astype(np.float32),
        np.concatenate([p.normals for p in parts]).astype(np.float32),
        np.concatenate([p.uvs for p in parts]).astype(np.float32),
        np.concatenate([p.triangles + o for p, o in zip(parts, offsets, strict=True)]).astype(np.int32),
        joint_names=tuple(joint_names),
        parents=np.asarray(parents, np.int32),
        pivots=np.asarray(pivots, np.float32).reshape(-1, 3),
        skin_joints=np.concatenate([p.skin_joints for p in parts]).astype(np.int32),
        skin_weights=np.concatenate([p.skin_weights for p in parts]).astype(np.float32),
    )


def skinned_limb(bones: int = 2, radius: float = 0.1, length: float = 1.0, segments: int = 12,
                 rings_per_bone: int = 6) -> SkinnedMesh:
    """A capsule limb standing on the origin along +Z, `length` tall, made of `bones` equal
    bones between the centres of its end caps. Joint k ("joint0", "joint1", ...) sits at
    height radius + k * (length - 2 radius) / bones and bends everything above it;
    vertices near a joint blend the two bones that meet there."""
    if isinstance(bones, bool) or not isinstance(bones, int) or bones < 1:
        raise ValueError(f"bones must be an int >= 1, got {bones!r}")
    if not radius > 0 or not length > 2 * radius:
        raise ValueError(f"skinned_limb needs radius > 0 and length > 2 * radius, got radius={radius}, length={length}")
    joints = list(range(bones))
    part, pivots = _limb_part(joints, (0.0, 0.0, 0.0), radius, length, down=False, segments=segments,
                              rings_per_bone=rings_per_bone)
    return _assemble("skinned_limb", [f"joint{k}" for k in joints], [k - 1 for k in joints], pivots, [part])


# The character's skeleton, parents first. It stands on the origin, 1 m tall, facing +Y
# with +X to its right (Panda3D's frame); left is -X.
CHARACTER_JOINTS = ("pelvis", "neck", "left_shoulder", "left_elbow", "right_shoulder", "right_elbow",
                    "left_hip", "left_knee", "right_hip", "right_knee")
_CHARACTER_PARENTS = ("", "pelvis", "pelvis", "left_shoulder", "pelvis", "right_shoulder",
                      "pelvis", "left_hip", "pelvis", "right_hip")


def skinned_character(segments: int = 12) -> SkinnedMesh:
    """A simple jointed character 1 m tall standing on the origin, facing +Y: a torso on the
    pelvis joint (at hip height), a head on the neck, and two-bone arms (shoulder, elbow)
    and legs (hip, knee) whose elbows and knees bend smoothly. Joint names: CHARACTER_JOINTS."""
    from .meshes import sphere

    index = {name: k for k, name in enumerate(CHARACTER_JOINTS)}
    parents = [index.get(parent, -1) for parent in _CHARACTER_PARENTS]
    pivots = np.zeros((len(CHARACTER_JOINTS), 3))
    pivots[index["pelvis"]] = (0.0, 0.0, 0.44)
    pivots[index["neck"]] = (0.0, 0.0, 0.84)
    ball = sphere(segments, max(segments // 2, 4))
    parts = [
        _rigid_part(ball, index["pelvis"], (0.30, 0.18, 0.40), (0.0, 0.0, 0.64)),  # torso
        _rigid_part(ball, index["neck"], (0.16, 0.16, 0.16), (0.0, 0.0, 0.92)),  # head
    ]
    for side, x in (("left", -1.0), ("right", 1.0)):
        for upper, lower, start, radius, length in (("shoulder", "elbow", (0.19 * x, 0.0, 0.80), 0.045, 0.40),
                                                    ("hip", "knee", (0.08 * x, 0.0, 0.50), 0.06, 0.50)):
            joints = [index[f"{side}_{upper}"], index[f"{side}_{lower}"]]
            part, limb_pivots = _limb_part(joints, start, radius, length, down=True, segments=segments)
            parts.append(part)
            pivots[joints] = limb_pivots
    return _assemble("skinned_character", CHARACTER_JOINTS, parents, pivots, parts)
