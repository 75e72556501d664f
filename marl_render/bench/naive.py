"""The plain Panda3D way, done well: the baseline the batch renderer is measured against.

One offscreen buffer; one camera and display region per view; one scene root per world
holding ordinary nodes (a pivot per instance, moved by Python calls, with the geometry
and the mounted camera below it); Panda3D's own lights; one readback per frame. It takes
the same Scene and the same update()/set_cameras() arguments as BatchRenderer, so both
can render identical scenes. Used by the benchmarks (`render`, `effects`) and the tests
that compare the two renderers; it loops over worlds and instances in Python on purpose.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from marl_render.assets.meshes import MeshData, to_panda_geom
from marl_render.render import backend
from marl_render.render.renderer import Frame
from marl_render.render.scene import Scene
from marl_render.render.tiling import plan_layout
from marl_render.util.transforms import look_at_quat, normalize_quat


class NaiveRenderer:
    """tiled=True: one buffer with a display region per view (the plain way done well).
    tiled=False: one buffer and readback per view (the first step of the ablation)."""

    def __init__(self, scene: Scene, *, tiled: bool = True):
        from panda3d.core import (
            AmbientLight,
            BitMask32,
            Camera,
            DirectionalLight,
            FrameBufferProperties,
            GraphicsOutput,
            GraphicsPipe,
            NodePath,
            PerspectiveLens,
            Texture,
            WindowProperties,
        )

        self.scene = scene
        ctx = self._context = backend.context()
        height, width = scene.resolution
        self.tiled = tiled
        views = scene.num_views if tiled else 1
        self.layout = plan_layout(views, height, width, ctx.info().max_framebuffer_size)
        if self.layout.num_passes != 1:
            raise ValueError("NaiveRenderer draws all views in one framebuffer; too many views for the GL limit")
        props = FrameBufferProperties()
        props.set_rgba_bits(8, 8, 8, 0)
        props.set_depth_bits(24)
        self.buffers, self.textures = [], []
        for index in range(1 if tiled else scene.num_views):
            with ctx.current():  # the new buffer is open and active until set_active(False)
                buffer = ctx.engine.make_output(ctx.pipe, "marl_render_naive", 0, props,
                                                WindowProperties.size(*self.layout.framebuffer_size),
                                                GraphicsPipe.BF_refuse_window, ctx.gsg, ctx.host)
                buffer.set_active(False)
            texture = Texture(f"naive_color_{index}")
            buffer.add_render_texture(texture, GraphicsOutput.RTM_copy_ram)
            buffer.set_clear_color(tuple(scene.background[:3]) + (1.0,))
            self.buffers.append(buffer)
            self.textures.append(texture)
        ctx.drop_render_texture_events()

        W, A = scene.num_worlds, scene.agents_per_world
        lighting = scene.lighting
        self.world_roots, self.pivots, self.cameras, self.lenses = [], {}, [], []
        templates = {name: self._geometry(g.mesh) for name, g in {**scene.static, **scene.groups}.items()}
        for w in range(W):
            root = NodePath(f"world_{w}")
            if "lighting" in scene.effects:
                ambient = root.attach_new_node(AmbientLight("ambient"))
                ambient.node().set_color(tuple(lighting.ambient) + (1.0,))
                sun = root.attach_new_node(DirectionalLight("sun"))
                sun.node().set_color(tuple(lighting.color) + (1.0,))
                sun.node().set_direction(tuple(float(v) for v in lighting.direction))
                root.set_light(ambient)
                root.set_light(sun)  # fixed-function lighting: the plain way on every GL
            for name, group in scene.static.items():
                for k in range(group.count):
                    node = templates[name].copy_to(root)
                    node.set_pos(*group.position[k].tolist())
                    node.set_quat(tuple(group.rotation[k].tolist()))
                    node.set_scale(*group.scale[k].tolist())
                    node.set_color(*group.color[k].tolist())
            for name, group in scene.groups.items():
                for c in range(group.capacity):
                    pivot = root.attach_new_node(f"{name}_{c}")
                    templates[name].copy_to(pivot)
                    pivot.hide()
                    self.pivots[(name, w, c)] = pivot
            self.world_roots.append(root)

        mount = scene.camera_mount
        for v in range(scene.num_views):
            w, a = divmod(v, A)
            lens = PerspectiveLens()
            camera = Camera(f"view_{v}", lens)
            camera.set_camera_mask(BitMask32.bit(a))
            if mount is None:
                camera_np = self.world_roots[w].attach_new_node(camera)
            else:
                camera_np = self.pivots[(mount.group, w, mount.instance[a])].attach_new_node(camera)
                camera_np.set_pos(*mount.offset)
                camera_np.set_p(math.degrees(mount.pitch))
                if mount.hide_owner:
                    self.pivots[(mount.group, w, mount.instance[a])].get_child(0).hide(BitMask32.bit(a))
            if tiled:
                row, col = divmod(v, self.layout.columns)
                rows, cols = self.layout.rows, self.layout.columns
                region = self.buffers[0].make_display_region(col / cols, (col + 1) / cols, 1 - (row + 1) / rows,
                                                             1 - row / rows)
            else:
                region = self.buffers[v].make_display_region()
            region.set_camera(camera_np)
            self.cameras.append(camera_np)
            self.lenses.append(lens)
        self.set_cameras(fov_y=scene.fov_y, near=scene.near, far=scene.far)

    @staticmethod
    def _geometry(mesh):
        from panda3d.core import NodePath

        return NodePath(to_panda_geom(mesh)) if isinstance(mesh, MeshData) else mesh

    def update(self, group, *, position=None, rotation=None, scale=None, color=None, active=None, owner=None):
        """Same arguments as BatchRenderer.update; applied with one Python call per node."""
        from panda3d.core import BitMask32

        W = self.scene.num_worlds
        capacity = self.scene.groups[group].capacity
        if rotation is not None:
            rotation = normalize_quat(torch.as_tensor(rotation, dtype=torch.float64))
        for w in range(W):
            for c in range(capacity):
                pivot = self.pivots[(group, w, c)]
                geometry = pivot.get_child(0)
                if position is not None:
                    pivot.set_pos(*map(float, position[w, c]))
                if rotation is not None:
                    pivot.set_quat(tuple(map(float, rotation[w, c])))
                if scale is not None:
                    geometry.set_scale(*map(float, scale[w, c]))
                if color is not None:
                    values = [float(x) for x in color[w, c]]
                    geometry.set_color(*(values + [1.0] * (4 - len(values))))
                if active is not None:
                    pivot.show() if bool(active[w, c]) else pivot.hide()
                if owner is not None and int(owner[w, c]) >= 0:
                    geometry.hide(BitMask32.bit(int(owner[w, c])))

    def set_cameras(self, *, position=None, rotation=None, look_at=None, fov_y=None, near=None, far=None):
        W, A = self.scene.num_worlds, self.scene.agents_per_world
        if look_at is not None:
            rotation = look_at_quat(torch.as_tensor(position, dtype=torch.float64),
                                    torch.as_tensor(look_at, dtype=torch.float64))
        height, width = self.scene.resolution
        for v, (camera, lens) in enumerate(zip(self.cameras, self.lenses, strict=True)):
            w, a = divmod(v, A)
            if position is not None:
                camera.set_pos(*map(float, position[w, a]))
            if rotation is not None:
                camera.set_quat(tuple(map(float, rotation[w, a])))
            if fov_y is not None:
                vertical = float(torch.as_tensor(fov_y, dtype=torch.float64).expand(W, A)[w, a])
                horizontal = 2 * math.atan(math.tan(vertical / 2) * width / height)
                lens.set_fov(math.degrees(horizontal), math.degrees(vertical))
            if near is not None or far is not None:
                n = near if near is not None else lens.get_near()
                f = far if far is not None else lens.get_far()
                n, f = (float(torch.as_tensor(x, dtype=torch.float64).expand(W, A)[w, a]) for x in (n, f))
                lens.set_near_far(n, f)

    def render(self) -> Frame:
        engine = self._context.engine
        with self._context.current():  # only this renderer's buffers are active while it draws
            for buffer in self.buffers:
                buffer.set_active(True)
            try:
                engine.render_frame()
            finally:
                for buffer in self.buffers:
                    buffer.set_active(False)
        height, width = self.scene.resolution
        layout = self.layout
        images = [np.frombuffer(memoryview(t.get_ram_image()), np.uint8) for t in self.textures]
        image = images[0] if self.tiled else np.concatenate(images)
        # Bottom-up BGR rows -> top-down tiles in RGB.
        if self.tiled:
            grid = image.reshape(layout.rows * height, layout.columns * width, 3)[::-1, :, ::-1]
            tiles = grid.reshape(layout.rows, height, layout.columns, width, 3).transpose(0, 2, 1, 3, 4)
            tiles = tiles.reshape(-1, height, width, 3)[: self.scene.num_views]
        else:
            tiles = image.reshape(-1, height, width, 3)[:, ::-1, :, ::-1]
        rgb = torch.from_numpy(np.ascontiguousarray(tiles))
        return Frame(rgb.view(self.scene.num_worlds, self.scene.agents_per_world, height, width, 3))

    def close(self):
        with self._context.current():
            for buffer in self.buffers:
                self._context.engine.remove_window(buffer)
            self._context.drop_render_texture_events()
        self.buffers, self.textures = [], []
        for root in self.world_roots:
            root.remove_node()
        self.world_roots = []
