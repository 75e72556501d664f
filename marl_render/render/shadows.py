"""Shadows on demand: every world's shadow map in one depth-only pass, into one atlas.

Each world has one directional light (Scene.lighting.direction) shared by all of its
views, so its shadow map is drawn once per world and read by every view of it. The pass
reuses the main pass's machinery with the light as the one "view" of each world:
- an orthographic view-projection per world, fitted to Scene.shadows.bounds and packed
  in the views layout (so static groups keep their hi/lo origin arithmetic);
- one square tile per world in a near-square atlas grid (not the views' single column:
  one texture must hold every world's map), drawn by the same vertex shader
  (shaders/batch.vert with SHADOW_CASTER: grid placement, four clip planes; the
  fragment stage is empty);
- each group's instances culled against the light's box in torch, as views are.

The atlas is the depth plane of an offscreen buffer of its own, bound as a texture. That
buffer sorts before every framebuffer of the views, so Panda3D draws it first in the one
render_frame that draws them all, and they read it (#ifdef EFFECT_SHADOWS in
shaders/batch.frag). It is drawn only in frames where an instance group or a world origin
changed. A fragment finds its texel from its own world position (projected by the light
in the vertex stage), so where its view's tile lies does not matter.

Only the faces turned away from the light are drawn into the map: a lit face then lies
in front of the stored depth by its mesh's thickness and never shadows itself. The
fragment shader compares each texel with the receiver's own depth at that texel (the
receiver's plane, from screen derivatives), so sloped receivers need no slope bias, and an
outline is off by at most the texel grid. Single-sided meshes (the "plane") cast no shadow.

Cost: the pass clears and rasterises num_worlds x resolution^2 depth texels per frame in
which anything moved; the main pass adds one (PCF: four) texel reads per fragment.
"""
from __future__ import annotations

import numpy as np
import torch

from ..assets.meshes import MeshData
from ..assets.skinning import SkinnedMesh
from . import backend, row_layouts, shaders
from .culling import frustum_planes
from .panda_buffers import TextureMemory, buffer_texture, clip_distances, int_input
from .scene import Scene
from .tiling import TileLayout, plan_layout

# Casters up to this many diagonals of the bounds box towards the light still cast into it.
CASTER_REACH = 2.0
# How close (metres along the light) a receiver may come to a stored face and still count
# as level with it. The shader compares each texel with the receiver's own depth at that
# texel, so this only absorbs float rounding.
SHADOW_BIAS_M = 1e-3
BUFFER_SORT = -1  # before the views' framebuffers (sort 0) in every render_frame


