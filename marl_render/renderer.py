"""The batch renderer: every view of every world in one instanced pass per mesh group.

Per step:
1. pack the groups that changed into their buffer textures (one row per world
   instance, read by all A views of that world);
2. pack one view-projection per view (cameras free or mounted on instances);
3. one draw per mesh group with instance count = views x capacity; the vertex shader
   places view v in its tile and clips it to that tile;
4. one readback of the tiled framebuffer, one strided copy into the batch tensor.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from . import backend, shaders
from .images import texture_pixels
from .meshes import MeshData, to_panda_geom
from .scene import Scene, StaticGroup
from .shadows import ShadowPass
from .culling import frustum_planes, mesh_radius, visible_pairs
from .threads import caller_threads, one_thread
from .tiling import TileLayout, copy_tiles, framebuffer_tiles, plan_layout
from .transforms import normalize_quat, perspective, quat_from_yaw_pitch_roll, quat_multiply, quat_rotate, view_matrix, look_at_quat
from .validation import FLOAT_DTYPES, as_tensor, check_finite, check_host, check_range, check_shape, describe, positive_int

# Worlds are re-centred when a camera strays this far from its world's origin, so that
# float32 positions relative to the origin stay precise (see the static-group shader).
RECENTRE_DISTANCE = 1024.0


@dataclass
class Frame:
    """One render: rgb [W, A, H, W, 3] uint8 (or [W, A, 3, H, W]), depth [W, A, H, W] float32
    metres along the view axis (inf where nothing was drawn), segmentation [W, A, H, W] int32
    (0 = background). Tensors are owned by the caller."""

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
    """GL side of one group: its node, instance data, visible-pair list and bounds."""

    node: object
    count: int  # instances per world (static: in total)
    static: bool
    instances: object  # float32 buffer texture
    pairs: object  # int32 buffer texture: visible view * count + instance
    radius: float  # bounding sphere of the mesh at unit scale
    pass_ranges: list | None = None  # [(first pair, pair count)] per pass
    pair_offset: object = None  # PTA_int shader input, updated in place per pass


class BatchRenderer:
    """Renders scene.num_worlds x scene.agents_per_world views per call of render()."""

    READBACKS = ("zero_copy", "copy")

    def __init__(self, scene: Scene, *, channels_first: bool = False, max_framebuffer_size: int | None = None,
                 egl_device_index: int | None = None, readback: str = "zero_copy", supersample: int = 1,
                 multisamples: int = 0):
        """readback: "zero_copy" (default) reads the tiles straight out of Panda3D's RAM
        image; "copy" first copies the whole image into a bytes object (the usual way,
        kept only so that benchmarks can show what the zero-copy path saves).
        supersample=k renders every view at k x the resolution and box-filters it down
        (anti-aliasing; depth and segmentation take the sample nearest each pixel centre).
        multisamples=n asks the GL for n-sample MSAA (colour only)."""
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a marl_render.Scene, got {describe(scene)}")
        if readback not in self.READBACKS:
            raise ValueError(f"readback must be one of {list(self.READBACKS)}, got {readback!r}")
        self.supersample = positive_int("supersample", supersample)
        self._supersamples = self._accumulator = None  # reused buffers of the box filter
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
        self.layout: TileLayout = plan_layout(scene.num_views, height * k, width * k, max_framebuffer_size)
        self.effects = frozenset(scene.effects)
        self._init_state()
        self.buffer = self.root = self.shadow_pass = None
        self._groups = {}
        try:
            self._build_target()
            self._build_groups()
            if "shadows" in self.effects:
                self.shadow_pass = ShadowPass(self._context, scene, self._groups, gl_max)
                self.shadow_pass.bind(self.root)
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
                tilt = quat_from_yaw_pitch_roll(torch.tensor(0.0, dtype=torch.float64),
                                                torch.tensor(mount.pitch, dtype=torch.float64))
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
            if mount is not None and mount.group == name and mount.hide_owner:
                state["owner"][:, list(mount.instance)] = torch.arange(A)
            self._state[name] = state
        self._dirty = set(s.groups)

    # ------------------------------------------------------------------ GL objects
    def _build_target(self):
        from panda3d.core import (Camera, ColorBlendAttrib, CullFaceAttrib, DepthTestAttrib, DepthWriteAttrib,
                                  FrameBufferProperties, GraphicsOutput, GraphicsPipe, LVecBase2i,
                                  NodePath, OmniBoundingVolume, Texture, TransparencyAttrib, WindowProperties)

        ctx = self._context
        width, height = self.layout.framebuffer_size
        aux = [e for e in ("depth", "segmentation") if e in self.effects]
        props = FrameBufferProperties()
        # No alpha: a 3-byte readback makes the tile copy a run of whole rows, which is
        # several times cheaper than dropping every fourth byte afterwards. Panda3D reads
        # aux targets with the colour target's channel count, so those need alpha.
        self._color_channels = 4 if aux else 3
        props.set_rgba_bits(8, 8, 8, 8 if aux else 0)
        props.set_depth_bits(24)
        props.set_aux_rgba(len(aux))
        props.set_multisamples(self.multisamples)
        self.buffer = ctx.engine.make_output(
            ctx.pipe, f"marl_render_{id(self)}", 0, props, WindowProperties.size(width, height),
            GraphicsPipe.BF_refuse_window, ctx.gsg, ctx.host)
        if self.buffer is None:
            raise backend.GLUnavailableError(
                f"could not create a {width}x{height} offscreen framebuffer with {len(aux)} aux targets; "
                "lower resolution / num views or max_framebuffer_size")
        self.color_texture = Texture("color")
        self.buffer.add_render_texture(self.color_texture, GraphicsOutput.RTM_copy_ram, GraphicsOutput.RTP_color)
        self.aux_textures = {}
        for index, name in enumerate(aux):
            texture = Texture(name)
            texture.setup_2d_texture(width, height, Texture.T_unsigned_byte, Texture.F_rgba8)
            plane = GraphicsOutput.RTP_aux_rgba_0 + index
            self.buffer.add_render_texture(texture, GraphicsOutput.RTM_copy_ram, plane)
            # Clear values in BGRA byte order: depth +inf (0x7f800000), segment 0.
            clear = (128 / 255, 0.0, 0.0, 127 / 255) if name == "depth" else (0.0, 0.0, 0.0, 0.0)
            self.buffer.set_clear_active(plane, True)
            self.buffer.set_clear_value(plane, clear)
            self.aux_textures[name] = texture
        r, g, b = self.scene.background[:3]
        self.buffer.set_clear_color((b, g, r, 1.0))  # swizzled like the shader output
        self.buffer.set_active(False)

        self.root = NodePath("marl_render_root")
        camera = Camera("tiles")
        camera.set_cull_bounds(OmniBoundingVolume())
        self.display_region = self.buffer.make_display_region()
        self.display_region.set_camera(self.root.attach_new_node(camera))
        # The per-view vertical flip reverses winding: cull the other side.
        self.root.set_attrib(CullFaceAttrib.make(CullFaceAttrib.M_cull_counter_clockwise))
        self.root.set_attrib(DepthTestAttrib.make(DepthTestAttrib.M_less))
        self.root.set_attrib(DepthWriteAttrib.make(DepthWriteAttrib.M_on))
        self.root.set_transparency(TransparencyAttrib.M_none)
        self.root.set_attrib(ColorBlendAttrib.make_off())

        self.views_texture = _buffer_texture("views", self.scene.num_views * shaders.VIEW_TEXELS)
        self.root.set_shader_input("views", self.views_texture)
        self.root.set_shader_input("agents", _int(self.scene.agents_per_world))
        self.root.set_shader_input("grid", LVecBase2i(self.layout.columns, self.layout.rows))
        self._view_offset = _int(0)  # updated in place per pass (a new PTA would make a new render state)
        self.root.set_shader_input("view_offset", self._view_offset)
        lighting, fog = self.scene.lighting, self.scene.fog
        direction = np.asarray(lighting.direction, dtype=float)
        self.root.set_shader_input("light_direction", _vec3(direction / np.linalg.norm(direction)))
        self.root.set_shader_input("light_color", _vec3(lighting.color))
        self.root.set_shader_input("ambient_color", _vec3(lighting.ambient))
        self.root.set_shader_input("fog_color", _vec3(fog.color))
        self.root.set_shader_input("fog_density", float(fog.density))

    def _build_groups(self):
        from panda3d.core import NodePath, OmniBoundingVolume

        self._groups: dict[str, _DrawGroup] = {}
        groups = [(g, True) for g in self.scene.static.values()] + [(g, False) for g in self.scene.groups.values()]
        for order, (group, static) in enumerate(groups):
            mesh = group.mesh
            node = NodePath(to_panda_geom(mesh)) if isinstance(mesh, MeshData) else mesh.copy_to(NodePath())
            node.reparent_to(self.root)
            # A fixed draw order: Panda3D would otherwise sort by render state (memory
            # addresses), and surfaces that touch exactly would tie differently per run.
            node.set_bin("fixed", order)
            node.node().set_bounds(OmniBoundingVolume())
            node.node().set_final(True)
            textured = group.texture is not None
            defines = shaders.defines_for(self.effects, static=static, textured=textured,
                                          flat=isinstance(mesh, MeshData) and mesh.flat,
                                          shadow_pcf=self.scene.shadows.pcf)
            node.set_shader(shaders.compiled(defines))
            if textured and "texture" in self.effects:
                node.set_texture(_panda_texture(group.texture, group.name), 1)
            count = group.count if static else group.capacity
            rows = count if static else self.scene.num_worlds * count
            texels = shaders.STATIC_INSTANCE_TEXELS if static else shaders.INSTANCE_TEXELS
            draw = _DrawGroup(node, count, static, _buffer_texture(f"instances:{group.name}", rows * texels),
                              _buffer_texture(f"pairs:{group.name}", self.scene.num_views * count, integer=True),
                              mesh_radius(mesh))
            node.set_shader_input("instances", draw.instances)
            node.set_shader_input("pairs", draw.pairs)
            node.set_shader_input("capacity", _int(count))
            node.set_shader_input("segment_base", _int(group.segment_base))
            draw.pair_offset = _int(0)
            node.set_shader_input("pair_offset", draw.pair_offset)
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
               owner=None) -> None:
        """Set per-instance data of a group for all worlds: tensors shaped [W, C, ...].

        position [W,C,3] (float32/64, metres), rotation [W,C,4] unit quaternions (w,x,y,z;
        normalised here), scale [W,C,3], color [W,C,4] or [W,C,3] in [0,1], active [W,C] bool,
        owner [W,C] int agent index (-1: none). Everything is validated before anything is stored.
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
        for key, value in staged.items():
            state[key].copy_(value)
        if staged:
            self._dirty.add(group)

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

    # ------------------------------------------------------------------ rendering
    @one_thread
    def render(self) -> Frame:
        """Draw all views; returns tensors the caller owns."""
        self._check_open()
        backend.context()  # raises in a forked child
        self._prepare()
        self.last_timings.update(gl=0.0, copy=0.0)
        return self._draw_and_read()

    def _prepare(self) -> list[str]:
        """The torch stages of a frame: camera poses, view and instance packing, culling.
        Returns the groups whose instance data was packed (to be uploaded)."""
        start = time.perf_counter()
        position, rotation = self._camera_poses()
        self._recentre(position)
        view_projection = self._pack_views(position, rotation)
        packed_groups = list(self._dirty)
        for name in packed_groups:
            self._pack_group(name)
        self._dirty.clear()
        packed = time.perf_counter()
        self._cull(frustum_planes(view_projection))
        if self.shadow_pass is not None:
            self.shadow_pass.prepare(self.world_origin, self._state, changed=bool(packed_groups))
        self.last_timings = {"pack": packed - start, "cull": time.perf_counter() - packed}
        return packed_groups

    def _camera_poses(self):
        mount = self.scene.camera_mount
        if mount is None:
            return self.camera_position, self.camera_rotation
        state = self._state[mount.group]
        index, offset, tilt = self._mount_constants
        body_position = state["position"][:, index]
        body_rotation = state["rotation"][:, index].to(torch.float64)
        position = body_position + quat_rotate(body_rotation, offset.expand_as(body_position))
        if tilt is not None:
            body_rotation = quat_multiply(body_rotation, tilt.expand_as(body_rotation))
        return position, body_rotation

    def _recentre(self, camera_position: torch.Tensor):
        distance = (camera_position - self.world_origin[:, None]).norm(dim=-1).amax(dim=1)
        far_worlds = distance > RECENTRE_DISTANCE
        if bool(far_worlds.any()):
            self.world_origin[far_worlds] = camera_position[far_worlds].mean(dim=1)
            self._dirty.update(self.scene.groups)

    def _pack_views(self, position: torch.Tensor, rotation: torch.Tensor):
        height, width = self.scene.resolution
        relative = position - self.world_origin[:, None]
        view = view_matrix(relative, rotation.to(torch.float64))
        projection = perspective(self.fov_y, width / height, self.near, self.far)
        view_projection = projection @ view
        memory = _writable(self.views_texture, np.float32).view(-1, shaders.VIEW_TEXELS, 4)
        memory[:, :4] = view_projection.reshape(-1, 4, 4).transpose(1, 2)  # texel j = column j
        origin_hi = self.world_origin.to(torch.float32)
        origin_lo = (self.world_origin - origin_hi.to(torch.float64)).to(torch.float32)
        A = self.scene.agents_per_world
        memory[:, 4, :3] = origin_hi.repeat_interleave(A, dim=0)
        memory[:, 5, :3] = origin_lo.repeat_interleave(A, dim=0)
        memory[:, 4, 3] = self.near.reshape(-1)
        memory[:, 5, 3] = self.far.reshape(-1)
        return view_projection

    def _pack_group(self, name: str):
        state = self._state[name]
        W, C = state["active"].shape
        memory = _writable(self._groups[name].instances, np.float32).view(W, C, shaders.INSTANCE_TEXELS, 4)
        memory[:, :, 0, :3] = state["position"] - self.world_origin[:, None]
        memory[:, :, 0, 3] = state["active"]
        memory[:, :, 1] = state["rotation"]
        memory[:, :, 2, :3] = state["scale"]
        memory[:, :, 2, 3] = state["owner"]
        memory[:, :, 3] = state["color"]

    def _cull(self, planes: torch.Tensor):
        """List each group's visible (view, instance) pairs and split them into passes."""
        W, A = self.scene.num_worlds, self.scene.agents_per_world
        pass_starts = torch.tensor([self.layout.pass_views(p).start for p in range(self.layout.num_passes)]
                                   + [self.scene.num_views], dtype=torch.int64)
        agent = torch.arange(A)[None, :, None]
        for name, draw in self._groups.items():
            if draw.static:
                group = self.scene.static[name]
                centers = group.position[None] - self.world_origin[:, None]
                radii = (draw.radius * group.scale.abs().amax(-1)).expand(W, -1)
                candidate = torch.ones(W, A, draw.count, dtype=torch.bool)
            else:
                state = self._state[name]
                centers = state["position"] - self.world_origin[:, None]
                radii = draw.radius * state["scale"].abs().amax(-1)
                candidate = state["active"][:, None, :] & (state["owner"][:, None, :] != agent)
            pairs = visible_pairs(planes, centers, radii, candidate)
            if len(pairs):
                _writable(draw.pairs, np.int32)[: len(pairs)] = pairs
            bounds = torch.searchsorted(pairs // draw.count, pass_starts.to(torch.int32)).tolist() if len(pairs) else [0] * len(pass_starts)
            draw.pass_ranges = [(bounds[p], bounds[p + 1] - bounds[p]) for p in range(self.layout.num_passes)]

    def _draw_and_read(self) -> Frame:
        s = self.scene
        W, A = s.num_worlds, s.agents_per_world
        height, width = s.resolution
        rgb_shape = (W * A, 3, height, width) if self.channels_first else (W * A, height, width, 3)
        rgb = torch.empty(rgb_shape, dtype=torch.uint8)
        depth = torch.empty(W * A, height, width, dtype=torch.float32) if "depth" in self.effects else None
        segmentation = torch.empty(W * A, height, width, dtype=torch.int32) if "segmentation" in self.effects else None
        engine = self._context.engine
        for index in range(self.layout.num_passes):
            views = self.layout.pass_views(index)
            self._view_offset[0] = views.start
            for draw in self._groups.values():
                first, count = draw.pass_ranges[index]
                if count == 0:  # Panda3D would draw an instance count of 0 once
                    draw.node.hide()
                    continue
                draw.node.show()
                draw.pair_offset[0] = first
                draw.node.set_instance_count(count)
            started = time.perf_counter()
            self.buffer.set_active(True)
            if self.shadow_pass is not None:
                self.shadow_pass.set_active(index == 0)  # drawn first (its buffer sorts first)
            try:
                engine.render_frame()
            finally:
                self.buffer.set_active(False)
                if self.shadow_pass is not None:
                    self.shadow_pass.set_active(False)
            drawn = time.perf_counter()
            self._check_shaders()
            self._read_pass(views, rgb, depth, segmentation)
            self.last_timings["gl"] += drawn - started
            self.last_timings["copy"] += time.perf_counter() - drawn
        rgb = rgb.view((W, A) + rgb_shape[1:])
        return Frame(rgb, None if depth is None else depth.view(W, A, height, width),
                     None if segmentation is None else segmentation.view(W, A, height, width))

    def _check_shaders(self):
        """A variant that failed to compile draws nothing: raise with the GL log instead."""
        log = self._context.drain_log()
        failed = [name for name, draw in self._groups.items() if draw.node.get_shader().get_error_flag()]
        failed += self.shadow_pass.failed_groups() if self.shadow_pass is not None else []
        if failed:
            text = "\n".join(log or self._context.recent_log[-20:])
            raise backend.ShaderCompileError(f"the shader of group(s) {failed} failed to compile or link:\n{text}")

    def _read_pass(self, views: range, rgb, depth, segmentation):
        image = self.color_texture.get_ram_image()
        if image is None or len(image) == 0:
            log = "\n".join(self._context.recent_log[-20:])
            raise RuntimeError(f"the GL driver returned no framebuffer image (render failed). GL log:\n{log}")
        if self.readback == "copy":
            image = bytes(image)
        tiles = framebuffer_tiles(image, np.uint8, self._color_channels, self.layout)[..., :3]
        k = self.supersample
        destination = rgb[views.start:views.stop]
        if self.channels_first:  # write through a channels-last view of the output
            destination = destination.permute(0, 2, 3, 1)
        with caller_threads():  # one large copy while the rasteriser's threads are idle
            if k > 1:
                self._box_filter(tiles, destination)
            else:
                copy_tiles(tiles, destination)
        for name, out, dtype in (("depth", depth, np.float32), ("segmentation", segmentation, np.int32)):
            if out is not None:
                aux = framebuffer_tiles(self.aux_textures[name].get_ram_image(), dtype, 1, self.layout)
                if k > 1:  # the sample nearest each output pixel's centre
                    aux = aux[:, :, k // 2::k, k // 2::k]
                copy_tiles(aux, out[views.start:views.stop])

    def _box_filter(self, tiles: torch.Tensor, destination: torch.Tensor) -> None:
        """[rows, cols, kH, kW, 3] uint8 tiles -> destination [n, H, W, 3], each pixel the
        rounded mean of its k x k samples, through buffers made once per renderer."""
        k, count = self.supersample, destination.shape[0]
        height, width = self.scene.resolution
        if self._supersamples is None:
            per_pass = min(self.layout.views_per_pass, self.scene.num_views)
            self._supersamples = torch.empty((per_pass, height * k, width * k, 3), dtype=torch.uint8)
            self._accumulator = torch.empty((per_pass, height, width, 3), dtype=torch.int32)
        samples, total = self._supersamples[:count], self._accumulator[:count]
        copy_tiles(tiles, samples)
        torch.sum(samples.view(count, height, k, width, k, 3), dim=(2, 4), dtype=torch.int32, out=total)
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

    def instance_state(self, group: str) -> dict:
        """Copies of a group's current per-instance tensors."""
        self._check_group(group)
        return {k: v.clone() for k, v in self._state[group].items()}

    def close(self) -> None:
        """Free the framebuffer and textures; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self.shadow_pass is not None:
            self.shadow_pass.close()
        if self.buffer is not None:
            self.buffer.clear_render_textures()
            self._context.engine.remove_window(self.buffer)
            self.buffer = None
        if self.root is not None:
            self.root.remove_node()
        textures = [getattr(self, name, None) for name in ("color_texture", "views_texture")]
        textures += list(getattr(self, "aux_textures", {}).values())
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
