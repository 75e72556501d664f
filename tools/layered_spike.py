"""Spike: layered rendering (one view per layer of a 2D array texture, gl_Layer from the
vertex shader) against the renderer's column of tiles, in a minimal moderngl-on-EGL harness.

Both paths share one vertex shader (LAYERED or not) and one fragment shader; the tiled path
uses batch.vert's remap y' = ((2t + 1 - T) w - y) / T with gl_ClipDistance top/bottom, at
most 256 tiles per framebuffer, all framebuffers drawn before any read; the layered path
draws every view into layer `view` of one GL_TEXTURE_2D_ARRAY (colour and depth), flipped
vertically likewise, and reads all layers with one glGetTextureSubImage: [layers, H, W, 3].

    python tools/layered_spike.py identity            # question 1: bit-identity per layer
    python tools/layered_spike.py speed --reps 9      # question 2: time, alternating A/B
"""
from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import math
import platform
import statistics
import time

import moderngl
import numpy as np

GL_TEXTURE_2D_ARRAY = 0x8C1A
GL_TEXTURE_2D = 0x0DE1
GL_RGBA8 = 0x8058
GL_DEPTH_COMPONENT24 = 0x81A6
GL_COLOR_ATTACHMENT0 = 0x8CE0
GL_DEPTH_ATTACHMENT = 0x8D00
GL_RGB = 0x1907
GL_UNSIGNED_BYTE = 0x1401
GL_PACK_ALIGNMENT = 0x0D05
GL_CLIP_DISTANCE0 = 0x3000
GL_FRAMEBUFFER_COMPLETE = 0x8CD5
GL_FRAMEBUFFER = 0x8D40
TILES_PER_FRAMEBUFFER = 256

VERTEX = """
#version 430
#ifdef LAYERED
#extension GL_ARB_shader_viewport_layer_array : require
#endif
layout(location = 0) in vec3 corner;
layout(location = 1) in vec3 normal;
layout(std430, binding = 0) readonly buffer Objects { vec4 objects[]; };  // (xyz, scale), (rgb, pattern)
layout(std430, binding = 1) readonly buffer Views { mat4 view_projection[]; };
uniform int per_view;    // instances of this mesh per view
uniform int first_view;  // first view of this framebuffer
uniform int first_object;  // this mesh's first object slot in a view
uniform int objects_per_view;
uniform int tiles;       // tile rows of this framebuffer (tiled path)
out vec3 surface_normal;
out vec2 surface;
flat out vec4 base_color;

void main() {
    int local_view = gl_InstanceID / per_view;
    int view = first_view + local_view;
    int object = view * objects_per_view + first_object + gl_InstanceID % per_view;
    vec4 place = objects[2 * object];
    base_color = objects[2 * object + 1];
    vec3 world = place.xyz + place.w * corner;
    surface_normal = normal;
    surface = world.xy;
    vec4 clip = view_projection[view] * vec4(world, 1.0);
#ifdef LAYERED
    gl_Layer = local_view;
    gl_Position = vec4(clip.x, -clip.y, clip.z, clip.w);
#else
    gl_ClipDistance[0] = clip.w + clip.y;
    gl_ClipDistance[1] = clip.w - clip.y;
    gl_Position = vec4(clip.x, (float(2 * local_view + 1 - tiles) * clip.w - clip.y) / float(tiles), clip.z, clip.w);
#endif
}
"""

FRAGMENT = """
#version 430
in vec3 surface_normal;
in vec2 surface;
flat in vec4 base_color;
out vec4 color;
void main() {
    vec3 n = normalize(surface_normal);
    float light = 0.35 + 0.65 * max(dot(n, normalize(vec3(0.4, -0.5, 0.8))), 0.0);
    vec3 c = base_color.rgb * light;
    if (base_color.a > 0.5)  // floor: checker of 0.5 m cells from the interpolated position
        c *= 0.6 + 0.4 * mod(floor(surface.x * 2.0) + floor(surface.y * 2.0), 2.0);
    color = vec4(c, 1.0);
}
"""