def light_axes(direction) -> torch.Tensor:
    """[..., 3, 3] float64 rows (right, up, forward) of the light's frame; forward = direction [..., 3]."""
    forward = torch.as_tensor(direction, dtype=torch.float64)
    forward = forward / forward.norm(dim=-1, keepdim=True)
    steep = forward[..., 2:].abs() >= 0.99  # the up hint must not be parallel to the light
    hint = torch.where(steep, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                       torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    right = torch.linalg.cross(forward, hint)
    right = right / right.norm(dim=-1, keepdim=True)
    return torch.stack((right, torch.linalg.cross(right, forward), forward), -2)


def static_bounds(scene: Scene) -> tuple:
    """((x0, y0, z0), (x1, y1, z1)): the box around all static geometry, exact for MeshData."""
    from ..util.transforms import quat_rotate

    lows, highs = [], []
    for group in scene.static.values():
        mesh = group.mesh
        if isinstance(mesh, MeshData):
            points = torch.from_numpy(mesh.positions.astype(np.float64))
        else:
            low, high = mesh.get_tight_bounds()
            points = torch.tensor([[x, y, z] for x in (low.x, high.x) for y in (low.y, high.y)
                                   for z in (low.z, high.z)], dtype=torch.float64)
        scaled = points[None] * group.scale.to(torch.float64)[:, None]  # [K, N, 3]
        rotation = group.rotation.to(torch.float64)[:, None].expand(-1, points.shape[0], 4)
        world = quat_rotate(rotation, scaled) + group.position[:, None]
        lows.append(world.reshape(-1, 3).amin(0))
        highs.append(world.reshape(-1, 3).amax(0))
    if not lows:
        raise ValueError("shadows.bounds must be given when the scene has no static geometry to fit it to, "
                         "got None")
    return tuple(torch.stack(lows).amin(0).tolist()), tuple(torch.stack(highs).amax(0).tolist())


def light_projection(direction, bounds) -> tuple[torch.Tensor, float]:
    """(view-projection [..., 4, 4] float64 in the world frame, depth bias in depth units) of one
    direction [3] or one per world [W, 3] (the appearance effect's lights; the bias is then the
    largest of theirs: it only absorbs rounding, SHADOW_BIAS_M).

    Orthographic along the light: x, y span the bounds' corners seen from the light, depth
    spans them too and reaches CASTER_REACH diagonals further towards the light."""
    axes = light_axes(direction)
    low, high = (torch.tensor(b, dtype=torch.float64) for b in bounds)
    corners = torch.stack([torch.where(torch.tensor(mask, dtype=torch.bool), high, low)
                           for mask in np.ndindex(2, 2, 2)])  # [8, 3]
    local = corners @ axes.transpose(-1, -2)  # [..., 8, 3] in (right, up, forward)
    near, far = local.amin(-2), local.amax(-2)
    near[..., 2] -= CASTER_REACH * float((high - low).norm())
    extent = far - near
    if bool((extent[..., :2].amin(-1) <= 1e-9 * extent.amax(-1).clamp(min=1.0)).any()):
        raise ValueError(f"shadows.bounds must have an area seen along lighting.direction (or each world's "
                         f"light_direction) {torch.as_tensor(direction).tolist()}, got bounds {bounds}")
    matrix = torch.eye(4, dtype=torch.float64).expand(*extent.shape[:-1], 4, 4).clone()
    matrix[..., :3, :3] = 2 * axes / extent[..., :, None]
    matrix[..., :3, 3] = -2 * near / extent - 1
    return matrix, max(SHADOW_BIAS_M / float(extent[..., 2].min()), 1e-6)  # window depth is (z - near) / extent


def atlas_layout(num_worlds: int, resolution: int, max_size: int) -> TileLayout:
    """One square tile per world in a near-square grid; the whole atlas in one texture."""
    try:
        layout = plan_layout(num_worlds, resolution, resolution, max_size)
    except ValueError:
        layout = None
    if layout is None or layout.num_passes > 1:
        raise ValueError(f"shadows.resolution must let {num_worlds} shadow maps fit in one "
                         f"{max_size}x{max_size} atlas (the GL limit), got {resolution}; lower it or num_worlds")
    return layout


class ShadowPass:
    """The shadow atlas of a BatchRenderer: its buffer, light matrices and caster nodes.

    groups: the renderer's draw groups by name (draw_groups.DrawGroup: node, count, static, instance
    texture); the casters draw the same nodes and instance data. Which instances cast is the
    packer's answer (FramePacker.light_pairs), as for the main pass."""

    def __init__(self, context, scene: Scene, groups: dict, max_size: int):
        settings = scene.shadows
        self.scene, self._context = scene, context
        self.layout = atlas_layout(scene.num_worlds, settings.resolution, max_size)
        bounds = settings.bounds if settings.bounds is not None else static_bounds(scene)
        self.bounds = bounds
        self.light, self.bias = light_projection(scene.lighting.direction, bounds)  # [4, 4], or [W, 4, 4]
        self._roots = []  # the main pass roots that read the atlas (bind)
        self.buffer = self.root = None
        self.casters, self.pairs, self.pair_offsets = {}, {}, {}
        self.pair_memory: dict[str, TextureMemory] = {}  # views of the pairs' RAM images, made once
        self.light_memory = None
        self.pending = True  # the atlas must be drawn in the next frame
        self.lights = self.atlas = None
        try:
            self._build(context, groups)
        except BaseException:
            self.close()  # free whatever GL objects were made before the failure
            raise

    def _build(self, context, groups: dict) -> None:
        from panda3d.core import (
            Camera,
            ColorWriteAttrib,
            CullFaceAttrib,
            DepthTestAttrib,
            DepthWriteAttrib,
            FrameBufferProperties,
            GraphicsOutput,
            GraphicsPipe,
            LVecBase2i,
            NodePath,
            OmniBoundingVolume,
            SamplerState,
            Texture,
            WindowProperties,
        )

        width, height = self.layout.framebuffer_size
        props = FrameBufferProperties()
        props.set_depth_bits(32)
        self.buffer = context.engine.make_output(
            # One name for all atlases: Panda3D keeps a statistics collector per buffer name.
            context.pipe, "marl_render_shadows", BUFFER_SORT, props,
            WindowProperties.size(width, height), GraphicsPipe.BF_refuse_window, context.gsg, context.host)
        if self.buffer is None:
            raise backend.GLUnavailableError(f"could not create a {width}x{height} shadow atlas; lower "
                                             "shadows.resolution or num_worlds")
        self.atlas = Texture("shadow_atlas")
        self.buffer.add_render_texture(self.atlas, GraphicsOutput.RTM_bind_or_copy, GraphicsOutput.RTP_depth)
        context.drop_render_texture_events()
        self.atlas.set_minfilter(SamplerState.FT_nearest)  # read with texelFetch; compares are in the shader
        self.atlas.set_magfilter(SamplerState.FT_nearest)
        self.buffer.set_clear_color_active(False)  # depth only
        self.buffer.set_clear_depth_active(True)
        self.buffer.set_clear_depth(1.0)
        self.buffer.set_active(False)

        self.root = NodePath("marl_render_shadow_root")
        camera = Camera("shadow_tiles")
        camera.set_cull_bounds(OmniBoundingVolume())
        region = self.buffer.make_display_region()
        region.set_camera(self.root.attach_new_node(camera))
        # Tiles are flipped like views (winding reversed): culling clockwise keeps the
        # faces turned away from the light.
        self.root.set_attrib(CullFaceAttrib.make(CullFaceAttrib.M_cull_clockwise))
        self.root.set_attrib(DepthTestAttrib.make(DepthTestAttrib.M_less))
        self.root.set_attrib(DepthWriteAttrib.make(DepthWriteAttrib.M_on))
        self.root.set_attrib(ColorWriteAttrib.make(ColorWriteAttrib.C_off))
        self.root.set_attrib(clip_distances(4))  # each world's square of the atlas (batch.vert)
        W = self.scene.num_worlds
        self.lights = buffer_texture("lights", W * row_layouts.VIEW.texels)
        self.light_memory = TextureMemory(self.lights, np.float32)
        self.root.set_shader_input("views", self.lights)
        self.root.set_shader_input("agents", int_input(1))
        self.root.set_shader_input("grid", LVecBase2i(self.layout.columns, self.layout.rows))
        self.root.set_shader_input("view_offset", int_input(0))
        for name, draw in groups.items():
            caster = draw.node.copy_to(self.root)  # shares the Geom; the state is replaced below
            mesh = (self.scene.static if draw.static else self.scene.groups)[name].mesh
            # Skinned groups cast their posed shape (static ones stay in the bind pose, as drawn).
            joints = mesh.num_joints if isinstance(mesh, SkinnedMesh) and not draw.static else 0
            caster.set_shader(shaders.compiled_caster(shaders.caster_defines(
                static=draw.static, joints=joints, influences=mesh.influences if joints else 4)))
            self.pairs[name] = buffer_texture(f"shadow_pairs:{name}", W * draw.count, integer=True)
            self.pair_memory[name] = TextureMemory(self.pairs[name], np.int32)
            self.pair_offsets[name] = int_input(0)
            caster.set_shader_input("instances", draw.instances)
            caster.set_shader_input("pairs", self.pairs[name])
            caster.set_shader_input("pair_offset", self.pair_offsets[name])
            caster.set_shader_input("capacity", int_input(draw.count))
            self.casters[name] = caster

    def bind(self, root) -> None:
        """Shader inputs of the main pass (its EFFECT_SHADOWS variants)."""
        from panda3d.core import LVecBase2i

        self._roots.append(root)
        root.set_shader_input("lights", self.lights)
        root.set_shader_input("shadow_atlas", self.atlas)
        root.set_shader_input("shadow_tiles", LVecBase2i(self.layout.columns, self.layout.tile_width))
        root.set_shader_input("shadow_bias", float(self.bias))

    def set_light_directions(self, directions: torch.Tensor) -> None:
        """One light direction per world ([W, 3], the appearance effect's): every map is drawn again."""
        self.light, self.bias = light_projection(directions, self.bounds)
        for root in self._roots:
            root.set_shader_input("shadow_bias", float(self.bias))
        self.pending = True

    def prepare(self, packer, changed: bool) -> None:
        """Light matrices and culled casters for the next frame, when anything moved. The packer
        (packing.FramePacker) holds the instances and culls them against the lights."""
        if not (changed or self.pending):
            return
        self._pack_lights(packer.world_origin)
        planes = frustum_planes(self._world_matrices(packer.world_origin)[:, None])  # [W, 1, 6, 4]
        for name, pairs in packer.light_pairs(planes).items():
            caster = self.casters[name]
            if len(pairs) == 0:  # Panda3D would draw an instance count of 0 once
                caster.hide()
                continue
            self.pair_memory[name]()[: len(pairs)] = pairs
            caster.show()
            caster.set_instance_count(len(pairs))
        self.pending = True

    def _world_matrices(self, world_origin: torch.Tensor) -> torch.Tensor:
        """[W, 4, 4] float64: the light's view-projection in each world's origin-relative frame."""
        if self.light.ndim == 3:  # a light per world
            matrices = self.light.clone()
            matrices[:, :3, 3] += (self.light[:, :3, :3] @ world_origin[..., None])[..., 0]
            return matrices
        matrices = self.light.expand(len(world_origin), 4, 4).clone()
        matrices[:, :3, 3] += world_origin @ self.light[:3, :3].T
        return matrices

    def _pack_lights(self, world_origin: torch.Tensor) -> None:
        row = row_layouts.VIEW  # one "view" per world: the light's
        memory = self.light_memory().view(-1, row.texels, 4)
        first = row.fields["projection"].texel
        memory[:, first:first + row_layouts.VIEW_PROJECTION_TEXELS] = self._world_matrices(world_origin).transpose(1, 2)
        origin_hi = world_origin.to(torch.float32)
        memory[(slice(None), *row["origin_hi"])] = origin_hi
        memory[(slice(None), *row["origin_lo"])] = (world_origin - origin_hi.to(torch.float64)).to(torch.float32)
        memory[(slice(None), *row["near"])] = 0.0
        memory[(slice(None), *row["far"])] = 0.0

    def set_active(self, on: bool) -> None:
        """Draw the atlas in the coming render_frame (only if it is out of date)."""
        self.buffer.set_active(on and self.pending)

    def drawn(self) -> None:
        """The frame that drew the atlas is done: it stays valid until something moves."""
        self.pending = False

    def failed_groups(self) -> list[str]:
        return [f"shadow:{name}" for name, node in self.casters.items() if node.get_shader().get_error_flag()]

    def close(self) -> None:
        """Free the buffer and textures; call with the GL context current (context.current())."""
        if self.buffer is not None:
            self.buffer.clear_render_textures()
            self._context.engine.remove_window(self.buffer)
            self._context.drop_render_texture_events()
            self.buffer = None
        if self.root is not None:
            self.root.remove_node()
            self.root = None
        for texture in [self.atlas, self.lights, *self.pairs.values()]:
            if texture is not None:
                texture.release_all()
                texture.clear_ram_image()
        for view in [self.light_memory, *self.pair_memory.values()]:
            if view is not None:
                view.release()
        self.light_memory = None
        self.pair_memory.clear()
        self.pairs.clear()
        self.casters.clear()
