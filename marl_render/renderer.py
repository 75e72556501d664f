"""The batch renderer: every view of every world in one instanced pass per mesh group.

Per step:
1. pack the groups that changed into their buffer textures (one row per world
   instance, read by all A views of that world);
2. pack one view-projection per view when a camera moved (cameras free or mounted on
   instances), and list the visible (view, instance) pairs when anything moved;
3. one draw per mesh group and framebuffer with instance count = visible pairs; the
   vertex shader places view v in its tile (one column of tiles per framebuffer) and
   clips it to that tile;
4. once every framebuffer is drawn, one GL read per framebuffer straight into the
   batch tensor (marl_render/readback.py).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import numpy as np
import torch

from . import backend, readback, shaders, skinning
from .images import texture_pixels
from .meshes import MeshData, to_panda_geom
from .provoking import shared_corner_mesh
from .scene import Scene, StaticGroup
from .shadows import ShadowPass
from .triangle_corners import to_panda_geom_with_corners
from .culling import frustum_planes, inside_frustum, mesh_radius, pair_list
from .threads import one_thread
from .tiling import TileLayout, column_layout
from .transforms import look_at_quat, normalize_quat, perspective, quat_from_yaw_pitch_roll, quat_to_matrix
from .validation import FLOAT_DTYPES, as_tensor, check_finite, check_host, check_range, check_shape, describe, positive_int

# Worlds are re-centred when a camera strays this far from its world's origin, so that
# float32 positions relative to the origin stay precise (see the static-group shader).
RECENTRE_DISTANCE = 1024.0

# Camera frame (x right, y forward, z up) -> GL eye frame (x right, y up, looking down -z).
_CAMERA_TO_GL = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)

# Frustum culling of a group is paused for CULL_RECHECK frames when its last test kept more
# than CULL_KEEPS of the candidate pairs: drawing those few hidden pairs costs less than
# testing every frame (cart-pole: everything is always in view).
CULL_KEEPS = 0.9
CULL_RECHECK = 32


@dataclass
class Frame:
    """One render: rgb [W, A, H, W, C] uint8 (or [W, A, C, H, W]; C = 3, or 1 for color="gray"),
    depth [W, A, H, W] float32 metres along the view axis (inf where nothing was drawn),
    segmentation [W, A, H, W] int32 (0 = background). Tensors are owned by the caller."""

    rgb: torch.Tensor
    depth: torch.Tensor | None = None
    segmentation: torch.Tensor | None = None


def _buffer_texture(name: str, texels: int, integer: bool = False):
    from panda3d.core import GeomEnums, Texture

    texture = Texture(name)
    kind, fmt = (Texture.T_int, Texture.F_r32i) if integer else (Texture.T_float, Texture.F_rgba32)
    texture.setup_buffer_texture(max(texels, 1), kind, fmt, GeomEnums.UH_dynamic)
    return texture


def _writable(texture, dtype) -> torch.Tensor:
    """Flat torch view of a texture's RAM image; marks the texture for upload."""
    return torch.from_numpy(np.frombuffer(memoryview(texture.modify_ram_image()), dtype=dtype))


@dataclass
class _DrawGroup:
    """GL side of one group: its nodes (one per framebuffer), instance data, visible pairs, bounds."""

    node: object  # the node drawn in the first framebuffer (the others are copies of it)
    count: int  # instances per world (static: in total)
    static: bool
    instances: object  # float32 buffer texture
    pairs: object  # int32 buffer texture: visible view * count + instance
    radius: float  # bounding sphere of the mesh at unit scale
    texels: int = shaders.INSTANCE_TEXELS  # per instance: more for skinned groups (their joints)
    pass_ranges: list | None = None  # [(first pair, pair count)] per pass
    pass_nodes: list | None = None  # [(NodePath, PTA_int pair offset, instance count drawn)] per pass
    frustum_pause: int = 0  # frames left without frustum tests (see CULL_KEEPS)
    frustum_culled: bool = False  # whether the current pair list came from a frustum test
    static_bounds: tuple | None = None  # (centres, radii) of a static group for the current origins


@dataclass
class _Pass:
    """One framebuffer: a column of up to layout.rows views, its scene root and render textures."""

    views: range
    buffer: object  # Panda3D GraphicsBuffer
    root: object  # NodePath holding this pass's copy of every group node
    color: object  # Texture rendered into (RGBA8)
    aux: dict  # name -> Texture of the depth / segmentation outputs
    texture_ids: dict | None = None  # GL names of the textures, known after the first frame


