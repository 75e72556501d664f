"""Frame packing without a GL: scene state and cameras -> the tensors one frame draws from.

A FramePacker holds the renderer's state (per-instance tensors of every group, the
cameras, the world origins) and turns it into plain tensors laid out as row_layouts.py says:
- one instance row per world and instance of each group (static groups: one row each);
- one view row per view: view-projection, world origin (hi + lo), near / far;
- per group, the visible (view, instance) pairs, sorted by view, and for each pass of
  the tile layout the range of pairs it draws. Under the "appearance" effect, a group whose
  variant carries floor and wall patterns lists, within each pass, the pairs of worlds whose
  patterns show first and those of plain worlds last (plain_counts), which the renderer draws
  with the variant without patterns: the pattern maths runs only where a pattern shows.

It writes straight into the tensors a backend hands it (`PackTargets`): views of the
backend's buffer memory, so packing costs no copy of its own. Each stage runs only when
its inputs changed. Nothing here knows about a GL; renderer.py draws what it packs.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Protocol

import torch

from ..assets import skinning
from ..util.transforms import look_at_quat, normalize_quat, perspective, quat_from_yaw_pitch_roll, quat_to_matrix
from ..util.validation import FLOAT_DTYPES, as_tensor, check_finite, check_host, check_range, check_shape, describe
from . import row_layouts
from .appearance import AppearanceRows
from .culling import frustum_planes, inside_frustum, mesh_radius, pair_list
from .scene import ROLES, Scene, StaticGroup, check_depth_range
from .tiling import TileLayout

# Worlds are re-centred when a camera strays this far from its world's origin, so that
# float32 positions relative to the origin stay precise (see the static-group shader).
RECENTRE_DISTANCE = 1024.0

# Camera frame (x right, y forward, z up) -> GL eye frame (x right, y up, looking down -z).
CAMERA_TO_GL = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)

# Frustum culling of a group is paused for CULL_RECHECK frames when its last test kept more
# than CULL_KEEPS of the candidate pairs: drawing those few hidden pairs costs less than
# testing every frame (cart-pole: everything is always in view).
CULL_KEEPS = 0.9
CULL_RECHECK = 32


class PackTargets(Protocol):
    """Where a frame is packed: flat tensors the packer writes into (a backend's buffer
    memory). Each is asked for only when it is written, so a backend may mark it for upload."""

    def views(self) -> torch.Tensor:
        """float32 [num_views * VIEW.texels * 4]."""

    def instances(self, group: str) -> torch.Tensor:
        """float32 [rows * texels * 4] of the group's layout (INSTANCE, or STATIC_INSTANCE)."""

    def pairs(self, group: str) -> torch.Tensor:
        """int32 [num_views * count]: the visible pairs, view * count + instance."""

    def appearance(self) -> torch.Tensor:
        """float32 [num_worlds * APPEARANCE.texels * 4] (scenes with the "appearance" effect)."""


@dataclass
class GroupPacking:
    """What the packer keeps per group: its size, bounds and the pairs of the current frame."""

    count: int  # instances per world (static: in total)
    static: bool
    radius: float  # bounding sphere of the mesh at unit scale
    joints: int  # joint matrices per instance row (skinned groups; static ones are drawn in the bind pose)
    pass_ranges: list | None = None  # [(first pair, pair count)] per pass
    plain_counts: list | None = None  # per pass, the last pairs of its range that show no pattern (surface groups)
    frustum_pause: int = 0  # frames left without frustum tests (see CULL_KEEPS)
    frustum_culled: bool = False  # whether the current pair list came from a frustum test
    static_bounds: tuple | None = None  # (centres, radii) of a static group for the current origins


