"""The batch renderer: every view of every world in one instanced pass per mesh group.

Per step:
Packing (steps 1-2) is packing.py's FramePacker, which holds the state and writes into
the buffer textures' memory; this module owns the GL objects and draws them: the framebuffers
are framebuffers.py's, the groups' nodes and textures draw_groups.py's, the reads
frame_reads.py's (a base class of BatchRenderer).
1. pack the groups that changed into their buffer textures (one row per world
   instance, read by all A views of that world);
2. pack one view-projection per view when a camera moved (cameras free or mounted on
   instances), and list the visible (view, instance) pairs when anything moved;
3. one draw per mesh group and framebuffer with instance count = visible pairs; the
   vertex shader places view v in its tile (one column of tiles per framebuffer) and
   clips it to that tile (under the appearance effect, a floor or wall group takes two:
   the worlds whose pattern shows, then the plain ones with the variant without patterns);
4. once every framebuffer is drawn, one GL read per framebuffer and output: straight
   into the batch tensor on the host (readback.py), or into one GL pixel-pack
   buffer that CUDA then copies device to device into tensors born on `device`
   (interop.py; readback="auto" | "gpu").
"""
from __future__ import annotations

import functools
import os
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..assets import skinning
from ..assets.meshes import MeshData, to_panda_geom
from ..util.threads import one_thread
from ..util.validation import describe, positive_int, torch_device, unpicklable
from . import backend, interop, memory, readback, row_layouts, shaders
from . import impostors as sphere_impostors
from .draw_groups import DrawGroup, PandaTargets, per_pass, set_draw
from .frame_reads import FrameReads
from .framebuffers import RenderPass, make_pass
from .packing import FramePacker
from .panda_buffers import buffer_texture, int_input, panda_texture, vec3_input
from .provoking import shared_corner_mesh
from .readback import max_array_texture_layers
from .scene import ROLES, Scene
from .shadows import ShadowPass, atlas_layout, light_projection
from .sky import SkyImages
from .tiling import TileLayout, column_layout, layer_layout
from .triangle_corners import to_panda_geom_with_corners


@dataclass
class Frame:
    """One render: rgb [W, A, H, W, C] uint8 (or [W, A, C, H, W]; C = 3, or 1 for color="gray"),
    depth [W, A, H, W] float32 metres along the view axis (inf where nothing was drawn),
    segmentation [W, A, H, W] int32 (0 = background). Tensors are owned by the caller."""

    rgb: torch.Tensor
    depth: torch.Tensor | None = None
    segmentation: torch.Tensor | None = None


