"""The performance floor: the same batched scene drawn with raw OpenGL, no engine.

`RawGLRenderer` renders a `marl_render.Scene` through moderngl on a standalone EGL
context (Mesa llvmpipe on CPU machines). It does exactly the work the batch renderer
does and nothing else, so its throughput is the floor the Panda3D path is measured
against (`python -m marl_render.bench floor`, via `measure_floor`):

- the same pure-torch steps, by calling BatchRenderer's own code: camera poses
  (free or mounted), re-centring, view-projection packing, per-group instance
  packing and frustum culling into sorted (view, instance) pair lists;
- the same tile layout (`tiling.plan_layout`), the same per-view vertical flip and
  clip-distance tiles, the same fragment shader text (shaders/batch.frag, writing RGB
  instead of Panda3D's BGR because glReadPixels here reads RGB);
- per frame: upload the packed bytes (glBufferSubData into shader storage buffers),
  clear, one instanced draw per mesh group and pass, one glReadPixels into a
  preallocated numpy array, one strided copy of the tiles into the batch tensor
  (BatchRenderer._read_pass). No Python per world, agent or object.

The BatchRenderer methods it reuses write through `texture.modify_ram_image()` and read
`texture.get_ram_image()`; `_HostBuffer` provides those two calls over plain numpy
memory, so that code runs unchanged here. Only the `lighting` and `fog` effects and
MeshData meshes (procedural shapes) are supported; anything else raises ValueError.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
import torch

from . import backend, shaders
from .culling import frustum_planes, mesh_radius
from .meshes import MeshData
from .renderer import BatchRenderer, Frame, _DrawGroup
from .scene import Scene
from .tiling import plan_layout
from .validation import describe

SUPPORTED_EFFECTS = frozenset({"lighting", "fog"})
GL_CLIP_DISTANCE0 = 0x3000

# Compact GLSL 430 twin of shaders/batch.vert: the same maths, with instances, views and
# pairs read from shader storage buffers (moderngl has no buffer textures). Layouts are
# the ones BatchRenderer packs (shaders.INSTANCE_TEXELS / VIEW_TEXELS vec4 rows).
VERTEX_SHADER = """
layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_normal;
layout(std430, binding = 0) readonly buffer Views { vec4 views[]; };
layout(std430, binding = 1) readonly buffer Instances { vec4 instances[]; };
layout(std430, binding = 2) readonly buffer Pairs { int pairs[]; };
uniform int pair_offset;
uniform int capacity;
uniform int agents;
uniform int view_offset;
uniform ivec2 grid;
out vec4 v_color;
#ifdef EFFECT_LIGHTING
out vec3 v_normal;
#endif
#ifdef EFFECT_FOG
out float v_depth;
#endif

vec3 rotate(vec4 q, vec3 v) {
    vec3 t = 2.0 * cross(q.yzw, v);
    return v + q.x * t + cross(q.yzw, t);
}