def gl():
    egl = ctypes.CDLL(ctypes.util.find_library("EGL"))
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    u, i, p = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
    sigs = {
        "glCreateTextures": (None, [u, i, ctypes.POINTER(u)]),
        "glTextureStorage2D": (None, [u, i, u, i, i]),
        "glTextureStorage3D": (None, [u, i, u, i, i, i]),
        "glCreateFramebuffers": (None, [i, ctypes.POINTER(u)]),
        "glNamedFramebufferTexture": (None, [u, u, u, i]),
        "glCheckNamedFramebufferStatus": (u, [u, u]),
        "glGetTextureSubImage": (None, [u, i, i, i, i, i, i, i, u, u, i, p]),
        "glPixelStorei": (None, [u, i]),
        "glEnable": (None, [u]),
        "glGetError": (u, []),
    }
    out = {}
    for name, (res, args) in sigs.items():
        out[name] = ctypes.CFUNCTYPE(res, *args)(egl.eglGetProcAddress(name.encode()))
    return out


def sphere(rings=12, segments=16):
    verts = []
    for r in range(rings + 1):
        t = math.pi * r / rings
        for s in range(segments + 1):
            f = 2 * math.pi * s / segments
            verts.append((math.sin(t) * math.cos(f), math.sin(t) * math.sin(f), math.cos(t)))
    v = np.array(verts, "f4")
    idx = []
    for r in range(rings):
        for s in range(segments):
            a, b = r * (segments + 1) + s, (r + 1) * (segments + 1) + s
            idx += [a, b, a + 1, a + 1, b, b + 1]
    return np.concatenate([v, v], 1), np.array(idx, "i4")


def box():
    verts, idx = [], []
    for axis in range(3):
        for sign in (-1, 1):
            n = np.zeros(3)
            n[axis] = sign
            u, w = np.roll(np.eye(3), 1, 0)[axis], np.roll(np.eye(3), 2, 0)[axis]
            base = len(verts)
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                verts.append(np.concatenate([n + a * u + b * w, n]))
            quad = [0, 1, 2, 0, 2, 3] if sign > 0 else [0, 2, 1, 0, 3, 2]
            idx += [base + q for q in quad]
    return np.array(verts, "f4"), np.array(idx, "i4")


def floor_quad():
    v = np.array([[-1, -1, 0, 0, 0, 1], [1, -1, 0, 0, 0, 1], [1, 1, 0, 0, 0, 1], [-1, 1, 0, 0, 0, 1]], "f4")
    return v, np.array([0, 1, 2, 0, 2, 3], "i4")


def perspective(fov_y, aspect, near, far):
    f = 1 / math.tan(fov_y / 2)
    return np.array([[f / aspect, 0, 0, 0], [0, f, 0, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)], [0, 0, -1, 0]])


def look(eye, yaw, pitch):
    """World-to-camera for a camera at eye looking along yaw (about z), pitch (down < 0)."""
    fwd = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    right = np.cross(fwd, [0, 0, 1])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = right, up, -fwd
    m[:3, 3] = -m[:3, :3] @ eye
    return m


# objects per view: floor, 2 spheres, 3 boxes  (xyz, scale), (rgb, is_floor)
MESHES = ("floor", "sphere", "box")
COUNTS = {"floor": 1, "sphere": 2, "box": 3}


def scene(views, same, seed=0):
    rng = np.random.default_rng(seed)
    per = sum(COUNTS.values())
    objects = np.zeros((views, per, 2, 4), "f4")
    vp = np.zeros((views, 4, 4), "f4")
    projection = perspective(math.radians(80), 1.0, 0.05, 50.0)
    for v in range(views):
        r = np.random.default_rng(seed) if same else rng
        eye = np.array([r.uniform(-1, 1), r.uniform(-1, 1), 0.25])
        yaw = r.uniform(0, 2 * math.pi)
        fwd = np.array([math.cos(yaw), math.sin(yaw), 0])
        rows = [((0, 0, 0, 20), (0.5, 0.6, 0.4, 1))]
        for _ in range(2):
            p = eye + fwd * r.uniform(0.8, 3) + np.cross(fwd, [0, 0, 1]) * r.uniform(-1, 1)
            rows.append(((p[0], p[1], 0.35, r.uniform(0.2, 0.5)), (*r.uniform(0.3, 1, 3), 0)))
        for _ in range(3):
            p = eye + fwd * r.uniform(1, 5) + np.cross(fwd, [0, 0, 1]) * r.uniform(-2, 2)
            rows.append(((p[0], p[1], 0.3, r.uniform(0.15, 0.4)), (*r.uniform(0.3, 1, 3), 0)))
        objects[v] = np.array(rows, "f4")
        vp[v] = (projection @ look(eye, yaw, math.radians(-12))).astype("f4")
    # GLSL mat4 is column-major: store the transpose's rows
    return objects, np.ascontiguousarray(vp.transpose(0, 2, 1))