class BatchRenderer(FrameReads):
    """Renders scene.num_worlds x scene.agents_per_world views per call of render()."""

    # "auto", "gpu", "host" (interop.READBACKS), and two host reads kept for benchmarks and tests.
    READBACKS = (*interop.READBACKS, "pbo", "copy")
    COLORS = {"rgb": 3, "gray": 1}  # color -> channels of Frame.rgb

    def __init__(self, scene: Scene, *, channels_first: bool = False, max_framebuffer_size: int | None = None,
                 egl_device_index: int | None = None, readback: str = "auto", supersample: int = 1,
                 multisamples: int = 0, color: str = "rgb", context: backend.GLContext | None = None,
                 device="cpu", exact_tiles: bool = False, layered: bool = False, impostors=False):
        """device: the torch device the frames are born on ("cpu", or a CUDA device).
        readback: how they get there. "host" reads each framebuffer straight into a host
        tensor (then copied to a CUDA `device`); "gpu" reads them into a GL pixel-pack
        buffer that CUDA copies device to device into `device` (CUDA-OpenGL interop,
        interop.py; raises where it cannot work, saying why); "auto" (default) is "gpu"
        where it works and otherwise "host", with one warning when a CUDA device was asked
        for. Two host reads are for benchmarks and tests: "pbo" reads through the pack
        buffer and copies it to the host, "copy" reads into a buffer and copies that into
        the output (the usual way: what the direct read saves).
        color="gray": one channel, ITU-R BT.601 luma computed in the fragment shader, so
        a third of the bytes is read back (and channels_first costs no copy).
        supersample=k renders every view at k x the resolution and box-filters it down
        (anti-aliasing; depth and segmentation take the sample nearest each pixel centre).
        multisamples=n asks the GL for n-sample MSAA (colour only).
        context: the GLContext to render on, which closes this renderer when it closes
        (None: the default context, shared by every renderer given none; with a CUDA
        `device`, a process's first context opens the EGL device that is that CUDA device,
        backend.context_for_cuda).
        exact_tiles=True makes a view's pixels bit-identical wherever its tile sits, so whatever
        its world's slot and the batch size (a geometry stage clips and places each triangle
        and the fragment stage evaluates every varying and depth inside the tile: shaders/
        exact.geom); it costs render time (docs/renderer.md). Shadow maps are not covered.
        layered=True draws every view into its own layer of an array texture instead of a tile
        of a column (gl_Layer from the vertex stage): every view is rasterised at the same window
        coordinates, so its pixels do not depend on its slot either, at less cost than exact_tiles
        (docs/levels.md); not with exact_tiles or multisamples, and read back to the host.
        impostors: "auto" draws sphere groups as ray-cast impostors (one quad an instance, exact
        depth and normals; impostors.py) where the effects and options allow, True asks for them
        and raises where they cannot be drawn, False (default) draws every mesh."""
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a marl_render.Scene, got {describe(scene)}")
        if not isinstance(exact_tiles, (bool, np.bool_)):
            raise TypeError(f"exact_tiles must be a bool, got {describe(exact_tiles)}")
        self.exact_tiles = bool(exact_tiles)
        interop.check_readback(readback, self.READBACKS)
        self.device = torch_device("device", device)
        interop.check_device(readback, self.device)
        if not isinstance(layered, (bool, np.bool_)):
            raise TypeError(f"layered must be a bool, got {describe(layered)}")
        self.layered = bool(layered)
        if self.layered and (self.exact_tiles or multisamples):
            raise ValueError("layered=True cannot be combined with exact_tiles or multisamples "
                             "(not implemented)")
        if self.layered and (readback in ("gpu", "pbo") or self.device.type != "cpu"):
            raise ValueError("layered=True reads back to the host only (not implemented with the pack buffer or "
                             f"a CUDA device), got readback={readback!r}, "
                             f"device={str(self.device)!r}")
        if not isinstance(color, str) or color not in self.COLORS:
            raise ValueError(f"color must be one of {list(self.COLORS)}, got {color!r}")
        self.color, self.channels = color, self.COLORS[color]
        self.supersample = positive_int("supersample", supersample)
        self._staging = self._accumulator = None  # reused buffers of reads that need a copy afterwards
        if isinstance(multisamples, (bool, np.bool_)) or not isinstance(multisamples, (int, np.integer)) \
                or multisamples < 0:
            raise ValueError(f"multisamples must be an int >= 0, got {multisamples!r}")
        multisamples = int(multisamples)
        if multisamples and {"depth", "segmentation"} & set(scene.effects):
            raise ValueError("multisamples cannot be combined with the depth or segmentation outputs (their "
                             "bit-packed samples would be averaged); use supersample instead")
        if multisamples and "appearance" in scene.effects:
            raise ValueError("multisamples cannot be combined with the appearance effect (MSAA resolves its own "
                             "buffer over the sky copied into each framebuffer, sky.py); use supersample instead")
        self.multisamples = multisamples
        # Checked before any GL object: the names of the groups drawn as impostors.
        self.impostor_groups = sphere_impostors.choose(scene, impostors, multisamples=multisamples,
                                                       exact_tiles=self.exact_tiles)
        height, width = scene.resolution
        self.scene = scene
        self.readback = readback
        self.channels_first = bool(channels_first)
        self.last_timings: dict[str, float] = {}  # seconds per stage of the last render()
        self._closed = False
        if context is None and egl_device_index is None and self.device.type == "cuda":
            context = backend.context_for_cuda(self.device.index if self.device.index is not None
                                               else torch.cuda.current_device())
        elif context is None:
            context = backend.context(egl_device_index)
        elif not isinstance(context, backend.GLContext):
            raise TypeError(f"context must be a marl_render.GLContext or None, got {describe(context)}")
        elif egl_device_index is not None and egl_device_index != context.device_index:
            raise ValueError(f"egl_device_index={egl_device_index!r} was given with a context on EGL device "
                             f"{context.device_index}; give one or the other")
        context.check_usable()
        self._context = context
        gl_max = self._context.info().max_framebuffer_size
        if max_framebuffer_size is None:
            max_framebuffer_size = gl_max
        if not isinstance(max_framebuffer_size, int) or not 1 <= max_framebuffer_size <= gl_max:
            raise ValueError(f"max_framebuffer_size must be an int in [1, {gl_max}], got {max_framebuffer_size!r}")
        if "shadows" in scene.effects:  # an atlas GL cannot hold is named as such, not as a memory shortage
            atlas_layout(scene.num_worlds, scene.shadows.resolution, gl_max)
        memory.check_fits(memory.renderer_bytes(scene, self.supersample),
                          f"a BatchRenderer of num_worlds={scene.num_worlds} x agents_per_world="
                          f"{scene.agents_per_world} at resolution {height}x{width} (supersample={self.supersample})",
                          "lower num_worlds, agents_per_world, resolution or supersample")
        height, width = scene.resolution
        k = self.supersample
        if self.layered:
            with self._context.current():
                max_layers = max_array_texture_layers()  # the `readback` argument hides the module here
            self.layout: TileLayout = layer_layout(scene.num_views, height * k, width * k, max_framebuffer_size,
                                                   max_layers)
        else:
            self.layout = column_layout(scene.num_views, height * k, width * k, max_framebuffer_size)
        self.effects = frozenset(scene.effects)
        self.packer = FramePacker(scene, self.layout)  # the state and its packing; this class draws it
        self._passes: list[RenderPass] = []
        self._groups: dict[str, DrawGroup] = {}
        self._targets = PandaTargets(self._groups)  # the packer writes into their textures
        self.shadow_pass = None
        self._sky = None  # the appearance effect's sky images (sky.py)
        self._pack = None  # the GL pixel-pack buffer of the "pbo" and interop reads (readback.PackBuffer)
        self._pack_layout: dict[str, tuple] = {}  # output -> (byte offset in the pack buffer, bytes per view)
        self._interop = None  # interop.PackBufferInterop where frames go device to device
        self._unpack_staging: dict[str, torch.Tensor] = {}  # pack reads that need a copy afterwards
        self._looks_version = -1  # the version of the appearance rows the sky and shadows show
        try:
            # Panda3D opens each framebuffer right away; until it is inactive, any frame
            # drawn by another thread would draw it too.
            with self._context.current():
                self._context.own(self)  # closed with the context
                self._build_passes()
                self._build_groups()
                if "shadows" in self.effects:
                    self.shadow_pass = ShadowPass(self._context, scene, self._groups, gl_max)
                    for render_pass in self._passes:
                        self.shadow_pass.bind(render_pass.root)
                if readback in interop.READBACKS:  # the GL context must be current for cudaGLGetDevices
                    self._interop = interop.open_interop(readback, self.device)
                if readback == "pbo" or self._interop is not None:
                    self._make_pack_buffer()
        except BaseException:
            self.close()  # free whatever GL objects were made before the failure
            raise

    # ------------------------------------------------------------------ state (kept by the packer)
    @property
    def world_origin(self) -> torch.Tensor:
        """Each world's origin, float64 [W, 3], which instance rows are relative to."""
        return self.packer.world_origin

    @property
    def camera_position(self) -> torch.Tensor:
        """Every view's camera position in its world's frame, float64 [W, A, 3] (set_cameras sets it)."""
        return self.packer.camera_position

    @property
    def camera_rotation(self) -> torch.Tensor:
        """Every view's camera orientation, a unit quaternion (w, x, y, z), float32 [W, A, 4] (set_cameras sets it)."""
        return self.packer.camera_rotation

    @property
    def fov_y(self) -> torch.Tensor:
        """Every view's vertical field of view in degrees, float64 [W, A]."""
        return self.packer.fov_y

    @property
    def near(self) -> torch.Tensor:
        """Every view's near clipping distance, float64 [W, A]."""
        return self.packer.near

    @property
    def far(self) -> torch.Tensor:
        """Every view's far clipping distance, float64 [W, A]."""
        return self.packer.far

    # ------------------------------------------------------------------ GL objects
    def _build_passes(self):
        """One framebuffer per column of views, each with its own scene root and camera."""
        from panda3d.core import LVecBase2f

        self.views_texture = self._targets.views_texture = buffer_texture("views", self.packer.view_texels())
        lighting, fog = self.scene.lighting, self.scene.fog
        direction = np.asarray(lighting.direction, dtype=float)
        self._shared_inputs = {
            "views": self.views_texture, "agents": int_input(self.scene.agents_per_world),
            "light_direction": vec3_input(direction / np.linalg.norm(direction)),
            "light_color": vec3_input(lighting.color),
            "ambient_color": vec3_input(lighting.ambient), "fog_color": vec3_input(fog.color),
            "fog_density": float(fog.density),
            "tile_size": LVecBase2f(self.layout.tile_width, self.layout.tile_height)}
        if "appearance" in self.effects:
            self.appearance_texture = self._targets.appearance_texture = buffer_texture(
                "appearance", self.scene.num_worlds * row_layouts.APPEARANCE.texels)
            self._shared_inputs["appearance"] = self.appearance_texture
            self._sky = SkyImages(self.layout, self.scene.agents_per_world, gray=self.color == "gray",
                                  layered=self.layered)
        for index in range(self.layout.num_passes):
            self._passes.append(self._make_pass(self.layout.pass_views(index)))

    def _make_pass(self, views: range) -> RenderPass:
        return make_pass(self._context, self.layout, views, effects=self.effects, multisamples=self.multisamples,
                         gray=self.color == "gray", layered=self.layered, background=self.scene.background,
                         shared_inputs=self._shared_inputs)

    def _build_groups(self):
        from panda3d.core import DepthTestAttrib, NodePath, OmniBoundingVolume

        groups = [(g, True) for g in self.scene.static.values()] + [(g, False) for g in self.scene.groups.values()]
        for order, (group, static) in enumerate(groups):
            mesh = group.mesh
            textured = group.texture is not None
            # Static geometry has no joints to pose: a skinned mesh is drawn in its bind pose.
            joints = mesh.num_joints if isinstance(mesh, skinning.SkinnedMesh) and not static else 0
            procedural = isinstance(mesh, MeshData) and not joints
            impostor = group.name in self.impostor_groups
            if impostor:
                node = sphere_impostors.quad_node()
            elif joints:
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
            surface = group.name in self.packer.surface_roles
            draw_order = order
            if surface:
                # Floors and walls with patterns (the costly fragments) go last, so that the depth
                # test drops what objects hide before it is shaded. A tie against another group
                # keeps its winner: equal depths pass for these (drawn first, they won ties under
                # "less"), drawn in reverse order among themselves. Within one such group the later
                # of two overlapping triangles now wins (walls' coplanar corners: one colour and
                # pattern, so at most a pattern edge rounded the other way).
                draw_order = 2 * len(groups) - order
                node.set_attrib(DepthTestAttrib.make(DepthTestAttrib.M_less_equal))
            node.set_bin("fixed", draw_order)
            node.node().set_bounds(OmniBoundingVolume())
            node.node().set_final(True)
            variant = functools.partial(
                shaders.defines_for, self.effects, static=static, textured=textured, flat=procedural and mesh.flat,
                corners=procedural, gray=self.color == "gray", shadow_pcf=self.scene.shadows.pcf, joints=joints,
                influences=mesh.influences if joints else 4, role=0 if static else ROLES[group.role],
                exact=self.exact_tiles, layered=self.layered)
            node.set_shader(sphere_impostors.compiled(sphere_impostors.defines(
                self.effects, static=static, gray=self.color == "gray", layered=self.layered)) if impostor
                else shaders.compiled(variant(surface=surface)))
            if textured and "texture" in self.effects:
                node.set_texture(panda_texture(group.texture, group.name), 1)
            packing = self.packer.groups[group.name]
            count = packing.count
            instances = buffer_texture(f"instances:{group.name}", self.packer.instance_texels(group.name))
            pairs = buffer_texture(f"pairs:{group.name}", self.packer.pair_capacity(group.name), integer=True)
            draw = DrawGroup(node, count, static, instances, pairs)
            node.set_shader_input("instances", draw.instances)
            node.set_shader_input("pairs", draw.pairs)
            node.set_shader_input("capacity", int_input(count))
            node.set_shader_input("segment_base", int_input(group.segment_base))
            if surface:  # the worlds whose floors or walls show no pattern: the variant without
                plain = node.copy_to(NodePath())
                plain.set_shader(shaders.compiled(variant(surface=False)))
                draw.plain_nodes = per_pass(plain, self._passes)
            draw.pass_nodes = per_pass(node, self._passes, sphere_impostors.QUADS_PER_INSTANCE if impostor else None)
            self._groups[group.name] = draw
            if static:
                self.packer.pack_static(group, self._targets.instances(group.name))

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
        self.packer.update(group, position=position, rotation=rotation, scale=scale, color=color, active=active,
                           owner=owner, joints=joints)

    @one_thread
    def set_cameras(self, *, position=None, rotation=None, look_at=None, fov_y=None, near=None, far=None,
                    mount_offset=None, mount_pitch=None) -> None:
        """Free cameras: position [W,A,3], rotation [W,A,4] or look_at [W,A,3] targets;
        fov_y (radians), near, far: scalars or [W,A]. Mounted cameras take fov_y/near/far and, per
        view, mount_offset [W,A,3] (metres in the instance's frame) and mount_pitch [W,A] (radians in
        [-pi/2, pi/2], positive looks up), which replace scene.mount_cameras' offset and pitch."""
        self._check_open()
        self.packer.set_cameras(position=position, rotation=rotation, look_at=look_at, fov_y=fov_y, near=near,
                                far=far, mount_offset=mount_offset, mount_pitch=mount_pitch)

    @one_thread
    def set_appearance(self, **kwargs) -> None:
        """Each world's look, for a scene that declares the "appearance" effect (appearance.py): any of
        light_direction [W,3] (non-zero, pointing from the light), light_color [W,3] and ambient [W,3]
        (>= 0), sky [W,3], floor [W,3] and wall [W,3] (RGB in [0,1]: the colour of instances with that
        role), floor_pattern [W] and wall_pattern [W] (int index into appearance.PATTERNS),
        pattern_scale [W,2] (cells per metre of floor and wall patterns), pattern_contrast [W,2] (in
        [0,1]), hue_shift [W] (turns), saturation [W] and value [W] (scales, >= 0) of the colours of
        every other instance. Each may broadcast to its shape (one value for all worlds); those not
        given keep their values. Everything is validated before anything is stored."""
        self._check_open()
        if self.packer.appearance is None:
            raise ValueError(f"set_appearance needs a scene that declares the 'appearance' effect, got effects "
                             f"{list(self.scene.effects)}")

        def drawable(staged):
            if self.shadow_pass is not None and "light_direction" in staged:  # a shadow map along each light
                light_projection(staged["light_direction"], self.shadow_pass.bounds)
            for name in ("floor_pattern", "wall_pattern"):
                if not self.scene.surface_patterns and name in staged and bool(staged[name].any()):
                    raise ValueError(f"{name} must be 0 (plain): the scene was built with surface_patterns=False, "
                                     f"got kinds {sorted(set(staged[name].tolist()))}")

        self.packer.appearance.set(check=drawable, **kwargs)

    # ------------------------------------------------------------------ rendering
    @one_thread
    def render(self) -> Frame:
        """Draw all views; returns tensors the caller owns. Any thread may call it (one at a
        time per renderer): the GL context is made current in the calling thread, for the
        frame and the GL reads that follow it."""
        self._check_open()
        with self._context.current():  # raises in a forked child
            self._prepare()
            self.last_timings.update(draw=0.0, read=0.0, copy=0.0)
            try:
                return self._draw_and_read()
            except AssertionError as error:  # Panda3D's C++ assertions (e.g. an input it could not bind)
                # The variants of this draw may be left unusable: never hand them out again.
                shaders.forget_compiled()
                raise backend.ShaderCompileError(f"the frame failed in Panda3D: {error}".strip()) from error

    def _prepare(self) -> list[str]:
        """Pack the frame into the buffer textures (packing.py) and bring the shadow atlas up
        to date. Returns the groups whose instance data was packed (to be uploaded)."""
        timings = self.packer.prepare(self._targets)
        packed_groups = timings.pop("packed")
        looks = self.packer.appearance
        new_looks = looks is not None and self._looks_version != looks.version
        if new_looks:
            self._sky.set_sky(looks.values["sky"])
            if self.shadow_pass is not None:  # each world's map along its own light
                self.shadow_pass.set_light_directions(looks.light_directions())
            self._looks_version = looks.version
        if self.shadow_pass is not None:  # the atlas depends on the instances, not on the cameras
            self.shadow_pass.prepare(self.packer, changed=bool(packed_groups) or new_looks)
        self.last_timings = timings
        return packed_groups

    def _draw_and_read(self) -> Frame:
        """Draw every pass, then read them: last_timings gets "draw" (packing aside, what the
        frame costs before the reads), "read" (the GL reads, which wait for the drawing they
        read) and "copy" (the bytes moved and reshaped after them: out of the pack buffer, or
        to a CUDA device, channels-first and supersampling). These are host clocks: on a GPU
        the GL returns before its work is done, so the wait for the drawing lands in "read"
        (host reads) or in "copy" (interop: mapping the buffer for CUDA waits for the GL), and
        the device-to-device copy itself, queued on the stream, in whatever waits for it next."""
        s = self.scene
        W, A = s.num_worlds, s.agents_per_world
        height, width = s.resolution
        C = self.channels
        rgb_shape = (W * A, C, height, width) if self.channels_first else (W * A, height, width, C)
        on = self.device if self._interop is not None else torch.device("cpu")  # where the reads land
        rgb = torch.empty(rgb_shape, dtype=torch.uint8, device=on)
        depth = torch.empty(W * A, height, width, dtype=torch.float32, device=on) if "depth" in self.effects else None
        segmentation = (torch.empty(W * A, height, width, dtype=torch.int32, device=on)
                        if "segmentation" in self.effects else None)
        started = time.perf_counter()
        for index in range(len(self._passes)):
            for name, draw in self._groups.items():
                packing = self.packer.groups[name]
                first, count = packing.pass_ranges[index]
                if draw.plain_nodes is not None:
                    plain = packing.plain_counts[index]
                    count -= plain
                    set_draw(draw.plain_nodes[index], first + count, plain)
                set_draw(draw.pass_nodes[index], first, count)
        if self._sky is not None:
            if self._passes[0].texture_ids is None:  # the colour textures are made by the first frame
                self._render_frame()
                self._texture_ids()
            for index, render_pass in enumerate(self._passes):
                self._sky.fill(index, render_pass.texture_ids["color"])
        self._render_frame()
        read_seconds = copy_seconds = 0.0
        for index, render_pass in enumerate(self._passes):
            if self._pack is None:
                read, copy = self._read_pass(render_pass, rgb, depth, segmentation)
            else:
                read, copy = self._read_pass_into_pack(render_pass), 0.0
            read_seconds, copy_seconds = read_seconds + read, copy_seconds + copy
            if self._sky is not None:  # the next frame's sky, while llvmpipe still draws the passes after this one
                self._sky.refill(index, render_pass.texture_ids["color"])
        self._check_shaders()  # after the reads: Panda3D reports some failures of the frame only then
        read_done = time.perf_counter()
        if self._pack is not None:
            self._unpack(rgb, depth, segmentation)
        if on != self.device:  # the host reads of frames for a CUDA device
            rgb, depth, segmentation = (None if t is None else t.to(self.device) for t in (rgb, depth, segmentation))
        self.last_timings.update(draw=read_done - started - read_seconds - copy_seconds, read=read_seconds,
                                 copy=copy_seconds + time.perf_counter() - read_done)
        rgb = rgb.view((W, A) + rgb_shape[1:])
        return Frame(rgb, None if depth is None else depth.view(W, A, height, width),
                     None if segmentation is None else segmentation.view(W, A, height, width))

    def _render_frame(self) -> None:
        """Every pass is drawn in one frame before any is read: llvmpipe rasterises one
        framebuffer on its threads while the next one is being drawn. The shadow atlas,
        when out of date, is drawn first in the same frame (its buffer sorts before them)."""
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

    def _texture_ids(self) -> None:
        """The GL names of every pass's render textures (they exist once a frame drew them)."""
        gsg = self._context.gsg
        for render_pass in self._passes:
            if render_pass.texture_ids is None:
                render_pass.texture_ids = {name: readback.texture_id(texture, gsg) for name, texture in
                                           [("color", render_pass.color), *render_pass.aux.items()]}

    def _check_shaders(self):
        """A variant that failed to compile draws nothing: raise with the GL log instead."""
        log = self._context.drain_log()
        failed = [name for name, draw in self._groups.items()
                  if any(entry[0].get_shader().get_error_flag()
                         for entry in draw.pass_nodes + (draw.plain_nodes or []))]
        failed += self.shadow_pass.failed_groups() if self.shadow_pass is not None else []
        # A shader input Panda3D could not bind (a NaN uniform was one way) fails the draw without an
        # error flag and leaves the variant unusable for every later renderer: a failure too.
        unbound = [line for line in log if "Shader input" in line and "is not present" in line]
        if unbound and not failed:
            failed = sorted(self._groups)
        if failed:
            shaders.forget_compiled()  # the failed Shader keeps its error flag: never hand it out again
            text = "\n".join(log or self._context.recent_log[-20:])
            raise backend.ShaderCompileError(f"the shader of group(s) {failed} failed to compile or link:\n{text}")

    # ------------------------------------------------------------------ helpers / lifecycle
    def _check_open(self):
        if self._closed:
            raise RuntimeError("this BatchRenderer is closed; create a new one")

    @property
    def num_views(self) -> int:
        """The number of views each render draws, V = W * A."""
        return self.scene.num_views

    @property
    def granted_multisamples(self) -> int:
        """MSAA samples the GL gave the framebuffers; never fewer than asked, as the constructor refuses that."""
        self._check_open()
        return min(p.buffer.get_fb_properties().get_multisamples() for p in self._passes)

    def instance_state(self, group: str) -> dict:
        """Copies of a group's current per-instance tensors."""
        self.packer.check_group(group)
        return {k: v.clone() for k, v in self.packer.state[group].items()}

    def close(self) -> None:
        """Free the framebuffer and textures; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        textures = [getattr(self, "views_texture", None), getattr(self, "appearance_texture", None)]
        passes = getattr(self, "_passes", [])
        shadow_pass = getattr(self, "shadow_pass", None)
        if (passes or shadow_pass is not None) and self._context.pid == os.getpid():
            # a forked child must not touch its parent's GL objects
            with self._context.current():  # Panda3D deletes the framebuffers right away
                if getattr(self, "_interop", None) is not None:  # CUDA lets go before the GL buffer goes
                    self._interop.close()
                if getattr(self, "_pack", None) is not None:
                    self._pack.delete()
                if getattr(self, "_sky", None) is not None:
                    self._sky.close()
                if shadow_pass is not None:
                    shadow_pass.close()
                for render_pass in passes:
                    render_pass.buffer.clear_render_textures()
                    self._context.engine.remove_window(render_pass.buffer)
                self._context.drop_render_texture_events()
        self.shadow_pass = None
        self._interop = self._pack = None
        for render_pass in passes:
            render_pass.root.remove_node()
            textures += [render_pass.color, *render_pass.aux.values()]
        self._passes = []
        textures += [t for g in self._groups.values() for t in (g.instances, g.pairs)]
        targets = getattr(self, "_targets", None)
        if targets is not None:  # the packer's views keep Panda3D's arrays alive
            targets.release()
        for texture in textures:
            if texture is not None:
                texture.release_all()
                texture.clear_ram_image()
        self._groups.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __reduce__(self):  # copy.copy, copy.deepcopy and pickle all come here
        raise unpicklable("a marl_render BatchRenderer", "marl_render.BatchRenderer")

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: Panda3D may already be gone
            pass