class BatchRenderer:
    """Renders scene.num_worlds x scene.agents_per_world views per call of render()."""

    READBACKS = ("zero_copy", "copy")
    COLORS = {"rgb": 3, "gray": 1}  # color -> channels of Frame.rgb

    def __init__(self, scene: Scene, *, channels_first: bool = False, max_framebuffer_size: int | None = None,
                 egl_device_index: int | None = None, readback: str = "zero_copy", supersample: int = 1,
                 multisamples: int = 0, color: str = "rgb"):
        """readback: "zero_copy" (default) reads each framebuffer straight into the output
        tensor; "copy" reads it into a buffer first and copies that into the output (the
        usual way, kept only so that benchmarks can show what the direct read saves).
        color="gray": one channel, ITU-R BT.601 luma computed in the fragment shader, so
        a third of the bytes is read back (and channels_first costs no copy).
        supersample=k renders every view at k x the resolution and box-filters it down
        (anti-aliasing; depth and segmentation take the sample nearest each pixel centre).
        multisamples=n asks the GL for n-sample MSAA (colour only)."""
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a marl_render.Scene, got {describe(scene)}")
        if readback not in self.READBACKS:
            raise ValueError(f"readback must be one of {list(self.READBACKS)}, got {readback!r}")
        if not isinstance(color, str) or color not in self.COLORS:
            raise ValueError(f"color must be one of {list(self.COLORS)}, got {color!r}")
        self.color, self.channels = color, self.COLORS[color]
        self.supersample = positive_int("supersample", supersample)
        self._staging = self._accumulator = None  # reused buffers of reads that need a copy afterwards
        if isinstance(multisamples, bool) or not isinstance(multisamples, int) or multisamples < 0:
            raise ValueError(f"multisamples must be an int >= 0, got {multisamples!r}")
        if multisamples and {"depth", "segmentation"} & set(scene.effects):
            raise ValueError("multisamples cannot be combined with the depth or segmentation outputs (their "
                             "bit-packed samples would be averaged); use supersample instead")
        self.multisamples = multisamples
        self.scene = scene
        self.readback = readback
        self.channels_first = bool(channels_first)
        self.last_timings: dict[str, float] = {}  # seconds per stage of the last render()
        self._closed = False
        self._context = backend.context(egl_device_index)
        gl_max = self._context.info().max_framebuffer_size
        if max_framebuffer_size is None:
            max_framebuffer_size = gl_max
        if not isinstance(max_framebuffer_size, int) or not 1 <= max_framebuffer_size <= gl_max:
            raise ValueError(f"max_framebuffer_size must be an int in [1, {gl_max}], got {max_framebuffer_size!r}")
        height, width = scene.resolution
        k = self.supersample
        self.layout: TileLayout = column_layout(scene.num_views, height * k, width * k, max_framebuffer_size)
        self.effects = frozenset(scene.effects)
        self._init_state()
        self._passes: list[_Pass] = []
        self._groups = {}
        self.shadow_pass = None
        try:
            # Panda3D opens each framebuffer right away; until it is inactive, any frame
            # drawn by another thread would draw it too.
            with self._context.current():
                self._build_passes()
                self._build_groups()
                if "shadows" in self.effects:
                    self.shadow_pass = ShadowPass(self._context, scene, self._groups, gl_max)
                    for render_pass in self._passes:
                        self.shadow_pass.bind(render_pass.root)
        except BaseException:
            self.close()  # free whatever GL objects were made before the failure
            raise

    # ------------------------------------------------------------------ state
    def _init_state(self):
        s = self.scene
        W, A = s.num_worlds, s.agents_per_world
        self.world_origin = torch.zeros(W, 3, dtype=torch.float64)
        self.camera_position = torch.zeros(W, A, 3, dtype=torch.float64)
        self.camera_position[..., 1] = -5.0
        self.camera_position[..., 2] = 1.0
        self.camera_rotation = torch.zeros(W, A, 4)
        self.camera_rotation[..., 0] = 1.0
        self.fov_y = torch.full((W, A), float(s.fov_y), dtype=torch.float64)
        self.near = torch.full((W, A), float(s.near), dtype=torch.float64)
        self.far = torch.full((W, A), float(s.far), dtype=torch.float64)
        mount = s.camera_mount
        if mount is not None:
            tilt = None
            if mount.pitch:
                tilt = quat_to_matrix(quat_from_yaw_pitch_roll(torch.tensor(0.0, dtype=torch.float64),
                                                               torch.tensor(mount.pitch, dtype=torch.float64)))
            self._mount_constants = (torch.tensor(mount.instance), torch.tensor(mount.offset, dtype=torch.float64), tilt)
        self._state = {}
        for name, group in s.groups.items():
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
            self._state[name] = state
        self._dirty = set(s.groups)  # groups whose instance data changed since the last frame
        self._mask_dirty = set(s.groups)  # groups whose active / owner masks changed
        self._cameras_dirty = True  # free cameras or their lenses changed
        self._projection = None  # (lens [W, A, 4, 3], shift [W, A, 4]) float64, made again when a lens changes
        self._origin_moved = True  # world origins not yet written to the views texture
        self._candidate_cache = {}  # group -> ([W, A, C] bool candidate pairs, their count)

    # ------------------------------------------------------------------ GL objects
    def _build_passes(self):
        """One framebuffer per column of views, each with its own scene root and camera."""
        from panda3d.core import LVecBase2f

        self.views_texture = _buffer_texture("views", self.scene.num_views * shaders.VIEW_TEXELS)
        lighting, fog = self.scene.lighting, self.scene.fog
        direction = np.asarray(lighting.direction, dtype=float)
        self._shared_inputs = {
            "views": self.views_texture, "agents": _int(self.scene.agents_per_world),
            "light_direction": _vec3(direction / np.linalg.norm(direction)), "light_color": _vec3(lighting.color),
            "ambient_color": _vec3(lighting.ambient), "fog_color": _vec3(fog.color),
            "fog_density": float(fog.density),
            "tile_size": LVecBase2f(self.layout.tile_width, self.layout.tile_height)}
        for index in range(self.layout.num_passes):
            self._passes.append(self._make_pass(self.layout.pass_views(index)))

    def _make_pass(self, views: range) -> _Pass:
        from panda3d.core import (Camera, ColorBlendAttrib, CullFaceAttrib, DepthTestAttrib, DepthWriteAttrib,
                                  FrameBufferProperties, GraphicsOutput, GraphicsPipe, NodePath,
                                  OmniBoundingVolume, Texture, TransparencyAttrib, WindowProperties)

        ctx, layout = self._context, self.layout
        width, height = layout.tile_width, layout.tile_height * len(views)
        aux_names = [e for e in ("depth", "segmentation") if e in self.effects]
        props = FrameBufferProperties()
        props.set_rgba_bits(8, 8, 8, 8)
        props.set_depth_bits(24)
        props.set_aux_rgba(len(aux_names))
        props.set_multisamples(self.multisamples)
        # One name for all buffers: Panda3D keeps a statistics collector per buffer name
        # for the life of the process (a unique name per renderer leaked about 3 KB each).
        buffer = ctx.engine.make_output(
            ctx.pipe, "marl_render", 0, props, WindowProperties.size(width, height),
            GraphicsPipe.BF_refuse_window, ctx.gsg, ctx.host)
        if buffer is None:
            raise backend.GLUnavailableError(
                f"could not create a {width}x{height} offscreen framebuffer with {len(aux_names)} aux targets; "
                "lower resolution / num views or max_framebuffer_size")
        # Render into textures that stay in GL; readback.py reads them once all passes are drawn.
        color = Texture("color")
        buffer.add_render_texture(color, GraphicsOutput.RTM_bind_or_copy, GraphicsOutput.RTP_color)
        aux = {}
        for index, name in enumerate(aux_names):
            texture = Texture(name)
            plane = GraphicsOutput.RTP_aux_rgba_0 + index
            buffer.add_render_texture(texture, GraphicsOutput.RTM_bind_or_copy, plane)
            # Clear values as RGBA bytes of the little-endian value: depth +inf (0x7f800000), segment 0.
            clear = (0.0, 0.0, 128 / 255, 127 / 255) if name == "depth" else (0.0, 0.0, 0.0, 0.0)
            buffer.set_clear_active(plane, True)
            buffer.set_clear_value(plane, clear)
            aux[name] = texture
        ctx.drop_render_texture_events()
        background = np.asarray(self.scene.background[:3], dtype=float)
        if self.color == "gray":  # the shader's luma of the background
            background = np.full(3, float(np.dot(background, shaders.GRAY_WEIGHTS)))
        buffer.set_clear_color(tuple(background) + (1.0,))
        buffer.set_active(False)

        root = NodePath(f"marl_render_pass_{views.start}")
        camera = Camera("tiles")
        camera.set_cull_bounds(OmniBoundingVolume())
        buffer.make_display_region().set_camera(root.attach_new_node(camera))
        # The per-view vertical flip reverses winding: cull the other side.
        root.set_attrib(CullFaceAttrib.make(CullFaceAttrib.M_cull_counter_clockwise))
        root.set_attrib(DepthTestAttrib.make(DepthTestAttrib.M_less))
        root.set_attrib(DepthWriteAttrib.make(DepthWriteAttrib.M_on))
        root.set_transparency(TransparencyAttrib.M_none)
        root.set_attrib(ColorBlendAttrib.make_off())
        for name, value in self._shared_inputs.items():
            root.set_shader_input(name, value)
        root.set_shader_input("tiles", _int(len(views)))
        root.set_shader_input("view_offset", _int(views.start))
        return _Pass(views, buffer, root, color, aux)

    def _build_groups(self):
        from panda3d.core import NodePath, OmniBoundingVolume

        self._groups: dict[str, _DrawGroup] = {}
        groups = [(g, True) for g in self.scene.static.values()] + [(g, False) for g in self.scene.groups.values()]
        for order, (group, static) in enumerate(groups):
            mesh = group.mesh
            textured = group.texture is not None
            # Static geometry has no joints to pose: a skinned mesh is drawn in its bind pose.
            joints = mesh.num_joints if isinstance(mesh, skinning.SkinnedMesh) and not static else 0
            procedural = isinstance(mesh, MeshData) and not joints
            if joints:
                # Skin columns beside the vertex; its depth plane comes from the geometry
                # shader, which sees the skinned corners (a triangle's corners follow joints
                # of their own, which the corner attributes of triangle_corners.py would not).
                node = NodePath(skinning.panda_geom(mesh))
            elif not procedural:
                node = mesh.copy_to(NodePath())
            elif "depth" in self.effects:
                # The depth output needs each triangle's corners at a provoking vertex of its
                # own (triangle_corners.py), which rules out shared corners.
                node = NodePath(to_panda_geom_with_corners(mesh))
            elif mesh.flat and not (textured and "texture" in self.effects):
                # Untextured flat meshes are drawn from their shared corners (8 vertices a box, not 24).
                node = NodePath(to_panda_geom(shared_corner_mesh(mesh)))
            else:
                node = NodePath(to_panda_geom(mesh))
            # A fixed draw order: Panda3D would otherwise sort by render state (memory
            # addresses), and surfaces that touch exactly would tie differently per run.
            node.set_bin("fixed", order)
            node.node().set_bounds(OmniBoundingVolume())
            node.node().set_final(True)
            defines = shaders.defines_for(self.effects, static=static, textured=textured,
                                          flat=procedural and mesh.flat, corners=procedural,
                                          gray=self.color == "gray", shadow_pcf=self.scene.shadows.pcf,
                                          joints=joints, influences=mesh.influences if joints else 4)
            node.set_shader(shaders.compiled(defines))
            if textured and "texture" in self.effects:
                node.set_texture(_panda_texture(group.texture, group.name), 1)
            count = group.count if static else group.capacity
            rows = count if static else self.scene.num_worlds * count
            texels = (shaders.STATIC_INSTANCE_TEXELS if static
                      else shaders.INSTANCE_TEXELS + shaders.JOINT_TEXELS * joints)
            draw = _DrawGroup(node, count, static, _buffer_texture(f"instances:{group.name}", rows * texels),
                              _buffer_texture(f"pairs:{group.name}", self.scene.num_views * count, integer=True),
                              mesh_radius(mesh), texels)
            node.set_shader_input("instances", draw.instances)
            node.set_shader_input("pairs", draw.pairs)
            node.set_shader_input("capacity", _int(count))
            node.set_shader_input("segment_base", _int(group.segment_base))
            # One copy of the node per framebuffer (they share the geometry), each with its
            # own pair offset and instance count.
            draw.pass_nodes = []
            for index, render_pass in enumerate(self._passes):
                if index == 0:
                    node.reparent_to(render_pass.root)
                copy = node if index == 0 else node.copy_to(render_pass.root)
                offset = _int(0)  # updated in place (a new PTA would make a new render state)
                copy.set_shader_input("pair_offset", offset)
                draw.pass_nodes.append([copy, offset, None])
            self._groups[group.name] = draw
            if static:
                self._pack_static(group, draw)

    def _pack_static(self, group: StaticGroup, draw: _DrawGroup):
        memory = _writable(draw.instances, np.float32).view(group.count, shaders.STATIC_INSTANCE_TEXELS, 4)
        hi = group.position.to(torch.float32)
        memory[:, 0, :3] = hi
        memory[:, 0, 3] = 1.0
        memory[:, 1] = group.rotation
        memory[:, 2, :3] = group.scale
        memory[:, 2, 3] = -1.0
        memory[:, 3] = group.color
        memory[:, 4, :3] = (group.position - hi.to(torch.float64)).to(torch.float32)
        memory[:, 4, 3] = 0.0

    # ------------------------------------------------------------------ public updates
    @one_thread
    def update(self, group: str, *, position=None, rotation=None, scale=None, color=None, active=None,
               owner=None, joints=None) -> None:
        """Set per-instance data of a group for all worlds: tensors shaped [W, C, ...].

        position [W,C,3] (float32/64, metres), rotation [W,C,4] unit quaternions (w,x,y,z;
        normalised here), scale [W,C,3], color [W,C,4] or [W,C,3] in [0,1], active [W,C] bool,
        owner [W,C] int agent index (-1: none); joints [W,C,J,4] (groups of a SkinnedMesh with
        J joints): each joint's rotation about its pivot in its parent's frame, non-zero
        quaternions (w,x,y,z; normalised here). Everything is validated before anything is stored.
        """
        self._check_open()
        self._check_group(group)
        state = self._state[group]
        W, C = state["active"].shape
        staged = {}
        if position is not None:
            staged["position"] = self._float_arg("position", position, (W, C, 3)).to(torch.float64)
        if rotation is not None:
            rotation = self._float_arg("rotation", rotation, (W, C, 4))
            staged["rotation"] = normalize_quat(rotation.to(torch.float64), name="rotation").to(torch.float32)
        if scale is not None:
            scale = self._float_arg("scale", scale, (W, C, 3))
            # A mirrored instance would have its winding reversed and be culled inside out.
            check_range("scale", scale, 0.0, None)
            staged["scale"] = scale.to(torch.float32)
        if color is not None:
            color = as_tensor("color", color)
            if color.ndim == 3 and color.shape[-1] == 3:
                color = torch.cat((color, torch.ones_like(color[..., :1])), -1)
            color = self._float_arg("color", color, (W, C, 4))
            check_range("color", color, 0.0, 1.0)
            staged["color"] = color.to(torch.float32)
        if active is not None:
            active = as_tensor("active", active, dtype_kind="bool")
            self._check_device("active", active)
            check_shape("active", active, (W, C))
            staged["active"] = active
        if owner is not None:
            owner = as_tensor("owner", owner, dtype_kind="int")
            self._check_device("owner", owner)
            check_shape("owner", owner, (W, C))
            check_range("owner", owner if owner.dtype.is_signed else owner.double(), -1, self.scene.agents_per_world - 1)
            staged["owner"] = owner.to(torch.int64)
        if joints is not None:
            if "joints" not in state:
                raise ValueError(f"joints can only be set on a group whose mesh is a SkinnedMesh; group {group!r} "
                                 "has a rigid mesh")
            joints = self._float_arg("joints", joints, state["joints"].shape)
            staged["joints"] = normalize_quat(joints.to(torch.float64), name="joints").to(torch.float32)
        for key, value in staged.items():
            state[key].copy_(value)
        if staged:
            self._dirty.add(group)
        if "active" in staged or "owner" in staged:
            self._mask_dirty.add(group)

    @one_thread
    def set_cameras(self, *, position=None, rotation=None, look_at=None, fov_y=None, near=None, far=None) -> None:
        """Free cameras: position [W,A,3], rotation [W,A,4] or look_at [W,A,3] targets;
        fov_y (radians), near, far: scalars or [W,A]. Mounted cameras take only fov_y/near/far."""
        self._check_open()
        W, A = self.scene.num_worlds, self.scene.agents_per_world
        mounted = self.scene.camera_mount is not None
        if mounted and (position is not None or rotation is not None or look_at is not None):
            raise ValueError("cameras are mounted on instances (scene.mount_cameras); position/rotation/look_at "
                             "cannot be set, move the instances instead")
        if rotation is not None and look_at is not None:
            raise ValueError("give either rotation or look_at, not both")
        staged = {}
        if position is not None:
            staged["position"] = self._float_arg("position", position, (W, A, 3)).to(torch.float64)
        eye = staged.get("position", self.camera_position)
        if rotation is not None:
            rotation = self._float_arg("rotation", rotation, (W, A, 4))
            staged["rotation"] = normalize_quat(rotation.to(torch.float64), name="rotation").to(torch.float32)
        if look_at is not None:
            target = self._float_arg("look_at", look_at, (W, A, 3)).to(torch.float64)
            staged["rotation"] = look_at_quat(eye, target).to(torch.float32)
        for name, value, low, high in (("fov_y", fov_y, 1e-6, math.pi - 1e-6), ("near", near, 1e-9, None),
                                        ("far", far, 1e-9, None)):
            if value is not None:
                tensor = as_tensor(name, value).detach().to(torch.float64)
                self._check_device(name, tensor)
                tensor = tensor.expand(W, A) if tensor.ndim == 0 else tensor
                check_shape(name, tensor, (W, A))
                check_finite(name, tensor)
                check_range(name, tensor, low, high)
                staged[name] = tensor
        near_new, far_new = staged.get("near", self.near), staged.get("far", self.far)
        if bool((far_new <= near_new).any()):
            raise ValueError("far must be greater than near for every camera")
        for key, value in staged.items():
            target = {"position": self.camera_position, "rotation": self.camera_rotation}.get(key)
            (target if target is not None else getattr(self, key)).copy_(value)
        if staged:
            self._cameras_dirty = True
        if {"fov_y", "near", "far"} & staged.keys():
            self._projection = None

    # ------------------------------------------------------------------ rendering
    @one_thread
    def render(self) -> Frame:
        """Draw all views; returns tensors the caller owns. Any thread may call it (one at a
        time per renderer): the GL context is made current in the calling thread, for the
        frame and the GL reads that follow it."""
        self._check_open()
        backend.context()  # raises in a forked child
        with self._context.current():
            self._prepare()
            self.last_timings.update(gl=0.0, copy=0.0)
            return self._draw_and_read()

    def _prepare(self) -> list[str]:
        """The torch stages of a frame, each only when its inputs changed: camera poses and
        view packing (cameras moved), instance packing (groups updated), culling (either).
        Returns the groups whose instance data was packed (to be uploaded)."""
        start = time.perf_counter()
        mount = self.scene.camera_mount
        cameras_moved = self._cameras_dirty or (mount is not None and mount.group in self._dirty)
        if cameras_moved:
            position, rotation = self._camera_frames()
            self._recentre(position)
            self._planes = frustum_planes(self._pack_views(position, rotation))
            self._cameras_dirty = False
        packed_groups = list(self._dirty)
        for name in packed_groups:
            self._pack_group(name)
        self._dirty.clear()
        packed = time.perf_counter()
        self._cull(set(packed_groups), cameras_moved)
        self._mask_dirty.clear()
        if self.shadow_pass is not None:  # the atlas depends on the instances, not on the cameras
            self.shadow_pass.prepare(self.world_origin, self._state, changed=bool(packed_groups))
        self.last_timings = {"pack": packed - start, "cull": time.perf_counter() - packed}
        return packed_groups

    def _camera_frames(self):
        """Camera positions [W, A, 3] and camera-to-world rotations [W, A, 3, 3], float64."""
        mount = self.scene.camera_mount
        if mount is None:
            return self.camera_position, quat_to_matrix(self.camera_rotation.to(torch.float64))
        state = self._state[mount.group]
        index, offset, tilt = self._mount_constants
        body = quat_to_matrix(state["rotation"][:, index].to(torch.float64))
        position = state["position"][:, index] + body @ offset
        return position, body if tilt is None else body @ tilt

    def _recentre(self, camera_position: torch.Tensor):
        distance = (camera_position - self.world_origin[:, None]).norm(dim=-1).amax(dim=1)
        far_worlds = distance > RECENTRE_DISTANCE
        if bool(far_worlds.any()):
            self.world_origin[far_worlds] = camera_position[far_worlds].mean(dim=1)
            self._dirty.update(self.scene.groups)
            self._origin_moved = True
            for draw in self._groups.values():
                draw.static_bounds = None

    def _pack_views(self, position: torch.Tensor, rotation: torch.Tensor):
        """View-projections [W, A, 4, 4] of cameras at `position` with camera-to-world
        `rotation` [W, A, 3, 3], written to the views texture (and origins / lenses when changed)."""
        memory = _writable(self.views_texture, np.float32).view(-1, shaders.VIEW_TEXELS, 4)
        if self._projection is None or self._origin_moved:  # lenses or world origins changed
            height, width = self.scene.resolution
            projection = perspective(self.fov_y, width / height, self.near, self.far)
            # The camera frame (x right, y forward, z up) to GL's eye frame folded into the lens.
            self._projection = (projection[..., :3] @ _CAMERA_TO_GL, projection[..., 3])
            origin_hi = self.world_origin.to(torch.float32)
            origin_lo = (self.world_origin - origin_hi.to(torch.float64)).to(torch.float32)
            A = self.scene.agents_per_world
            memory[:, 4, :3] = origin_hi.repeat_interleave(A, dim=0)
            memory[:, 5, :3] = origin_lo.repeat_interleave(A, dim=0)
            memory[:, 4, 3] = self.near.reshape(-1)
            memory[:, 5, 3] = self.far.reshape(-1)
            self._origin_moved = False
        lens, lens_shift = self._projection
        linear = lens @ rotation.transpose(-1, -2)  # [W, A, 4, 3]: world directions to clip space
        shift = lens_shift - (linear @ (position - self.world_origin[:, None])[..., None])[..., 0]
        view_projection = torch.cat((linear, shift[..., None]), -1)
        memory[:, :4] = view_projection.reshape(-1, 4, 4).transpose(1, 2)  # texel j = column j
        return view_projection

    def _pack_group(self, name: str):
        state = self._state[name]
        W, C = state["active"].shape
        draw = self._groups[name]
        memory = _writable(draw.instances, np.float32).view(W, C, draw.texels, 4)
        memory[:, :, 0, :3] = state["position"] - self.world_origin[:, None]
        memory[:, :, 0, 3] = state["active"]
        memory[:, :, 1] = state["rotation"]
        memory[:, :, 2, :3] = state["scale"]
        memory[:, :, 2, 3] = state["owner"]
        memory[:, :, 3] = state["color"]
        if "joints" in state:
            transforms = skinning.joint_transforms(self.scene.groups[name].mesh, state["joints"])
            memory[:, :, shaders.INSTANCE_TEXELS:] = transforms.view(W, C, -1, 4)

    def _cull(self, moved: set, cameras_moved: bool):
        """Bring each group's list of drawn (view, instance) pairs up to date.

        A group whose instances and cameras did not move keeps its list. Frustum tests of
        all groups that need one run as one batched test; a group whose last test showed
        nothing worth culling draws its candidate pairs (active, not the viewer's own body)
        for CULL_RECHECK frames instead."""
        tested, candidates_only = [], []
        for name, draw in self._groups.items():
            mask_changed = name in self._mask_dirty
            if not (cameras_moved or name in moved or mask_changed):
                continue
            if draw.frustum_pause == 0:
                tested.append(name)
            else:
                draw.frustum_pause -= 1
                if mask_changed or draw.frustum_culled:
                    candidates_only.append(name)
        for name in candidates_only:
            candidate, _ = self._candidates(name)
            self._store_pairs(self._groups[name], pair_list(candidate) if candidate is not None else None, False)
        if not tested:
            return
        centers, radii = zip(*(self._bounds(name) for name in tested))
        inside = inside_frustum(self._planes, torch.cat(centers, 1), torch.cat(radii, 1))
        first = 0
        for name, count in zip(tested, (c.shape[1] for c in centers)):
            draw, visible = self._groups[name], inside[:, :, first:first + count]
            first += count
            candidate, possible = self._candidates(name)
            pairs = pair_list(visible if candidate is None else visible & candidate)
            if len(pairs) > CULL_KEEPS * possible:
                draw.frustum_pause = CULL_RECHECK
            self._store_pairs(draw, pairs, True)

    def _bounds(self, name: str):
        """Bounding-sphere centres [W, K, 3] (relative to the world origin) and radii [W, K] of a
        group (scales are >= 0); those of static groups are kept until the world origins move."""
        draw, W = self._groups[name], self.scene.num_worlds
        if draw.static:
            if draw.static_bounds is None:
                group = self.scene.static[name]
                draw.static_bounds = (group.position[None] - self.world_origin[:, None],
                                      (draw.radius * group.scale.amax(-1)).expand(W, -1))
            return draw.static_bounds
        state = self._state[name]
        return state["position"] - self.world_origin[:, None], state["scale"].amax(-1) * draw.radius

    def _candidates(self, name: str):
        """([W, A, C] bool, count): the instance is active and not the viewing agent's own body
        ((None, all pairs) for static groups); kept until the group's masks change."""
        draw = self._groups[name]
        if draw.static:
            return None, self.scene.num_views * draw.count
        if name in self._mask_dirty or name not in self._candidate_cache:
            state = self._state[name]
            agent = torch.arange(self.scene.agents_per_world)[None, :, None]
            candidate = state["active"][:, None, :] & (state["owner"][:, None, :] != agent)
            self._candidate_cache[name] = (candidate, int(candidate.sum()))
        return self._candidate_cache[name]

    def _store_pairs(self, draw: _DrawGroup, pairs: torch.Tensor | None, culled: bool):
        """Upload a group's drawn pairs (None: every pair of a static group) and split them per pass."""
        total = self.scene.num_views * draw.count
        if pairs is None:
            pairs = torch.arange(total, dtype=torch.int32)
        if len(pairs):
            _writable(draw.pairs, np.int32)[: len(pairs)] = pairs
        draw.frustum_culled = culled
        if self.layout.num_passes == 1:
            draw.pass_ranges = [(0, len(pairs))]
            return
        starts = torch.tensor([render_pass.views.start * draw.count for render_pass in self._passes] + [total],
                              dtype=torch.int32)
        bounds = torch.searchsorted(pairs, starts).tolist()
        draw.pass_ranges = [(bounds[p], bounds[p + 1] - bounds[p]) for p in range(self.layout.num_passes)]

    def _draw_and_read(self) -> Frame:
        s = self.scene
        W, A = s.num_worlds, s.agents_per_world
        height, width = s.resolution
        C = self.channels
        rgb_shape = (W * A, C, height, width) if self.channels_first else (W * A, height, width, C)
        rgb = torch.empty(rgb_shape, dtype=torch.uint8)
        depth = torch.empty(W * A, height, width, dtype=torch.float32) if "depth" in self.effects else None
        segmentation = torch.empty(W * A, height, width, dtype=torch.int32) if "segmentation" in self.effects else None
        started = time.perf_counter()
        for index, render_pass in enumerate(self._passes):
            for draw in self._groups.values():
                first, count = draw.pass_ranges[index]
                entry = draw.pass_nodes[index]
                node, offset, drawn = entry
                offset[0] = first
                if count == drawn:
                    continue
                if count == 0:  # Panda3D would draw an instance count of 0 once
                    node.hide()
                else:
                    if not drawn:
                        node.show()
                    node.set_instance_count(count)
                entry[2] = count
        # Every pass is drawn in one frame before any is read: llvmpipe rasterises one
        # framebuffer on its threads while the next one is being drawn. The shadow atlas,
        # when out of date, is drawn first in the same frame (its buffer sorts before them).
        for render_pass in self._passes:
            render_pass.buffer.set_active(True)
        if self.shadow_pass is not None:
            self.shadow_pass.set_active(True)
        try:
            self._context.engine.render_frame()
            if self.shadow_pass is not None:
                self.shadow_pass.drawn()
        finally:
            for render_pass in self._passes:
                render_pass.buffer.set_active(False)
            if self.shadow_pass is not None:
                self.shadow_pass.set_active(False)
        self._check_shaders()
        copy_seconds = 0.0
        for render_pass in self._passes:
            copy_seconds += self._read_pass(render_pass, rgb, depth, segmentation)
        self.last_timings["gl"] = time.perf_counter() - started - copy_seconds
        self.last_timings["copy"] = copy_seconds
        rgb = rgb.view((W, A) + rgb_shape[1:])
        return Frame(rgb, None if depth is None else depth.view(W, A, height, width),
                     None if segmentation is None else segmentation.view(W, A, height, width))

    def _check_shaders(self):
        """A variant that failed to compile draws nothing: raise with the GL log instead."""
        log = self._context.drain_log()
        failed = [name for name, draw in self._groups.items()
                  if any(node.get_shader().get_error_flag() for node, _, _ in draw.pass_nodes)]
        failed += self.shadow_pass.failed_groups() if self.shadow_pass is not None else []
        if failed:
            text = "\n".join(log or self._context.recent_log[-20:])
            raise backend.ShaderCompileError(f"the shader of group(s) {failed} failed to compile or link:\n{text}")

    def _read_pass(self, render_pass: _Pass, rgb, depth, segmentation) -> float:
        """Read one framebuffer's textures into the outputs; returns the seconds spent on
        copies after the GL reads (none for plain channels-last colour and k = 1)."""
        if render_pass.texture_ids is None:
            gsg = self._context.gsg
            render_pass.texture_ids = {name: readback.texture_id(texture, gsg) for name, texture in
                                       [("color", render_pass.color), *render_pass.aux.items()]}
        views, k = render_pass.views, self.supersample
        height, width = self.scene.resolution
        rows, columns = len(views) * height * k, width * k
        ids = render_pass.texture_ids
        destination = rgb[views.start:views.stop]
        C = self.channels
        copy_seconds = 0.0
        # One channel is laid out alike channels first or last: read straight into it too.
        if k == 1 and (C == 1 or not self.channels_first) and self.readback == "zero_copy":
            readback.read_texture(ids["color"], columns, rows, C, destination)
        else:
            staging = self._staging_buffer(rows * columns * C)
            readback.read_texture(ids["color"], columns, rows, C, staging)
            started = time.perf_counter()
            samples = staging.view(len(views), height * k, width * k, C)
            if self.channels_first:  # write through a channels-last view of the output
                destination = destination.permute(0, 2, 3, 1)
            if k > 1:
                self._box_filter(samples, destination)
            else:
                destination.copy_(samples)
            copy_seconds += time.perf_counter() - started
        for name, out in (("depth", depth), ("segmentation", segmentation)):
            if out is None:
                continue
            target = out[views.start:views.stop]
            if k == 1:
                readback.read_texture(ids[name], columns, rows, 4, target)
                continue
            staging = self._staging_buffer(rows * columns * 4)
            readback.read_texture(ids[name], columns, rows, 4, staging)
            started = time.perf_counter()
            samples = staging.view(out.dtype).view(len(views), height * k, width * k)
            target.copy_(samples[:, k // 2::k, k // 2::k])  # the sample nearest each output pixel's centre
            copy_seconds += time.perf_counter() - started
        return copy_seconds

    def _staging_buffer(self, size: int) -> torch.Tensor:
        """Reused bytes for reads that need a copy afterwards (channels-first, supersampling, "copy")."""
        if self._staging is None or self._staging.numel() < size:
            self._staging = torch.empty(size, dtype=torch.uint8)
        return self._staging[:size]

    def _box_filter(self, samples: torch.Tensor, destination: torch.Tensor) -> None:
        """samples [n, kH, kW, C] uint8 -> destination [n, H, W, C], each pixel the rounded
        mean of its k x k samples (through an accumulator made once per renderer)."""
        k, count, C = self.supersample, destination.shape[0], self.channels
        height, width = self.scene.resolution
        if self._accumulator is None:
            self._accumulator = torch.empty((self.layout.views_per_pass, height, width, C), dtype=torch.int32)
        total = self._accumulator[:count]
        torch.sum(samples.view(count, height, k, width, k, C), dim=(2, 4), dtype=torch.int32, out=total)
        destination.copy_(total.add_((k * k) // 2).div_(k * k, rounding_mode="floor"))

    # ------------------------------------------------------------------ helpers / lifecycle
    def _float_arg(self, name, value, shape):
        tensor = as_tensor(name, value).detach()  # the renderer's state never joins an autograd graph
        tensor = tensor if tensor.dtype in FLOAT_DTYPES else tensor.float()  # float8: no isfinite kernel
        self._check_device(name, tensor)
        check_shape(name, tensor, shape)
        check_finite(name, tensor)
        return tensor

    @staticmethod
    def _check_device(name, tensor):
        check_host(name, tensor)

    def _check_group(self, group):
        if not isinstance(group, str):
            raise TypeError(f"group must be the name (str) of one of this scene's instance groups {sorted(self._state)}, "
                            f"got {describe(group)}")
        if group not in self._state:
            raise ValueError(f"group must be one of this scene's instance groups {sorted(self._state)}, got {group!r}")

    def _check_open(self):
        if self._closed:
            raise RuntimeError("this BatchRenderer is closed; create a new one")

    @property
    def num_views(self) -> int:
        return self.scene.num_views

    @property
    def granted_multisamples(self) -> int:
        """MSAA samples the GL gave the framebuffers (it may give fewer than asked)."""
        self._check_open()
        return min(p.buffer.get_fb_properties().get_multisamples() for p in self._passes)

    def instance_state(self, group: str) -> dict:
        """Copies of a group's current per-instance tensors."""
        self._check_group(group)
        return {k: v.clone() for k, v in self._state[group].items()}

    def close(self) -> None:
        """Free the framebuffer and textures; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        textures = [getattr(self, "views_texture", None)]
        passes = getattr(self, "_passes", [])
        shadow_pass = getattr(self, "shadow_pass", None)
        if (passes or shadow_pass is not None) and self._context.pid == os.getpid():
            # a forked child must not touch its parent's GL objects
            with self._context.current():  # Panda3D deletes the framebuffers right away
                if shadow_pass is not None:
                    shadow_pass.close()
                for render_pass in passes:
                    render_pass.buffer.clear_render_textures()
                    self._context.engine.remove_window(render_pass.buffer)
                self._context.drop_render_texture_events()
        self.shadow_pass = None
        for render_pass in passes:
            render_pass.root.remove_node()
            textures += [render_pass.color, *render_pass.aux.values()]
        self._passes = []
        textures += [t for g in self._groups.values() for t in (g.instances, g.pairs)]
        for texture in textures:
            if texture is not None:
                texture.release_all()
                texture.clear_ram_image()
        self._groups.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: Panda3D may already be gone
            pass


def _int(value: int):
    from panda3d.core import PTA_int

    return PTA_int([int(value)])


def _vec3(values):
    from panda3d.core import LVecBase3f

    return LVecBase3f(*(float(v) for v in values))


def _panda_texture(texture, name):
    """A Panda3D Texture from a Texture, or from pixels: an image path or a uint8 array [h, w, 3|4].

    Image files are decoded by Pillow (images.py), never by Panda3D's own readers, which
    end the process on some corrupt files."""
    from panda3d.core import SamplerState, Texture

    if type(texture).__name__ == "Texture":
        return texture
    try:
        array = texture_pixels(texture, name="texture")
    except (TypeError, ValueError) as error:
        raise type(error)(f"texture of group {name!r}: {error}") from None
    h, w, channels = array.shape
    result = Texture(f"texture:{name}")
    result.setup_2d_texture(w, h, Texture.T_unsigned_byte, Texture.F_rgb if channels == 3 else Texture.F_rgba)
    # Panda3D stores images bottom-up in BGR(A) order.
    swizzled = array[::-1, :, [2, 1, 0, 3][:channels]]
    result.set_ram_image(np.ascontiguousarray(swizzled).tobytes())
    result.set_minfilter(SamplerState.FT_linear_mipmap_linear)
    result.set_magfilter(SamplerState.FT_linear)
    return result