class Harness:
    def __init__(self, size, views, layered, same=True, seed=0, ctx=None):
        self.ctx = ctx or moderngl.create_context(standalone=True, backend="egl", require=430)
        self.gl = gl()
        self.size, self.views, self.layered = size, views, layered
        defines = "#define LAYERED\n" if layered else ""
        vs = VERTEX.replace("#version 430\n", "#version 430\n" + defines, 1)
        self.program = self.ctx.program(vertex_shader=vs, fragment_shader=FRAGMENT)
        objects, vp = scene(views, same, seed)
        self.objects = self.ctx.buffer(objects.tobytes())
        self.vp = self.ctx.buffer(vp.tobytes())
        self.vaos = {}
        for name, (v, i) in {"floor": floor_quad(), "sphere": sphere(), "box": box()}.items():
            vbo, ibo = self.ctx.buffer(v.tobytes()), self.ctx.buffer(i.tobytes())
            self.vaos[name] = self.ctx.vertex_array(self.program, [(vbo, "3f 3f", "corner", "normal")], ibo)
        self.framebuffers = []  # (moderngl fb, colour texture name, first view, views)
        step = views if layered else TILES_PER_FRAMEBUFFER
        for first in range(0, views, step):
            count = min(step, views - first)
            self.framebuffers.append((*self._framebuffer(count), first, count))
        self.out = np.empty((views, size, size, 3), np.uint8)

    def _texture(self, fmt, count):
        name = ctypes.c_uint()
        if self.layered:
            self.gl["glCreateTextures"](GL_TEXTURE_2D_ARRAY, 1, ctypes.byref(name))
            self.gl["glTextureStorage3D"](name.value, 1, fmt, self.size, self.size, count)
        else:
            self.gl["glCreateTextures"](GL_TEXTURE_2D, 1, ctypes.byref(name))
            self.gl["glTextureStorage2D"](name.value, 1, fmt, self.size, self.size * count)
        return name.value

    def _framebuffer(self, count):
        color, depth = self._texture(GL_RGBA8, count), self._texture(GL_DEPTH_COMPONENT24, count)
        fbo = ctypes.c_uint()
        self.gl["glCreateFramebuffers"](1, ctypes.byref(fbo))
        self.gl["glNamedFramebufferTexture"](fbo.value, GL_COLOR_ATTACHMENT0, color, 0)
        self.gl["glNamedFramebufferTexture"](fbo.value, GL_DEPTH_ATTACHMENT, depth, 0)
        status = self.gl["glCheckNamedFramebufferStatus"](fbo.value, GL_FRAMEBUFFER)
        assert status == GL_FRAMEBUFFER_COMPLETE, hex(status)
        fb = self.ctx.detect_framebuffer(fbo.value)
        # moderngl's size query on a layered attachment raises GL_INVALID_OPERATION (it reports
        # size (0, 0)); the viewport is set explicitly in render().
        while self.gl["glGetError"]():
            pass
        return fb, color

    def render(self):
        ctx, p = self.ctx, self.program
        ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.front_face = "cw"  # every view is flipped vertically
        if not self.layered:
            self.gl["glEnable"](GL_CLIP_DISTANCE0)
            self.gl["glEnable"](GL_CLIP_DISTANCE0 + 1)
        self.objects.bind_to_storage_buffer(0)
        self.vp.bind_to_storage_buffer(1)
        p["objects_per_view"] = sum(COUNTS.values())
        for fb, _, first, count in self.framebuffers:
            fb.use()
            fb.viewport = (0, 0, self.size, self.size if self.layered else self.size * count)
            fb.clear(0.5, 0.7, 0.9, 1.0, depth=1.0)
            p["first_view"] = first
            if "tiles" in p:
                p["tiles"] = count
            first_object = 0
            for name in MESHES:
                p["per_view"] = COUNTS[name]
                p["first_object"] = first_object
                first_object += COUNTS[name]
                self.vaos[name].render(instances=COUNTS[name] * count)
        self.gl["glPixelStorei"](GL_PACK_ALIGNMENT, 1)
        for _, color, first, count in self.framebuffers:
            dst = self.out[first:first + count]
            depth = count if self.layered else 1
            height = self.size if self.layered else self.size * count
            self.gl["glGetTextureSubImage"](color, 0, 0, 0, 0, self.size, height, depth, GL_RGB, GL_UNSIGNED_BYTE,
                                            dst.nbytes, dst.ctypes.data)
        error = self.gl["glGetError"]()
        assert not error, hex(error)
        return self.out