void main() {
    int pair = pairs[pair_offset + gl_InstanceID];
    int view = pair / capacity;
    int instance = pair - view * capacity;
#ifdef STATIC_GROUP
    int row = instance * INSTANCE_TEXELS;
#else
    int row = ((view / agents) * capacity + instance) * INSTANCE_TEXELS;
#endif
    vec4 rotation = instances[row + 1];
    vec4 scale = instances[row + 2];
    v_color = instances[row + 3];
    int vrow = view * VIEW_TEXELS;
    mat4 view_projection = mat4(views[vrow], views[vrow + 1], views[vrow + 2], views[vrow + 3]);
#ifdef STATIC_GROUP
    vec3 origin = (instances[row].xyz - views[vrow + 4].xyz) + (instances[row + 4].xyz - views[vrow + 5].xyz);
#else
    vec3 origin = instances[row].xyz;
#endif
    vec4 clip = view_projection * vec4(origin + rotate(rotation, in_position * scale.xyz), 1.0);
    gl_ClipDistance[0] = clip.w + clip.x;
    gl_ClipDistance[1] = clip.w - clip.x;
    gl_ClipDistance[2] = clip.w + clip.y;
    gl_ClipDistance[3] = clip.w - clip.y;
    int tile = view - view_offset;
    vec2 shift = vec2(2 * (tile % grid.x) + 1 - grid.x, 2 * (tile / grid.x) + 1 - grid.y);
    gl_Position = vec4((vec2(clip.x, -clip.y) + clip.w * shift) / vec2(grid), clip.z, clip.w);
#ifdef EFFECT_LIGHTING
    v_normal = rotate(rotation, in_normal / max(abs(scale.xyz), vec3(1e-20)) * sign(scale.xyz));
#endif
#ifdef EFFECT_FOG
    v_depth = clip.w;
#endif
}
"""


def _require_moderngl():
    try:
        import moderngl
    except ImportError as exc:  # optional dependency
        raise ImportError("the raw OpenGL floor needs moderngl: pip install 'marl-render[bench]'") from exc
    return moderngl


def _glsl(stage_source: str, defines: tuple[str, ...]) -> str:
    return "#version 430\n" + "".join(f"#define {d}\n" for d in defines) + stage_source


def _fragment_source(defines: tuple[str, ...]) -> str:
    """shaders/batch.frag with its output in RGB order (it writes BGR for Panda3D's BGRA readback)."""
    text = shaders.source("batch.frag")
    swizzle = "clamp(color, 0.0, 1.0).bgr"
    if text.count(swizzle) != 1:
        raise RuntimeError(f"shaders/batch.frag no longer contains exactly one {swizzle!r}; update "
                           "marl_render/rawgl.py to its new output convention")
    return _glsl(text.replace(swizzle, "clamp(color, 0.0, 1.0).rgb"), defines)


class _HostBuffer:
    """Numpy memory that answers the two Panda3D Texture calls BatchRenderer's packers use."""

    def __init__(self, nbytes: int):
        self.array = np.zeros(max(int(nbytes), 16), dtype=np.uint8)

    def modify_ram_image(self):
        return self.array

    get_ram_image = modify_ram_image


@dataclass
class _GLGroup:
    vao: object
    program: object
    instances: object  # moderngl.Buffer, shader storage binding 1
    pairs: object  # moderngl.Buffer, shader storage binding 2


class RawGLRenderer(BatchRenderer):
    """BatchRenderer's inputs and outputs (update, set_cameras, render -> Frame.rgb), drawn by raw GL.

    Subclasses BatchRenderer only to reuse its validation and pure-torch stages; no
    Panda3D object is created or imported. Outputs are owned by the caller.
    """

    def __init__(self, scene: Scene, *, channels_first: bool = False, max_framebuffer_size: int | None = None,
                 egl_device_index: int | None = None):
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a marl_render.Scene, got {describe(scene)}")
        unsupported = sorted(set(scene.effects) - SUPPORTED_EFFECTS - {"texture"})
        textured = [g.name for g in [*scene.static.values(), *scene.groups.values()] if g.texture is not None]
        if unsupported or ("texture" in scene.effects and textured):
            raise ValueError(f"RawGLRenderer supports the effects {sorted(SUPPORTED_EFFECTS)} only; scene declares "
                             f"{unsupported or ['texture']}{' for groups ' + str(textured) if not unsupported else ''}")
        for group in [*scene.static.values(), *scene.groups.values()]:
            if not isinstance(group.mesh, MeshData):
                raise ValueError(f"RawGLRenderer draws MeshData meshes only; group {group.name!r} has "
                                 f"{describe(group.mesh)} (a Panda3D model): convert it to MeshData first")
        moderngl = _require_moderngl()
        kwargs = {} if egl_device_index is None else {"device_index": int(egl_device_index)}
        try:
            self.ctx = moderngl.create_context(standalone=True, backend="egl", require=430, **kwargs)
        except Exception as exc:
            raise backend.GLUnavailableError(f"moderngl could not create an OpenGL 4.3 EGL context: {exc}. "
                                             + backend.INSTALL_HINT) from exc
        self._pid = os.getpid()
        self.scene, self.channels_first, self._closed, self.buffer = scene, bool(channels_first), False, None
        self.effects = frozenset(scene.effects) & SUPPORTED_EFFECTS
        info = self.ctx.info
        gl_max = min(int(info["GL_MAX_RENDERBUFFER_SIZE"]), *(int(v) for v in info["GL_MAX_VIEWPORT_DIMS"]))
        max_size = gl_max if max_framebuffer_size is None else max_framebuffer_size
        if not isinstance(max_size, int) or not 1 <= max_size <= gl_max:
            raise ValueError(f"max_framebuffer_size must be an int in [1, {gl_max}], got {max_framebuffer_size!r}")
        self.layout = plan_layout(scene.num_views, *scene.resolution, max_size)
        self._color_channels = 3
        self.stage_seconds = {"prepare": 0.0, "upload": 0.0, "draw": 0.0, "readback": 0.0, "copy": 0.0}
        self._init_state()
        with self.ctx:
            self._build_target()
            self._build_groups()

    # ------------------------------------------------------------------ GL objects
    def _build_target(self):
        ctx, (width, height) = self.ctx, self.layout.framebuffer_size
        self.buffer = ctx.framebuffer(color_attachments=[ctx.renderbuffer((width, height), components=3)],
                                      depth_attachment=ctx.depth_renderbuffer((width, height)))
        self.color_texture = _HostBuffer(width * height * 3)  # glReadPixels lands here
        self.views_texture = _HostBuffer(self.scene.num_views * shaders.VIEW_TEXELS * 16)
        self._views_gl = ctx.buffer(reserve=self.views_texture.array.nbytes, dynamic=True)
        self._programs = {}
        for static in (True, False):
            defines = shaders.defines_for(self.effects, static=static, textured=False)
            program = ctx.program(vertex_shader=_glsl(VERTEX_SHADER, defines), fragment_shader=_fragment_source(defines))
            lighting, fog = self.scene.lighting, self.scene.fog
            direction = np.asarray(lighting.direction, dtype=float)
            uniforms = {"agents": self.scene.agents_per_world, "grid": (self.layout.columns, self.layout.rows),
                        "light_direction": tuple(direction / np.linalg.norm(direction)),
                        "light_color": tuple(lighting.color), "ambient_color": tuple(lighting.ambient),
                        "fog_color": tuple(fog.color), "fog_density": float(fog.density)}
            for name, value in uniforms.items():
                if name in program:  # unused uniforms are compiled out
                    program[name].value = value
            self._programs[static] = program

    def _build_groups(self):
        ctx = self.ctx
        self._groups: dict[str, _DrawGroup] = {}
        self._gl: dict[str, _GLGroup] = {}
        groups = [(g, True) for g in self.scene.static.values()] + [(g, False) for g in self.scene.groups.values()]
        for group, static in groups:
            mesh, program = group.mesh, self._programs[static]
            vertices = ctx.buffer(np.concatenate((mesh.positions, mesh.normals), axis=1).astype(np.float32))
            indices = ctx.buffer(mesh.triangles.astype(np.uint32))
            layout = (vertices, "3f 3f", "in_position", "in_normal") if "in_normal" in program else \
                (vertices, "3f 12x", "in_position")
            vao = ctx.vertex_array(program, [layout], index_buffer=indices, index_element_size=4)
            count = group.count if static else group.capacity
            rows = count if static else self.scene.num_worlds * count
            texels = shaders.STATIC_INSTANCE_TEXELS if static else shaders.INSTANCE_TEXELS
            draw = _DrawGroup(vao, count, static, _HostBuffer(rows * texels * 16),
                              _HostBuffer(self.scene.num_views * count * 4), mesh_radius(mesh))
            self._groups[group.name] = draw
            self._gl[group.name] = _GLGroup(vao, program, ctx.buffer(reserve=draw.instances.array.nbytes, dynamic=True),
                                            ctx.buffer(reserve=draw.pairs.array.nbytes, dynamic=True))
            if static:
                self._pack_static(group, draw)
                self._gl[group.name].instances.write(draw.instances.array)

    # ------------------------------------------------------------------ rendering
    def render(self) -> Frame:
        """Draw all views; returns tensors the caller owns (rgb only)."""
        self._check_open()
        if self._pid != os.getpid():
            raise backend.ForkedContextError("this RawGLRenderer was created before fork(); GL contexts do not "
                                             "survive fork(): create it in the child process")
        start = time.perf_counter()
        # The pure-torch stages of BatchRenderer.render, called one by one.
        position, rotation = self._camera_poses()
        self._recentre(position)
        view_projection = self._pack_views(position, rotation)
        dirty = [name for name in self._dirty if name in self.scene.groups]
        for name in dirty:
            self._pack_group(name)
        self._dirty.clear()
        self._cull(frustum_planes(view_projection))
        self.stage_seconds["prepare"] += time.perf_counter() - start
        with self.ctx:
            self._upload(dirty)
            return self._draw_and_read()

    def _upload(self, dirty):
        start = time.perf_counter()
        self._views_gl.write(self.views_texture.array)
        for name in dirty:
            self._gl[name].instances.write(self._groups[name].instances.array)
        for name, draw in self._groups.items():
            used = sum(count for _, count in draw.pass_ranges) * 4
            if used:
                self._gl[name].pairs.write(memoryview(draw.pairs.array)[:used])
        self.stage_seconds["upload"] += time.perf_counter() - start

    def _draw_and_read(self) -> Frame:
        s, ctx, seconds = self.scene, self.ctx, self.stage_seconds
        W, A = s.num_worlds, s.agents_per_world
        height, width = s.resolution
        rgb_shape = (W * A, 3, height, width) if self.channels_first else (W * A, height, width, 3)
        rgb = torch.empty(rgb_shape, dtype=torch.uint8)
        self.buffer.use()
        ctx.enable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        ctx.depth_func, ctx.front_face, ctx.cull_face = "<", "cw", "back"  # the per-view flip reverses winding
        for plane in range(4):
            ctx.enable_direct(GL_CLIP_DISTANCE0 + plane)
        self._views_gl.bind_to_storage_buffer(0)
        red, green, blue = s.background[:3]
        for index in range(self.layout.num_passes):
            views = self.layout.pass_views(index)
            start = time.perf_counter()
            self.buffer.clear(red, green, blue, 1.0, depth=1.0)
            for name, draw in self._groups.items():
                first, count = draw.pass_ranges[index]
                if count:
                    gl = self._gl[name]
                    gl.program["pair_offset"].value = first
                    gl.program["capacity"].value = draw.count
                    gl.program["view_offset"].value = views.start
                    gl.instances.bind_to_storage_buffer(1)
                    gl.pairs.bind_to_storage_buffer(2)
                    gl.vao.render(instances=count)
            middle = time.perf_counter()
            # llvmpipe rasterises lazily: most drawing time shows up in this readback.
            self.buffer.read_into(self.color_texture.array, components=3, alignment=1)
            end = time.perf_counter()
            self._read_pass(views, rgb, None, None)  # the tile -> batch copy of BatchRenderer
            seconds["draw"] += middle - start
            seconds["readback"] += end - middle
            seconds["copy"] += time.perf_counter() - end
        return Frame(rgb.view((W, A) + rgb_shape[1:]))

    def gl_info(self) -> dict:
        info = self.ctx.info
        return {"vendor": info["GL_VENDOR"], "renderer": info["GL_RENDERER"], "gl_version": info["GL_VERSION"]}

    def close(self) -> None:
        """Free the GL context and everything in it; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        with self.ctx:
            for gl in self._gl.values():
                for resource in (gl.vao, gl.instances, gl.pairs):
                    resource.release()
            for program in self._programs.values():
                program.release()
            self._views_gl.release()
            self.buffer.release()
        self.ctx.release()
        self._groups.clear()
        self._gl.clear()
        self.buffer = None


# ---------------------------------------------------------------------- measurement
def _time_methods(renderer, names, totals: dict):
    """Wrap bound methods on one instance to add their wall time to totals[name]."""
    for name in names:
        method = getattr(renderer, name)

        def timed(*args, _method=method, _name=name, **kwargs):
            start = time.perf_counter()
            try:
                return _method(*args, **kwargs)
            finally:
                totals[_name] = totals.get(_name, 0.0) + time.perf_counter() - start

        setattr(renderer, name, timed)


def measure_floor(scene_builder, steps: int = 20, *, warmup: int = 3, stages: bool = True,
                  panda3d: bool = True) -> dict:
    """Time `steps` frames of RawGLRenderer and BatchRenderer on the same scene, in this process.

    scene_builder() returns a Scene, or (Scene, pose) where pose(renderer, step) sets the
    poses of step `step` through renderer.update / set_cameras (deterministic in step, so
    both renderers draw the same frames); pose time is not counted. Returns views/s and
    ms/frame of both, ratio = raw views/s / Panda3D views/s (>= 1: how far the engine path
    is above the floor), and per-stage ms/frame when `stages` (for BatchRenderer the
    stages are its methods; `_read_pass` runs inside `_draw_and_read`, whose remainder is
    Panda3D's render_frame: cull traversal, draw, glReadPixels into its RAM image).
    """
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive int, got {steps!r}")
    if not isinstance(warmup, int) or warmup < 0:
        raise ValueError(f"warmup must be a non-negative int, got {warmup!r}")
    built = scene_builder()
    scene, pose = built if isinstance(built, tuple) else (built, None)
    if not isinstance(scene, Scene):
        raise TypeError(f"scene_builder must return a Scene or (Scene, pose), got {describe(scene)}")
    views = scene.num_views
    result = {"scene": {"num_worlds": scene.num_worlds, "agents_per_world": scene.agents_per_world,
                        "resolution": list(scene.resolution), "effects": list(scene.effects),
                        "static": {k: g.count for k, g in scene.static.items()},
                        "groups": {k: g.capacity for k, g in scene.groups.items()}},
              "steps": steps, "warmup": warmup}
    runners = [("raw", RawGLRenderer)] + ([("panda3d", BatchRenderer)] if panda3d else [])
    stage_names = ["_camera_poses", "_pack_views", "_pack_group", "_cull", "_draw_and_read", "_read_pass"]
    for key, cls in runners:
        renderer = cls(scene)
        try:
            totals = {}
            if stages:
                _time_methods(renderer, stage_names, totals)
            if isinstance(renderer, RawGLRenderer):
                result["gl"] = renderer.gl_info()
            for step in range(warmup):
                if pose is not None:
                    pose(renderer, step)
                renderer.render()
            totals.clear()
            if isinstance(renderer, RawGLRenderer):
                renderer.stage_seconds = dict.fromkeys(renderer.stage_seconds, 0.0)
            elapsed = 0.0
            for step in range(warmup, warmup + steps):
                if pose is not None:
                    pose(renderer, step)
                start = time.perf_counter()
                renderer.render()
                elapsed += time.perf_counter() - start
            entry = {"views_per_s": views * steps / elapsed, "ms_per_frame": 1e3 * elapsed / steps}
            if stages:
                if isinstance(renderer, RawGLRenderer):
                    totals.update({f"gl.{k}": v for k, v in renderer.stage_seconds.items()})
                entry["stages_ms"] = {k: round(1e3 * v / steps, 3) for k, v in totals.items()}
            result[key] = entry
        finally:
            renderer.close()
    if panda3d:
        result["ratio"] = result["raw"]["views_per_s"] / result["panda3d"]["views_per_s"]
    return result


# ---------------------------------------------------------------------- benchmark scenes
def boxes_scene(num_worlds: int = 256, agents_per_world: int = 4, resolution=64, boxes: int = 10, seed: int = 0):
    """Floor + `boxes` moving boxes per world, agents on a circle looking at the centre."""
    scene = Scene(num_worlds, agents_per_world, resolution=resolution)
    scene.add_static("floor", "plane", [0.0, 0.0, 0.0], scale=[40.0, 40.0, 1.0], color=[0.35, 0.55, 0.3])
    scene.add_group("boxes", "box", boxes)
    generator = torch.Generator().manual_seed(seed)
    W, A, C = num_worlds, agents_per_world, boxes
    home = (torch.rand(W, C, 3, generator=generator) * 2 - 1) * torch.tensor([4.0, 4.0, 0.0])
    size = 0.4 + 0.8 * torch.rand(W, C, 1, generator=generator)
    home[..., 2] = size[..., 0] / 2
    color = torch.rand(W, C, 3, generator=generator)
    angle = torch.arange(A, dtype=torch.float64) * (2 * np.pi / A)
    eye = torch.stack((7 * torch.cos(angle), 7 * torch.sin(angle), torch.full_like(angle, 2.0)), -1).expand(W, A, 3)

    def pose(renderer, step):
        t = 0.1 * step
        position = home.clone()
        position[..., 0] += 0.5 * torch.sin(t + home[..., 1])
        yaw = (t + home[..., 0]) / 2
        rotation = torch.stack((torch.cos(yaw), torch.zeros_like(yaw), torch.zeros_like(yaw), torch.sin(yaw)), -1)
        renderer.update("boxes", position=position, rotation=rotation, scale=size.expand(W, C, 3), color=color,
                        active=torch.ones(W, C, dtype=torch.bool))
        renderer.set_cameras(position=eye, look_at=torch.zeros(W, A, 3))

    return scene, pose


def cartpole_scene(num_worlds: int = 1024, resolution=64):
    """One agent per world watching a 3-box cart-pole (rail, cart, pole); cart and pole move each step."""
    scene = Scene(num_worlds, 1, resolution=resolution)
    scene.add_group("parts", "box", 3)
    W = num_worlds
    phase = torch.linspace(0, 2 * np.pi, W, dtype=torch.float64)
    scale = torch.tensor([[4.0, 0.05, 0.05], [0.4, 0.3, 0.2], [0.05, 0.05, 1.0]]).expand(W, 3, 3)
    color = torch.tensor([[0.3, 0.3, 0.3], [0.2, 0.4, 0.9], [0.9, 0.6, 0.2]]).expand(W, 3, 3)

    def pose(renderer, step):
        x = torch.sin(0.05 * step + phase)
        theta = 0.3 * torch.sin(0.11 * step + 2 * phase)
        position = torch.zeros(W, 3, 3, dtype=torch.float64)
        position[:, 1, 0] = x
        position[:, 2, 0] = x + 0.5 * torch.sin(theta)
        position[:, 2, 2] = 0.1 + 0.5 * torch.cos(theta)
        rotation = torch.zeros(W, 3, 4)
        rotation[..., 0] = 1.0
        rotation[:, 2, 0] = torch.cos(-theta / 2)
        rotation[:, 2, 2] = torch.sin(-theta / 2)  # about +Y: tilts the pole sideways
        renderer.update("parts", position=position, rotation=rotation, scale=scale, color=color,
                        active=torch.ones(W, 3, dtype=torch.bool))
        renderer.set_cameras(position=torch.tensor([0.0, -4.0, 0.6]).expand(W, 1, 3),
                             look_at=torch.tensor([0.0, 0.0, 0.3]).expand(W, 1, 3))

    return scene, pose
