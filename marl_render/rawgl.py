"""The performance floor: the same batched scene drawn with raw OpenGL, no engine.

`RawGLRenderer` renders a `marl_render.Scene` through moderngl on a standalone EGL
context (Mesa llvmpipe on CPU machines). It does exactly the work the batch renderer
does and nothing else, so its throughput is the floor the Panda3D path is measured
against (`python -m marl_render.bench floor`, via `measure_floor`):

- the same pure-torch steps, by calling BatchRenderer's own code: camera poses
  (free or mounted), re-centring, view-projection packing, per-group instance
  packing and frustum culling into sorted (view, instance) pair lists;
- the same tile layout (`tiling.plan_layout`) and the same shaders, shaders/batch.vert
  and batch.frag as they are (per-instance data in buffer textures, per-view tiles
  with clip distances and a vertical flip), except that the fragment shader writes RGB
  where Panda3D's BGRA readback wants BGR;
- per frame: upload the packed bytes (glBufferSubData), clear, one instanced draw per
  mesh group and pass, one glReadPixels into a preallocated numpy array, one strided
  copy of the tiles into the batch tensor (tiling.framebuffer_tiles + copy_tiles).
  No Python per world, agent or object.

The BatchRenderer methods it reuses write their packed data through
`texture.modify_ram_image()`; `_HostBuffer` answers that call with plain numpy memory,
so that code runs unchanged here. moderngl has no buffer textures: the five GL calls
they need go through ctypes (`_BufferTextures`). On llvmpipe, buffer textures beat
shader storage buffers for this vertex shader (about 20% less vertex time measured
with 10 boxes x 1024 views), so the floor uses what BatchRenderer uses.
Only the `lighting` and `fog` effects and MeshData meshes (procedural shapes) are
supported; anything else raises ValueError.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import time
from dataclasses import dataclass

import numpy as np
import torch

from . import backend, shaders
from .culling import mesh_radius
from .meshes import MeshData
from .renderer import BatchRenderer, Frame, _DrawGroup
from .scene import Scene
from .tiling import copy_tiles, framebuffer_tiles, plan_layout
from .validation import describe

SUPPORTED_EFFECTS = frozenset({"lighting", "fog"})
GL_CLIP_DISTANCE0 = 0x3000


def _require_moderngl():
    try:
        import moderngl
    except ImportError as exc:  # optional dependency
        raise ImportError("the raw OpenGL floor needs moderngl: pip install 'marl-render[bench]'") from exc
    return moderngl


def _fragment_source(defines: tuple[str, ...]) -> str:
    """shaders/batch.frag with its output in RGB order (it writes BGR for Panda3D's BGRA readback)."""
    text = shaders.variant_source("frag", defines)
    swizzle = "clamp(color, 0.0, 1.0).bgr"
    if text.count(swizzle) != 1:
        raise RuntimeError(f"shaders/batch.frag no longer contains exactly one {swizzle!r}; update "
                           "marl_render/rawgl.py to its new output convention")
    return text.replace(swizzle, "clamp(color, 0.0, 1.0).rgb")


class _BufferTextures:
    """The raw GL calls for buffer textures (samplerBuffer), which moderngl does not wrap."""

    TEXTURE_BUFFER, TEXTURE0, RGBA32F, R32I = 0x8C2A, 0x84C0, 0x8814, 0x8235

    def __init__(self):
        name = ctypes.util.find_library("OpenGL") or ctypes.util.find_library("GL")
        if name is None:
            raise backend.GLUnavailableError("libOpenGL / libGL not found (needed for buffer textures). "
                                             + backend.INSTALL_HINT)
        gl = ctypes.CDLL(name)
        uint, sint = ctypes.c_uint, ctypes.c_int
        for function, argtypes in (("glGenTextures", [sint, ctypes.POINTER(uint)]), ("glBindTexture", [uint, uint]),
                                   ("glTexBuffer", [uint, uint, uint]), ("glActiveTexture", [uint]),
                                   ("glProgramUniform1i", [uint, sint, sint])):
            getattr(gl, function).argtypes = argtypes
            getattr(gl, function).restype = None
        self.gl = gl

    def create(self, buffer, integer: bool = False) -> int:
        """A texture viewing a moderngl Buffer as RGBA32F (or R32I) texels."""
        name = ctypes.c_uint()
        self.gl.glGenTextures(1, ctypes.byref(name))
        self.gl.glBindTexture(self.TEXTURE_BUFFER, name)
        self.gl.glTexBuffer(self.TEXTURE_BUFFER, self.R32I if integer else self.RGBA32F, buffer.glo)
        return name.value

    def bind(self, unit: int, texture: int):
        self.gl.glActiveTexture(self.TEXTURE0 + unit)
        self.gl.glBindTexture(self.TEXTURE_BUFFER, texture)

    def set_sampler(self, program, name: str, unit: int):
        self.gl.glProgramUniform1i(program.glo, program[name].location, unit)


class _HostBuffer:
    """Numpy memory answering the one Panda3D Texture call BatchRenderer's packers make."""

    def __init__(self, nbytes: int):
        self.array = np.zeros(max(int(nbytes), 16), dtype=np.uint8)

    def modify_ram_image(self):
        return self.array


@dataclass
class _GLGroup:
    vao: object
    program: object
    instances: object  # moderngl.Buffer
    pairs: object  # moderngl.Buffer
    textures: tuple  # buffer textures over (instances, pairs), bound to units 1 and 2


class RawGLRenderer(BatchRenderer):
    """BatchRenderer's inputs and outputs (update, set_cameras, render -> Frame.rgb), drawn by raw GL.

    Subclasses BatchRenderer only to reuse its validation and pure-torch stages; no
    Panda3D object is created or imported. Outputs are owned by the caller.
    `last_timings` holds the seconds per stage of the last render(), with BatchRenderer's
    keys (pack, cull, gl, copy) plus the parts of gl (upload, draw, readback).
    """

    def __init__(self, scene: Scene, *, channels_first: bool = False, max_framebuffer_size: int | None = None,
                 egl_device_index: int | None = None):
        self._closed, self.ctx = True, None  # until the context exists: close() has nothing to free
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a marl_render.Scene, got {describe(scene)}")
        unsupported = sorted(set(scene.effects) - SUPPORTED_EFFECTS - {"texture"})
        textured = [g.name for g in [*scene.static.values(), *scene.groups.values()] if g.texture is not None]
        if unsupported or ("texture" in scene.effects and textured):
            what = unsupported or [f"texture (groups {textured})"]
            raise ValueError(f"RawGLRenderer supports the effects {sorted(SUPPORTED_EFFECTS)} only; "
                             f"scene declares {what}")
        for group in [*scene.static.values(), *scene.groups.values()]:
            if not isinstance(group.mesh, MeshData):
                raise ValueError(f"RawGLRenderer draws MeshData meshes only; group {group.name!r} has "
                                 f"{describe(group.mesh)} (a Panda3D model): convert it to MeshData first")
        moderngl = _require_moderngl()
        kwargs = {} if egl_device_index is None else {"device_index": int(egl_device_index)}
        try:
            self.ctx = moderngl.create_context(standalone=True, backend="egl", require=410, **kwargs)
        except Exception as exc:
            raise backend.GLUnavailableError(f"moderngl could not create an OpenGL 4.1 EGL context: {exc}. "
                                             + backend.INSTALL_HINT) from exc
        self._closed, self._pid = False, os.getpid()
        self.scene, self.channels_first = scene, bool(channels_first)
        self.effects = frozenset(scene.effects) & SUPPORTED_EFFECTS
        self.last_timings: dict[str, float] = {}
        try:
            info = self.ctx.info
            gl_max = min(int(info["GL_MAX_RENDERBUFFER_SIZE"]), *(int(v) for v in info["GL_MAX_VIEWPORT_DIMS"]))
            max_size = gl_max if max_framebuffer_size is None else max_framebuffer_size
            if not isinstance(max_size, int) or not 1 <= max_size <= gl_max:
                raise ValueError(f"max_framebuffer_size must be an int in [1, {gl_max}], got {max_framebuffer_size!r}")
            self.layout = plan_layout(scene.num_views, *scene.resolution, max_size)
            self._init_state()
            with self.ctx:
                self._textures = _BufferTextures()
                self._build_target()
                self._build_groups()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ GL objects
    def _build_target(self):
        ctx, (width, height) = self.ctx, self.layout.framebuffer_size
        # RGB8 colour read back as RGB: 3 bytes a pixel make the tile copy whole rows.
        self.buffer = ctx.framebuffer(color_attachments=[ctx.renderbuffer((width, height), components=3)],
                                      depth_attachment=ctx.depth_renderbuffer((width, height)))
        self._image = np.empty(width * height * 3, dtype=np.uint8)  # glReadPixels lands here, every pass
        self.views_texture = _HostBuffer(self.scene.num_views * shaders.VIEW_TEXELS * 16)
        self._views_gl = ctx.buffer(reserve=self.views_texture.array.nbytes, dynamic=True)
        self._views_texture_gl = self._textures.create(self._views_gl)
        lighting, fog = self.scene.lighting, self.scene.fog
        direction = np.asarray(lighting.direction, dtype=float)
        uniforms = {"agents": self.scene.agents_per_world, "grid": (self.layout.columns, self.layout.rows),
                    "light_direction": tuple(direction / np.linalg.norm(direction)),
                    "light_color": tuple(lighting.color), "ambient_color": tuple(lighting.ambient),
                    "fog_color": tuple(fog.color), "fog_density": float(fog.density)}
        self._programs = {}
        for static in (True, False):
            defines = shaders.defines_for(self.effects, static=static, textured=False)
            program = ctx.program(vertex_shader=shaders.variant_source("vert", defines),
                                  fragment_shader=_fragment_source(defines))
            for name, value in uniforms.items():
                if name in program:  # unused uniforms are compiled out
                    program[name].value = value
            for unit, name in enumerate(("views", "instances", "pairs")):
                self._textures.set_sampler(program, name, unit)
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
            attributes = (vertices, "3f 3f", "p3d_Vertex", "p3d_Normal") if "p3d_Normal" in program else \
                (vertices, "3f 12x", "p3d_Vertex")
            vao = ctx.vertex_array(program, [attributes], index_buffer=indices, index_element_size=4)
            count = group.count if static else group.capacity
            rows = count if static else self.scene.num_worlds * count
            texels = shaders.STATIC_INSTANCE_TEXELS if static else shaders.INSTANCE_TEXELS
            draw = _DrawGroup(vao, count, static, _HostBuffer(rows * texels * 16),
                              _HostBuffer(self.scene.num_views * count * 4), mesh_radius(mesh))
            self._groups[group.name] = draw
            instances = ctx.buffer(reserve=draw.instances.array.nbytes, dynamic=True)
            pairs = ctx.buffer(reserve=draw.pairs.array.nbytes, dynamic=True)
            self._gl[group.name] = _GLGroup(vao, program, instances, pairs, (
                self._textures.create(instances), self._textures.create(pairs, integer=True)))
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
        dirty = self._prepare()  # the same torch stages as BatchRenderer.render
        self.last_timings.update(dict.fromkeys(("gl", "upload", "draw", "readback", "copy"), 0.0))
        with self.ctx:  # another EGL context (Panda3D's) may be current
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
        self.last_timings["upload"] = time.perf_counter() - start

    def _draw_and_read(self) -> Frame:
        s, ctx, timings = self.scene, self.ctx, self.last_timings
        W, A = s.num_worlds, s.agents_per_world
        height, width = s.resolution
        rgb_shape = (W * A, 3, height, width) if self.channels_first else (W * A, height, width, 3)
        rgb = torch.empty(rgb_shape, dtype=torch.uint8)
        self.buffer.use()
        ctx.enable_only(ctx.DEPTH_TEST | ctx.CULL_FACE)
        ctx.depth_func, ctx.front_face, ctx.cull_face = "<", "cw", "back"  # the per-view flip reverses winding
        for plane in range(4):
            ctx.enable_direct(GL_CLIP_DISTANCE0 + plane)
        self._textures.bind(0, self._views_texture_gl)
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
                    self._textures.bind(1, gl.textures[0])
                    self._textures.bind(2, gl.textures[1])
                    gl.vao.render(instances=count)
            drawn = time.perf_counter()
            # llvmpipe rasterises lazily: most of the drawing time is spent inside this read.
            self.buffer.read_into(self._image, components=3, alignment=1)
            read = time.perf_counter()
            tiles = framebuffer_tiles(self._image, np.uint8, 3, self.layout)
            copy_tiles(tiles.permute(0, 1, 4, 2, 3) if self.channels_first else tiles, rgb[views.start:views.stop])
            timings["draw"] += drawn - start
            timings["readback"] += read - drawn
            timings["copy"] += time.perf_counter() - read
        timings["gl"] = timings["upload"] + timings["draw"] + timings["readback"]
        return Frame(rgb.view((W, A) + rgb_shape[1:]))

    def gl_info(self) -> dict:
        info = self.ctx.info
        return {"vendor": info["GL_VENDOR"], "renderer": info["GL_RENDERER"], "gl_version": info["GL_VERSION"]}

    def close(self) -> None:
        """Free the GL context and with it every GL object of this renderer; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self.ctx is not None:
            self.ctx.release()
        self._groups, self._gl, self.buffer = {}, {}, None


# ---------------------------------------------------------------------- measurement
def measure_floor(scene_builder, steps: int = 20, *, warmup: int = 3, repeats: int = 3, panda3d: bool = True,
                  torch_threads: int | None = None) -> dict:
    """Time RawGLRenderer against BatchRenderer on the same scene, in this process.

    scene_builder() returns a Scene, or (Scene, pose) where pose(renderer, step) sets the
    poses of step `step` through renderer.update / set_cameras (deterministic in step, so
    both renderers draw the same frames); pose time is not counted, render() is. Both
    renderers are built first, then run `repeats` alternating blocks of `warmup` + `steps`
    frames, so a load that comes and goes on a shared machine hits both alike.
    Returns, per renderer ("raw", "panda3d"): views/s and ms/frame of the median frame,
    the best frame, the median CPU time of the process per frame (all threads: the
    driver's rasteriser threads too; less sensitive to other processes than wall time)
    and the median ms of each stage of `last_timings` (pack, cull:
    the same torch code in both; gl: Panda3D's render_frame, or raw upload + draw +
    readback; copy: tiles -> batch). ratio = raw views/s / Panda3D views/s, i.e. how many
    times faster the no-engine floor is. torch_threads: torch.set_num_threads for the
    measurement, restored afterwards (None: leave as is).
    """
    for name, value, low in (("steps", steps, 1), ("warmup", warmup, 0), ("repeats", repeats, 1)):
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    built = scene_builder()
    scene, pose = built if isinstance(built, tuple) else (built, None)
    if not isinstance(scene, Scene):
        raise TypeError(f"scene_builder must return a Scene or (Scene, pose), got {describe(scene)}")
    threads = torch.get_num_threads()
    result = {"scene": {"num_worlds": scene.num_worlds, "agents_per_world": scene.agents_per_world,
                        "num_views": scene.num_views, "resolution": list(scene.resolution),
                        "effects": list(scene.effects), "static": {k: g.count for k, g in scene.static.items()},
                        "groups": {k: g.capacity for k, g in scene.groups.items()}},
              "steps": steps, "warmup": warmup, "repeats": repeats}
    runs = {}
    try:
        if torch_threads is not None:
            torch.set_num_threads(torch_threads)
        result["torch_threads"] = torch.get_num_threads()
        for key, cls in [("raw", RawGLRenderer)] + ([("panda3d", BatchRenderer)] if panda3d else []):
            runs[key] = (cls(scene), [], [])
        result["gl"] = runs["raw"][0].gl_info()
        for _ in range(repeats):
            for renderer, frames, stages in runs.values():
                for step in range(warmup + steps):
                    if pose is not None:
                        pose(renderer, step)
                    start, cpu = time.perf_counter(), time.process_time()
                    renderer.render()
                    if step >= warmup:
                        frames.append((time.perf_counter() - start, time.process_time() - cpu))
                        stages.append(dict(getattr(renderer, "last_timings", {})))
        for key, (renderer, frames, stages) in runs.items():
            wall = [f[0] for f in frames]
            median, best = float(np.median(wall)), min(wall)
            result[key] = {"views_per_s": scene.num_views / median, "ms_per_frame": 1e3 * median,
                           "best_views_per_s": scene.num_views / best, "best_ms_per_frame": 1e3 * best,
                           "cpu_ms_per_frame": 1e3 * float(np.median([f[1] for f in frames])),
                           "stages_ms": {k: round(1e3 * float(np.median([f.get(k, 0.0) for f in stages])), 3)
                                         for k in stages[0]}}
    finally:
        for renderer, *_ in runs.values():
            renderer.close()
        torch.set_num_threads(threads)
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
        rotation[:, 2, 0] = torch.cos(theta / 2)
        rotation[:, 2, 2] = torch.sin(theta / 2)  # about +Y: the pole's top moves to +x
        renderer.update("parts", position=position, rotation=rotation, scale=scale, color=color,
                        active=torch.ones(W, 3, dtype=torch.bool))
        renderer.set_cameras(position=torch.tensor([0.0, -4.0, 0.6]).expand(W, 1, 3),
                             look_at=torch.tensor([0.0, 0.0, 0.3]).expand(W, 1, 3))

    return scene, pose