def identity(args):
    ctx = moderngl.create_context(standalone=True, backend="egl", require=430)
    print(ctx.info["GL_RENDERER"], "GL_MAX_ARRAY_TEXTURE_LAYERS", ctx.info["GL_MAX_ARRAY_TEXTURE_LAYERS"])
    reference = None
    for layered in (False, True):
        for views in args.views:
            out = Harness(args.size, views, layered, same=True, ctx=ctx).render().copy()
            if layered and reference is None:
                reference = out[0].copy()
            differ = (out != out[0]).any(axis=(1, 2, 3))
            pixels = (out != out[0]).any(axis=3).sum(axis=(1, 2))
            against = "" if reference is None else \
                f"; view 0 vs layered 1-view run: {(out[0] != reference).any(axis=2).sum()} px differ"
            print(f"{'layered' if layered else 'tiled  '} {views:5d} identical views at {args.size} px: "
                  f"{differ.sum()} views differ from view 0 (max {pixels.max()} px, max |diff| "
                  f"{np.abs(out.astype(int) - out[0]).max()}){against}")
    tiled = Harness(args.size, 1, False, same=True, ctx=ctx).render()
    print("one-view tiled vs one-view layered:", (tiled[0] != reference).any(axis=2).sum(), "px differ")


def speed(args):
    ctx = moderngl.create_context(standalone=True, backend="egl", require=430)
    print(ctx.info["GL_RENDERER"], platform.processor())
    for views in args.views:
        runs = {name: Harness(args.size, views, name == "layers", same=False, seed=1, ctx=ctx)
                for name in ("tiles", "layers")}
        for h in runs.values():  # warm up: compile, first upload
            h.render()
        a, b = runs["tiles"].render().copy(), runs["layers"].render()
        times = {name: [] for name in runs}
        for rep in range(args.reps):
            order = ("tiles", "layers") if rep % 2 == 0 else ("layers", "tiles")
            for name in order:
                t = time.perf_counter()
                runs[name].render()
                times[name].append(time.perf_counter() - t)
        med = {n: statistics.median(t) for n, t in times.items()}
        ratios = [b / a for a, b in zip(times["tiles"], times["layers"], strict=True)]
        print(f"{views:5d} views {args.size} px: tiles {med['tiles'] * 1e3:8.1f} ms"
              f"  layers {med['layers'] * 1e3:8.1f} ms"
              f"  layers/tiles median {statistics.median(ratios):.2f} (min {min(ratios):.2f} max {max(ratios):.2f})"
              f"  px differing tiles vs layers {(a != b).any(axis=3).mean() * 100:.3f}%")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("what", choices=("identity", "speed"))
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--views", type=int, nargs="+")
    parser.add_argument("--reps", type=int, default=9)
    args = parser.parse_args()
    if args.views is None:
        args.views = [1, 7, 64, 256, 1024] if args.what == "identity" else [64, 256, 1024]
    identity(args) if args.what == "identity" else speed(args)