class FramePacker:
    """State of scene.num_worlds x scene.agents_per_world views, packed per frame along `tiles`."""

    def __init__(self, scene: Scene, tiles: TileLayout):
        self.scene, self.tiles = scene, tiles
        W, A = scene.num_worlds, scene.agents_per_world
        self.world_origin = torch.zeros(W, 3, dtype=torch.float64)
        self.camera_position = torch.zeros(W, A, 3, dtype=torch.float64)
        self.camera_position[..., 1] = -5.0
        self.camera_position[..., 2] = 1.0
        self.camera_rotation = torch.zeros(W, A, 4)
        self.camera_rotation[..., 0] = 1.0
        self.fov_y = torch.full((W, A), float(scene.fov_y), dtype=torch.float64)
        self.near = torch.full((W, A), float(scene.near), dtype=torch.float64)
        self.far = torch.full((W, A), float(scene.far), dtype=torch.float64)
        mount = scene.camera_mount
        if mount is not None:
            tilt = None
            if mount.pitch:
                tilt = quat_to_matrix(quat_from_yaw_pitch_roll(torch.tensor(0.0, dtype=torch.float64),
                                                               torch.tensor(mount.pitch, dtype=torch.float64)))
            offset = torch.tensor(mount.offset, dtype=torch.float64)
            self._mount_constants = (torch.tensor(mount.instance), offset, tilt)
        self._mount_per_view = None  # (offset [W, A, 3], tilt [W, A, 3, 3]) once set_cameras gave mount_*
        # Each world's look (the "appearance" effect), packed when it changed.
        self.appearance = AppearanceRows(scene) if "appearance" in scene.effects else None
        self.surface_roles = surface_roles(scene)
        self._plain_worlds: dict[str, torch.Tensor] = {}  # surface group -> [W] bool: no pattern shows
        self.state: dict[str, dict[str, torch.Tensor]] = {}
        for name, group in scene.groups.items():
            C = group.capacity
            state = {
                "position": torch.zeros(W, C, 3, dtype=torch.float64),
                "rotation": torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(W, C, 1),
                "scale": torch.ones(W, C, 3),
                "color": torch.tensor([0.8, 0.8, 0.8, 1.0]).repeat(W, C, 1),
                "active": torch.zeros(W, C, dtype=torch.bool),
                "owner": torch.full((W, C), -1, dtype=torch.int64),
            }
            if isinstance(group.mesh, skinning.SkinnedMesh):  # the bind pose: every joint unrotated
                state["joints"] = torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(W, C, group.mesh.num_joints, 1)
            if mount is not None and mount.group == name and mount.hide_owner:
                state["owner"][:, list(mount.instance)] = torch.arange(A)
            self.state[name] = state
        # Static groups first, in declaration order: the draw order of the backend.
        self.groups: dict[str, GroupPacking] = {}
        for group in scene.static.values():
            self.groups[group.name] = GroupPacking(group.count, True, mesh_radius(group.mesh), 0)
        for group in scene.groups.values():
            joints = group.mesh.num_joints if isinstance(group.mesh, skinning.SkinnedMesh) else 0
            self.groups[group.name] = GroupPacking(group.capacity, False, mesh_radius(group.mesh), joints)
        # Where each field goes, as index tuples into rows viewed as [..., texels, 4], read
        # from row_layouts.py once (a lookup per field and frame cost ~10% of the pack stage).
        self._instance_rows = _indices(row_layouts.INSTANCE, leading=2)
        self._static_rows = _indices(row_layouts.STATIC_INSTANCE, leading=1)
        self._view_rows = _indices(row_layouts.VIEW, leading=1)
        self._texels = {"instance": row_layouts.INSTANCE.texels, "view": row_layouts.VIEW.texels}
        first = row_layouts.VIEW.fields["projection"].texel
        self._view_rows["projection"] = (slice(None), slice(first, first + row_layouts.VIEW_PROJECTION_TEXELS))
        self.planes = None  # frustum planes [W, A, 6, 4] of the current cameras
        self._dirty = set(scene.groups)  # groups whose instance data changed since the last frame
        self._mask_dirty = set(scene.groups)  # groups whose active / owner masks changed
        self._cameras_dirty = True  # free cameras or their lenses changed
        self._projection = None  # (lens [W, A, 4, 3], shift [W, A, 4]) float64, made again when a lens changes
        self._origin_moved = True  # world origins not yet written to the view rows
        self._candidate_cache = {}  # group -> ([W, A, C] bool candidate pairs, their count)

    # ------------------------------------------------------------------ sizes
    def instance_texels(self, group: str) -> int:
        """Texels of the group's instance buffer."""
        packing = self.groups[group]
        rows = packing.count if packing.static else self.scene.num_worlds * packing.count
        return rows * row_layouts.instance_texels(static=packing.static, joints=packing.joints)

    def pair_capacity(self, group: str) -> int:
        return self.scene.num_views * self.groups[group].count

    def view_texels(self) -> int:
        return self.scene.num_views * self._texels["view"]

    # ------------------------------------------------------------------ updates
    def update(self, group: str, *, position=None, rotation=None, scale=None, color=None, active=None,
               owner=None, joints=None) -> None:
        """See BatchRenderer.update: everything is validated before anything is stored."""
        self.check_group(group)
        state = self.state[group]
        W, C = state["active"].shape
        staged = {}
        if position is not None:
            staged["position"] = _float_arg("position", position, (W, C, 3)).to(torch.float64)
        if rotation is not None:
            rotation = _float_arg("rotation", rotation, (W, C, 4))
            staged["rotation"] = normalize_quat(rotation.to(torch.float64), name="rotation").to(torch.float32)
        if scale is not None:
            scale = _float_arg("scale", scale, (W, C, 3))
            # A mirrored instance would have its winding reversed and be culled inside out.
            check_range("scale", scale, 0.0, None)
            staged["scale"] = scale.to(torch.float32)
        if color is not None:
            color = as_tensor("color", color)
            if color.ndim == 3 and color.shape[-1] == 3:
                color = torch.cat((color, torch.ones_like(color[..., :1])), -1)
            color = _float_arg("color", color, (W, C, 4))
            check_range("color", color, 0.0, 1.0)
            staged["color"] = color.to(torch.float32)
        if active is not None:
            active = as_tensor("active", active, dtype_kind="bool")
            check_host("active", active)
            check_shape("active", active, (W, C))
            staged["active"] = active
        if owner is not None:
            owner = as_tensor("owner", owner, dtype_kind="int")
            check_host("owner", owner)
            check_shape("owner", owner, (W, C))
            signed = owner if owner.dtype.is_signed else owner.double()
            check_range("owner", signed, -1, self.scene.agents_per_world - 1)
            staged["owner"] = owner.to(torch.int64)
        if joints is not None:
            if "joints" not in state:
                raise ValueError(f"joints can only be set on a group whose mesh is a SkinnedMesh; group {group!r} "
                                 "has a rigid mesh")
            joints = _float_arg("joints", joints, state["joints"].shape)
            staged["joints"] = normalize_quat(joints.to(torch.float64), name="joints").to(torch.float32)
        for key, value in staged.items():
            state[key].copy_(value)
        if staged:
            self._dirty.add(group)
        if "active" in staged or "owner" in staged:
            self._mask_dirty.add(group)

    def set_cameras(self, *, position=None, rotation=None, look_at=None, fov_y=None, near=None, far=None,
                    mount_offset=None, mount_pitch=None) -> None:
        """See BatchRenderer.set_cameras: everything is validated before anything is stored."""
        W, A = self.scene.num_worlds, self.scene.agents_per_world
        mounted = self.scene.camera_mount is not None
        if mounted and (position is not None or rotation is not None or look_at is not None):
            raise ValueError("cameras are mounted on instances (scene.mount_cameras); position/rotation/look_at "
                             "cannot be set, move the instances instead")
        mount = self._mount_arguments(mount_offset, mount_pitch) if mounted else None
        if not mounted and (mount_offset is not None or mount_pitch is not None):
            raise ValueError("mount_offset and mount_pitch apply to cameras mounted on instances "
                             "(scene.mount_cameras); these cameras are free: set position and rotation instead")
        if rotation is not None and look_at is not None:
            raise ValueError("give either rotation or look_at, not both")
        staged = {}
        if position is not None:
            staged["position"] = _float_arg("position", position, (W, A, 3)).to(torch.float64)
        eye = staged.get("position", self.camera_position)
        if rotation is not None:
            rotation = _float_arg("rotation", rotation, (W, A, 4))
            staged["rotation"] = normalize_quat(rotation.to(torch.float64), name="rotation").to(torch.float32)
        if look_at is not None:
            target = _float_arg("look_at", look_at, (W, A, 3)).to(torch.float64)
            staged["rotation"] = look_at_quat(eye, target).to(torch.float32)
        for name, value, low, high in (("fov_y", fov_y, 1e-6, math.pi - 1e-6), ("near", near, 1e-9, None),
                                        ("far", far, 1e-9, None)):
            if value is not None:
                tensor = as_tensor(name, value).detach().to(torch.float64)
                check_host(name, tensor)
                tensor = tensor.expand(W, A) if tensor.ndim == 0 else tensor
                check_shape(name, tensor, (W, A))
                check_finite(name, tensor)
                check_range(name, tensor, low, high)
                staged[name] = tensor
        near_new, far_new = staged.get("near", self.near), staged.get("far", self.far)
        if bool((far_new <= near_new).any()):
            raise ValueError("far must be greater than near for every camera")
        check_depth_range(near_new, far_new, "log_depth" in self.scene.effects)
        for key, value in staged.items():
            target = {"position": self.camera_position, "rotation": self.camera_rotation}.get(key)
            (target if target is not None else getattr(self, key)).copy_(value)
        if mount is not None:
            self._mount_per_view = mount
        if staged or mount is not None:
            self._cameras_dirty = True
        if {"fov_y", "near", "far"} & staged.keys():
            self._projection = None

    def _mount_arguments(self, offset, pitch):
        """(offset [W, A, 3], tilt [W, A, 3, 3]) float64 of mounted cameras with per-view mount_offset /
        mount_pitch (each defaults to the current value), or None when neither is given."""
        if offset is None and pitch is None:
            return None
        W, A = self.scene.num_worlds, self.scene.agents_per_world
        mount = self.scene.camera_mount
        if offset is None:
            current = self._mount_per_view
            offset = current[0] if current is not None else torch.tensor(mount.offset, dtype=torch.float64)
        offset = _broadcast_arg("mount_offset", offset, (W, A, 3)).to(torch.float64)
        if pitch is None:
            tilt = self._mount_per_view[1] if self._mount_per_view is not None else None
        else:
            pitch = _broadcast_arg("mount_pitch", pitch, (W, A)).to(torch.float64)
            check_range("mount_pitch", pitch, -math.pi / 2, math.pi / 2)
            tilt = quat_to_matrix(quat_from_yaw_pitch_roll(torch.zeros_like(pitch), pitch))
        if tilt is None:
            tilt = quat_to_matrix(quat_from_yaw_pitch_roll(torch.zeros(W, A, dtype=torch.float64),
                                                           torch.full((W, A), mount.pitch, dtype=torch.float64)))
        return offset.clone(), tilt

    def check_group(self, group) -> None:
        if not isinstance(group, str):
            raise TypeError("group must be the name (str) of one of this scene's instance groups "
                            f"{sorted(self.state)}, got {describe(group)}")
        if group not in self.state:
            raise ValueError(f"group must be one of this scene's instance groups {sorted(self.state)}, got {group!r}")

    # ------------------------------------------------------------------ packing
    def pack_static(self, group: StaticGroup, target: torch.Tensor) -> None:
        """A static group's rows (once: they never change), its absolute positions as hi + lo."""
        row = self._static_rows
        memory = target.view(group.count, row_layouts.instance_texels(static=True), 4)
        hi = group.position.to(torch.float32)
        memory[row["position"]] = hi
        memory[row["active"]] = 1.0
        memory[row["rotation"]] = group.rotation
        memory[row["scale"]] = group.scale
        memory[row["owner"]] = -1.0
        memory[row["color"]] = group.color
        memory[row["position_lo"]] = (group.position - hi.to(torch.float64)).to(torch.float32)
        memory[row["role"]] = 0.0 if group.role is None else group.role.to(torch.float32)

    def prepare(self, targets: PackTargets) -> dict:
        """The packing stages of a frame, each only when its inputs changed: camera poses
        and view rows (cameras moved), instance rows (groups updated), visible pairs (either).
        Returns {"packed": groups whose rows were written, "pack" / "cull": seconds}."""
        start = time.perf_counter()
        mount = self.scene.camera_mount
        cameras_moved = self._cameras_dirty or (mount is not None and mount.group in self._dirty)
        if cameras_moved:
            position, rotation = self.camera_frames()
            self._recentre(position)
            self.planes = frustum_planes(self._pack_views(targets.views(), position, rotation))
            self._cameras_dirty = False
        packed_groups = list(self._dirty)
        for name in packed_groups:
            self._pack_group(name, targets.instances(name))
        if self.appearance is not None and self.appearance.dirty:
            targets.appearance().copy_(self.appearance.rows.reshape(-1))
            self.appearance.dirty = False
            self._split_surfaces()
        self._dirty.clear()
        packed = time.perf_counter()
        self._cull(set(packed_groups), cameras_moved, targets)
        self._mask_dirty.clear()
        return {"packed": packed_groups, "pack": packed - start, "cull": time.perf_counter() - packed}

    def camera_frames(self):
        """Camera positions [W, A, 3] and camera-to-world rotations [W, A, 3, 3], float64."""
        mount = self.scene.camera_mount
        if mount is None:
            return self.camera_position, quat_to_matrix(self.camera_rotation.to(torch.float64))
        state = self.state[mount.group]
        index, offset, tilt = self._mount_constants
        body = quat_to_matrix(state["rotation"][:, index].to(torch.float64))
        if self._mount_per_view is not None:  # set_cameras(mount_offset=, mount_pitch=): one per view
            offset, tilt = self._mount_per_view
            return state["position"][:, index] + (body @ offset[..., None])[..., 0], body @ tilt
        position = state["position"][:, index] + body @ offset
        return position, body if tilt is None else body @ tilt

    def _recentre(self, camera_position: torch.Tensor):
        distance = (camera_position - self.world_origin[:, None]).norm(dim=-1).amax(dim=1)
        far_worlds = distance > RECENTRE_DISTANCE
        if bool(far_worlds.any()):
            self.world_origin[far_worlds] = camera_position[far_worlds].mean(dim=1)
            self._dirty.update(self.scene.groups)
            self._origin_moved = True
            for packing in self.groups.values():
                packing.static_bounds = None

    def _pack_views(self, target: torch.Tensor, position: torch.Tensor, rotation: torch.Tensor):
        """View-projections [W, A, 4, 4] of cameras at `position` with camera-to-world
        `rotation` [W, A, 3, 3], written to the view rows (and origins / lenses when changed)."""
        row = self._view_rows
        memory = target.view(-1, self._texels["view"], 4)
        if self._projection is None or self._origin_moved:  # lenses or world origins changed
            height, width = self.scene.resolution
            projection = perspective(self.fov_y, width / height, self.near, self.far)
            # The camera frame (x right, y forward, z up) to GL's eye frame folded into the lens.
            self._projection = (projection[..., :3] @ CAMERA_TO_GL, projection[..., 3])
            origin_hi = self.world_origin.to(torch.float32)
            origin_lo = (self.world_origin - origin_hi.to(torch.float64)).to(torch.float32)
            A = self.scene.agents_per_world
            memory[row["origin_hi"]] = origin_hi.repeat_interleave(A, dim=0)
            memory[row["origin_lo"]] = origin_lo.repeat_interleave(A, dim=0)
            memory[row["near"]] = self.near.reshape(-1)
            memory[row["far"]] = self.far.reshape(-1)
            self._origin_moved = False
        lens, lens_shift = self._projection
        linear = lens @ rotation.transpose(-1, -2)  # [W, A, 4, 3]: world directions to clip space
        shift = lens_shift - (linear @ (position - self.world_origin[:, None])[..., None])[..., 0]
        view_projection = torch.cat((linear, shift[..., None]), -1)
        memory[row["projection"]] = view_projection.reshape(-1, 4, 4).transpose(1, 2)  # texel j = column j
        return view_projection

    def _pack_group(self, name: str, target: torch.Tensor):
        state, row = self.state[name], self._instance_rows
        W, C = state["active"].shape
        joints = self.groups[name].joints
        memory = target.view(W, C, self._texels["instance"] + row_layouts.JOINT_TEXELS * joints, 4)
        memory[row["position"]] = state["position"] - self.world_origin[:, None]
        memory[row["active"]] = state["active"]
        memory[row["rotation"]] = state["rotation"]
        memory[row["scale"]] = state["scale"]
        memory[row["owner"]] = state["owner"]
        memory[row["color"]] = state["color"]
        if joints:  # the bind-to-pose matrix of every joint, after the instance's own texels
            transforms = skinning.joint_transforms(self.scene.groups[name].mesh, state["joints"])
            memory[:, :, self._texels["instance"]:] = transforms.view(W, C, -1, 4)

    # ------------------------------------------------------------------ culling
    def _cull(self, moved: set, cameras_moved: bool, targets: PackTargets):
        """Bring each group's list of drawn (view, instance) pairs up to date.

        A group whose instances and cameras did not move keeps its list. Frustum tests of
        all groups that need one run as one batched test; a group whose last test showed
        nothing worth culling draws its candidate pairs (active, not the viewer's own body)
        for CULL_RECHECK frames instead."""
        tested, candidates_only = [], []
        for name, packing in self.groups.items():
            mask_changed = name in self._mask_dirty
            if not (cameras_moved or name in moved or mask_changed):
                continue
            if packing.frustum_pause == 0:
                tested.append(name)
            else:
                packing.frustum_pause -= 1
                if mask_changed or packing.frustum_culled:
                    candidates_only.append(name)
        for name in candidates_only:
            candidate, _ = self._candidates(name)
            self._store_pairs(name, pair_list(candidate) if candidate is not None else None, False, targets)
        if not tested:
            return
        centers, radii = zip(*(self._bounds(name) for name in tested), strict=True)
        inside = inside_frustum(self.planes, torch.cat(centers, 1), torch.cat(radii, 1))
        first = 0
        for name, count in zip(tested, (c.shape[1] for c in centers), strict=True):
            visible = inside[:, :, first:first + count]
            first += count
            candidate, possible = self._candidates(name)
            pairs = pair_list(visible if candidate is None else visible & candidate)
            if len(pairs) > CULL_KEEPS * possible:
                self.groups[name].frustum_pause = CULL_RECHECK
            self._store_pairs(name, pairs, True, targets)

    def light_pairs(self, planes: torch.Tensor) -> dict:
        """{group: int32 pairs world * count + instance} of the instances inside each world's light
        frustum (planes [W, 1, 6, 4], relative to the world origins): what a shadow pass draws.
        Active instances only, owners included (a body casts its shadow into its own view too)."""
        out = {}
        for name, packing in self.groups.items():
            centers, radii = self._bounds(name)
            inside = inside_frustum(planes, centers, radii)  # [W, 1, K]
            if not packing.static:
                inside &= self.state[name]["active"][:, None, :]
            out[name] = pair_list(inside)
        return out

    def _bounds(self, name: str):
        """Bounding-sphere centres [W, K, 3] (relative to the world origin) and radii [W, K] of a
        group (scales are >= 0); those of static groups are kept until the world origins move."""
        packing, W = self.groups[name], self.scene.num_worlds
        if packing.static:
            if packing.static_bounds is None:
                group = self.scene.static[name]
                packing.static_bounds = (group.position[None] - self.world_origin[:, None],
                                         (packing.radius * group.scale.amax(-1)).expand(W, -1))
            return packing.static_bounds
        state = self.state[name]
        return state["position"] - self.world_origin[:, None], state["scale"].amax(-1) * packing.radius

    def _candidates(self, name: str):
        """([W, A, C] bool, count): the instance is active and not the viewing agent's own body
        ((None, all pairs) for static groups); kept until the group's masks change."""
        packing = self.groups[name]
        if packing.static:
            return None, self.scene.num_views * packing.count
        if name in self._mask_dirty or name not in self._candidate_cache:
            state = self.state[name]
            agent = torch.arange(self.scene.agents_per_world)[None, :, None]
            candidate = state["active"][:, None, :] & (state["owner"][:, None, :] != agent)
            self._candidate_cache[name] = (candidate, int(candidate.sum()))
        return self._candidate_cache[name]

    def _split_surfaces(self):
        """Which worlds show no pattern on each surface group (after the looks changed); their pairs
        are listed again."""
        plain = self.appearance.plain_surfaces()  # [W, 2]: floor, wall
        for name, roles in self.surface_roles.items():
            self._plain_worlds[name] = plain[:, [role - 1 for role in roles]].all(-1)
            self._mask_dirty.add(name)

    def _store_pairs(self, name: str, pairs: torch.Tensor | None, culled: bool, targets: PackTargets):
        """Write a group's drawn pairs (None: every pair of a static group) and split them per pass."""
        packing = self.groups[name]
        total = self.scene.num_views * packing.count
        if pairs is None:
            pairs = torch.arange(total, dtype=torch.int32)
        if self.tiles.num_passes == 1:
            packing.pass_ranges = [(0, len(pairs))]
        else:
            starts = torch.tensor([self.tiles.pass_views(p).start * packing.count
                                   for p in range(self.tiles.num_passes)] + [total], dtype=torch.int32)
            bounds = torch.searchsorted(pairs, starts).tolist()
            packing.pass_ranges = [(bounds[p], bounds[p + 1] - bounds[p]) for p in range(self.tiles.num_passes)]
        plain_worlds = self._plain_worlds.get(name)
        if plain_worlds is not None:
            pairs, packing.plain_counts = self._plain_last(pairs, plain_worlds, packing)
        if len(pairs):
            targets.pairs(name)[: len(pairs)] = pairs
        packing.frustum_culled = culled

    def _plain_last(self, pairs: torch.Tensor, plain_worlds: torch.Tensor, packing: GroupPacking):
        """(pairs, plain count per pass): within each pass's range, the pairs of worlds that show a
        pattern, then those of plain worlds, each still in view order (a stable sort)."""
        plain = plain_worlds[pairs.long() // (packing.count * self.scene.agents_per_world)]
        passes = len(packing.pass_ranges)
        pass_of = torch.repeat_interleave(torch.arange(passes), torch.tensor([n for _, n in packing.pass_ranges]))
        counts = torch.zeros(passes, dtype=torch.int64).index_add_(0, pass_of, plain.long())
        if 0 < int(counts.sum()) < len(pairs):
            pairs = pairs[torch.sort(pass_of * 2 + plain.long(), stable=True).indices]
        return pairs, counts.tolist()


def _float_arg(name, value, shape):
    tensor = as_tensor(name, value).detach()  # the renderer's state never joins an autograd graph
    tensor = tensor if tensor.dtype in FLOAT_DTYPES else tensor.float()  # float8: no isfinite kernel
    check_host(name, tensor)
    check_shape(name, tensor, shape)
    check_finite(name, tensor)
    return tensor


def _broadcast_arg(name, value, shape):
    """_float_arg of a value that may broadcast to `shape` (one value for every view, or per world)."""
    tensor = as_tensor(name, value)
    try:
        tensor = torch.broadcast_to(tensor, shape)
    except RuntimeError:
        raise ValueError(f"{name} must have shape {list(shape)} (or broadcast to it), "
                         f"got {list(tensor.shape)}") from None
    return _float_arg(name, tensor, shape)


def _indices(table: row_layouts.RowLayout, leading: int) -> dict:
    """{field: index tuple} into rows viewed as [*leading dims, texels, 4]."""
    return {name: (slice(None),) * leading + table[name] for name in table.fields}


def surface_roles(scene: Scene) -> dict[str, tuple[int, ...]]:
    """{group: the role codes (scene.ROLES) of its instances} of the groups whose shader variants carry
    the appearance effect's floor and wall patterns: those with a role, when the scene declares the
    effect with surface_patterns (static groups first, as drawn)."""
    if "appearance" not in scene.effects or not scene.surface_patterns:
        return {}
    roles = {name: () if group.role is None else tuple(sorted(set(group.role.tolist()) - {0}))
             for name, group in scene.static.items()}
    roles.update((name, (ROLES[group.role],) if ROLES[group.role] else ()) for name, group in scene.groups.items())
    return {name: codes for name, codes in roles.items() if codes}
