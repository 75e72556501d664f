"""An independent floor: the plainest fast way found to draw an env's scene with raw OpenGL.

`FloorGL` takes a scene description (`marl_render.Scene`: meshes, static poses, colours,
lighting, cameras) and per-instance state, and draws every view of every world into a
preallocated `[W, A, H, W, 3]` uint8 batch. It shares no code with `BatchRenderer`: no
shader, buffer layout, tile layout, packing or culling of the renderer is used, only the
scene's public description and the mesh vertex arrays. It exists so that
`python -m marl_render.bench floor` can say how far the renderer is from what this
machine can do, not from its own design.

What it does per frame, each choice measured on Mesa llvmpipe (2 cores):
- pack: one `torch.cat` per instance group into the group's rows of a host array
  (position, active, rotation, scale, owner, colour; 16 floats), one view-projection
  matrix per view from the camera poses; both uploaded whole;
- draw: per framebuffer, one instanced draw per distinct mesh covering every
  (view, instance) pair of its views. Views are tiles stacked in ONE column, at most
  256 per framebuffer (more framebuffers for more views), every view flipped
  vertically so that the bottom-up rows glReadPixels returns are the batch's
  top-down rows. All framebuffers are drawn before the first readback: llvmpipe
  rasterises a framebuffer on its worker threads while the main thread bins the next.
- read: `glReadPixels` with 3 components (the driver drops alpha faster than numpy
  would) straight into the batch, no rearranging copy.
- flat-shaded meshes (boxes) are welded to shared corners: a box has 8 vertices
  instead of 24, and each face's normal rides on its triangles' provoking (last)
  vertex, lit per vertex and passed `flat`. Smooth meshes are lit per fragment.
- cull=False: the viewer's own body and inactive instances are clipped away in the
  vertex shader; cull=True: a torch frustum test per (view, instance) leaves them and
  everything out of view out of the draw (pays in the arena scenes, where most vertex
  work is out of sight).
- impostors=True: spheres (every vertex of the mesh 0.5 from its centre) are drawn as the
  renderer draws them by default, one quad per instance whose fragments cast the pixel's ray
  at the sphere and write its depth (its own minimal code below, not the renderer's: uniform
  scale, the radius 0.5 x scale.x); from_env turns it on where the env's renderer draws
  impostors, so the floor draws the same minimal geometry.
Only the `lighting` effect and `MeshData` meshes are supported (skinned meshes only in
static groups, which stay in their bind pose).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import moderngl
import numpy as np
import torch

from marl_render.assets.meshes import MeshData
from marl_render.assets.skinning import SkinnedMesh
from marl_render.render.scene import Scene

TILES_PER_FRAMEBUFFER = 256
FLOATS_PER_INSTANCE = 16  # position xyz, active, rotation wxyz, scale xyz, owner, colour rgba

# Which view, tile and instance row this draw instance is (culled: from the visible pairs), shared by both
# vertex shaders.
_INSTANCE_ROW = """#ifdef CULLED
    int pair = visible_pairs[first_pair + gl_InstanceID];
    int view = pair / per_view;
    int slot = pair - view * per_view;
    int tile = view - first_view;
#else
    int tile = gl_InstanceID / per_view;
    int slot = gl_InstanceID - tile * per_view;
    int view = first_view + tile;
#endif
    int world = view / agents;
    ivec2 rows = row_of[slot];
    int row = 4 * (rows.x + world * rows.y);
"""

_VERTEX = """
#version 430
layout(location = 0) in vec3 corner;
layout(location = 1) in vec3 normal;
layout(std430, binding = 0) readonly buffer Instances { vec4 instance_data[]; };
layout(std430, binding = 1) readonly buffer Views { mat4 view_projection[]; };
layout(std430, binding = 2) readonly buffer Rows { ivec2 row_of[]; };  // (first row, rows per world)
#ifdef CULLED
layout(std430, binding = 3) readonly buffer Pairs { int visible_pairs[]; };  // view * per_view + slot
uniform int first_pair;    // first pair of this framebuffer
#endif

uniform int per_view;      // instances of this mesh seen by one view
uniform int agents;        // views per world
uniform int first_view;    // first view of this framebuffer
uniform int tiles;         // tile rows of this framebuffer
uniform vec3 light_to;     // unit vector towards the light
uniform vec3 light_color;
uniform vec3 ambient;

#ifdef SMOOTH
out vec3 surface_normal;
flat out vec3 base_color;
#else
flat out vec3 lit_color;
#endif

vec3 turn(vec4 q, vec3 v) {  // rotate v by the unit quaternion q = (w, x, y, z)
    vec3 t = 2.0 * cross(q.yzw, v);
    return v + q.x * t + cross(q.yzw, t);
}

void main() {
""" + _INSTANCE_ROW + """    vec4 position = instance_data[row];
    vec4 rotation = instance_data[row + 1];
    vec4 scale = instance_data[row + 2];
    vec3 color = instance_data[row + 3].rgb;

    vec4 clip = view_projection[view] * vec4(position.xyz + turn(rotation, corner * scale.xyz), 1.0);
#ifdef CULLED
    const bool hidden = false;  // culling left out inactive instances and the viewer's own body
#else
    bool hidden = position.w == 0.0 || int(scale.w) == view - world * agents;
#endif
    // Tiles share the framebuffer's width, so only the top and bottom need clip planes.
    gl_ClipDistance[0] = hidden ? -1.0 : clip.w + clip.y;
    gl_ClipDistance[1] = hidden ? -1.0 : clip.w - clip.y;
    // Flip the view and move it into its tile row: image row 0 lands at the tile's lowest GL row.
    gl_Position = vec4(clip.x, (float(2 * tile + 1 - tiles) * clip.w - clip.y) / float(tiles), clip.z, clip.w);

    vec3 n = turn(rotation, normalize(normal / max(scale.xyz, vec3(1e-6))));
#ifdef SMOOTH
    surface_normal = n;
    base_color = color;
#else
    lit_color = color * (ambient + light_color * max(dot(n, light_to), 0.0));
#endif
}
"""

_FRAGMENT = """
#version 430
uniform vec3 light_to;
uniform vec3 light_color;
uniform vec3 ambient;
#ifdef SMOOTH
in vec3 surface_normal;
flat in vec3 base_color;
#else
flat in vec3 lit_color;
#endif
out vec4 pixel;

void main() {
#ifdef SMOOTH
    vec3 lit_color = base_color * (ambient + light_color * max(dot(normalize(surface_normal), light_to), 0.0));
#endif
    pixel = vec4(clamp(lit_color, 0.0, 1.0), 1.0);
}
"""


_IMPOSTOR_VERTEX = """
#version 430
layout(location = 0) in vec3 corner;  // (+-1, +-1, 0)
layout(std430, binding = 0) readonly buffer Instances { vec4 instance_data[]; };
layout(std430, binding = 1) readonly buffer Views { mat4 view_projection[]; };
layout(std430, binding = 2) readonly buffer Rows { ivec2 row_of[]; };
layout(std430, binding = 4) readonly buffer Eyes { vec4 eye_of[]; };  // camera position per view
#ifdef CULLED
layout(std430, binding = 3) readonly buffer Pairs { int visible_pairs[]; };
uniform int first_pair;
#endif
uniform int per_view;
uniform int agents;
uniform int first_view;
uniform int tiles;

out vec3 on_quad;            // world point of the quad
flat out vec4 sphere;        // centre, radius
flat out vec3 base_color;
flat out int view_index;

void main() {
""" + _INSTANCE_ROW + """    vec4 position = instance_data[row];
    float radius = 0.5 * instance_data[row + 2].x;
    vec3 eye = eye_of[view].xyz;
    vec3 out_of = eye - position.xyz;
    float d = length(out_of);
    vec3 toward = out_of / d;
    vec3 side = normalize(cross(abs(toward.z) < 0.9 ? vec3(0, 0, 1) : vec3(1, 0, 0), toward));
    vec3 up = cross(toward, side);
    // The square around the silhouette circle, in the silhouette's plane.
    float half_side = radius * sqrt(max(d * d - radius * radius, 0.0)) / d;
    on_quad = position.xyz + toward * (radius * radius / d) + half_side * (corner.x * side + corner.y * up);
    sphere = vec4(position.xyz, radius);
    base_color = instance_data[row + 3].rgb;
    view_index = view;
    vec4 clip = view_projection[view] * vec4(on_quad, 1.0);
    bool hidden = position.w == 0.0 || d <= radius || int(instance_data[row + 2].w) == view - world * agents;
    gl_ClipDistance[0] = hidden ? -1.0 : clip.w + clip.y;
    gl_ClipDistance[1] = hidden ? -1.0 : clip.w - clip.y;
    gl_Position = vec4(clip.x, (float(2 * tile + 1 - tiles) * clip.w - clip.y) / float(tiles), clip.z, clip.w);
}
"""

_IMPOSTOR_FRAGMENT = """
#version 430
layout(std430, binding = 1) readonly buffer Views { mat4 view_projection[]; };
layout(std430, binding = 4) readonly buffer Eyes { vec4 eye_of[]; };
uniform vec3 light_to;
uniform vec3 light_color;
uniform vec3 ambient;
in vec3 on_quad;
flat in vec4 sphere;
flat in vec3 base_color;
flat in int view_index;
out vec4 pixel;

void main() {
    vec3 eye = eye_of[view_index].xyz;
    vec3 ray = normalize(on_quad - eye);
    vec3 to_centre = sphere.xyz - eye;
    float along = dot(to_centre, ray);
    vec3 miss = to_centre - along * ray;
    float inside = sphere.w * sphere.w - dot(miss, miss);
    if (inside < 0.0) discard;
    vec3 hit = eye + (along - sqrt(inside)) * ray;
    vec4 clip = view_projection[view_index] * vec4(hit, 1.0);
    gl_FragDepth = 0.5 * clip.z / clip.w + 0.5;
    vec3 n = (hit - sphere.xyz) / sphere.w;
    pixel = vec4(clamp(base_color * (ambient + light_color * max(dot(n, light_to), 0.0)), 0.0, 1.0), 1.0);
}
"""


def _round(mesh: MeshData) -> bool:
    """Every vertex 0.5 from the origin: a unit-diameter sphere (what an impostor draws exactly)."""
    return mesh.name == "sphere" and bool(np.abs(np.linalg.norm(mesh.positions, axis=1) - 0.5).max() < 1e-5)


def shared_corners(mesh: MeshData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions [N, 3], normals [N, 3], triangles [T, 3]) of a flat-shaded mesh with its
    corners welded: each triangle's normal sits on its last (provoking) vertex.

    A corner shared by several faces can carry one face's normal; a face takes a corner
    that is free or already carries its normal, and a corner is duplicated only when none
    is. Triangles are rotated (winding kept) so that the chosen corner comes last.
    """
    _, welded = np.unique(mesh.positions.round(6), axis=0, return_inverse=True)
    welded = welded.reshape(-1)
    positions = np.zeros((welded.max() + 1, 3), dtype=np.float32)
    positions[welded] = mesh.positions
    normals: list = [None] * len(positions)
    triangles = welded[mesh.triangles]
    face_normals = mesh.normals[mesh.triangles[:, 0]]
    faces: dict = {}
    for index, normal in enumerate(face_normals.round(5)):  # build time only: a few dozen triangles
        faces.setdefault(tuple(normal), []).append(index)
    result = []
    for members in faces.values():
        normal = face_normals[members[0]]
        common = set(triangles[members[0]]).intersection(*(set(triangles[m]) for m in members[1:]))
        usable = [c for c in sorted(common) if normals[c] is None or np.allclose(normals[c], normal)]
        for member in members:
            corners = list(triangles[member])
            choice = usable[0] if usable else next(
                (c for c in corners if normals[c] is None or np.allclose(normals[c], normal)), None)
            if choice is None:  # every corner carries another face's normal: add a copy
                choice = len(normals)
                original = corners[0]
                positions = np.vstack((positions, positions[original:original + 1]))
                normals.append(None)
                corners[0] = choice
            normals[choice] = normal
            turn = (corners.index(choice) + 1) % 3
            result.append(corners[turn:] + corners[:turn])
    normal_array = np.array([n if n is not None else (0.0, 0.0, 1.0) for n in normals], dtype=np.float32)
    return positions, normal_array, np.array(result, dtype=np.uint32)


@dataclass
class _MeshDraw:
    vao: object
    rows: object  # moderngl.Buffer of (first row, rows per world) per slot
    per_view: int  # instances of this mesh in one world (= seen by each view)
    row_index: torch.Tensor  # [W, per_view] rows of the instance array (culling reads them)
    radius: float  # of the mesh's bounding sphere at unit scale
    pairs: object = None  # moderngl.Buffer of visible view * per_view + slot (culling)
    impostor: bool = False  # one quad per instance, the sphere ray-cast (impostors=True)
    ranges: list | None = None  # (first pair, count) per framebuffer (culling)


def _mesh_key(mesh: MeshData):
    return (mesh.positions.tobytes(), mesh.normals.tobytes(), mesh.triangles.tobytes())


class FloorGL:
    """Draws scene.num_worlds x scene.agents_per_world views of `scene` with moderngl on EGL.

    set_instances(group, ...) and set_cameras(...) store float32 state; render() packs it,
    draws and returns the preallocated batch [W, A, H, W, 3] uint8 (overwritten by the
    next render). Cameras mounted on instances (scene.mount_cameras) follow their bodies.
    cull=True tests every (view, instance) bounding sphere against the view's frustum in
    torch and draws only the visible pairs: it pays where vertex work dominates (many
    instances per view, most out of sight), and costs a few torch ops where it does not.
    """

    def __init__(self, scene: Scene, *, tiles_per_framebuffer: int = TILES_PER_FRAMEBUFFER, cull: bool = False,
                 impostors: bool = False):
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a marl_render.Scene, got {type(scene).__name__}")
        if set(scene.effects) - {"lighting"}:
            raise ValueError(f"FloorGL draws the lighting effect only; scene declares {list(scene.effects)}")
        groups = [*scene.static.values(), *scene.groups.values()]
        if any(not isinstance(g.mesh, MeshData) for g in groups):
            raise ValueError("FloorGL draws MeshData meshes only")
        skinned = [g.name for g in scene.groups.values() if isinstance(g.mesh, SkinnedMesh)]
        if skinned:
            raise ValueError(f"FloorGL has no skinning; groups {skinned} have skinned meshes (use BatchRenderer, "
                             "or mesh.rigid() for their bind pose)")
        self.scene, self.cull, self.impostors = scene, bool(cull), bool(impostors)
        self.ctx = moderngl.create_context(standalone=True, backend="egl", require=430)
        W, A = scene.num_worlds, scene.agents_per_world
        H, Wpx = scene.resolution
        max_size = int(self.ctx.info["GL_MAX_TEXTURE_SIZE"])
        self.tiles = max(1, min(tiles_per_framebuffer, max_size // H, scene.num_views))
        self.batch = torch.empty((W, A, H, Wpx, 3), dtype=torch.uint8)
        self._flat_batch = self.batch.numpy().reshape(-1)
        with self.ctx:
            self._build(scene)

    # ------------------------------------------------------------------ building
    def _build(self, scene: Scene):
        ctx, W, A = self.ctx, scene.num_worlds, scene.agents_per_world
        H, Wpx = scene.resolution
        # Rows of the instance array: every static instance once, then each group's [W, C] block.
        static_rows = sum(g.count for g in scene.static.values())
        rows = static_rows + sum(W * g.capacity for g in scene.groups.values())
        self._instances = torch.zeros(rows, FLOATS_PER_INSTANCE)
        first, self._blocks, mesh_rows = 0, {}, {}
        for group in scene.static.values():
            block = self._instances[first:first + group.count]
            block[:, 0:3] = group.position.to(torch.float32)
            block[:, 3] = 1.0
            block[:, 4:8] = group.rotation
            block[:, 8:11] = group.scale
            block[:, 11] = -1.0
            block[:, 12:16] = group.color
            mesh_rows.setdefault(_mesh_key(group.mesh), (group.mesh, []))[1].extend(
                (first + k, 0) for k in range(group.count))
            first += group.count
        for group in scene.groups.values():
            C = group.capacity
            self._blocks[group.name] = self._instances[first:first + W * C].view(W, C, FLOATS_PER_INSTANCE)
            mesh_rows.setdefault(_mesh_key(group.mesh), (group.mesh, []))[1].extend(
                (first + k, C) for k in range(C))
            first += W * C
        self._state = {name: {"position": torch.zeros(W, g.capacity, 3), "active": torch.zeros(W, g.capacity, 1),
                              "rotation": torch.tensor([1.0, 0, 0, 0]).repeat(W, g.capacity, 1),
                              "scale": torch.ones(W, g.capacity, 3), "owner": torch.full((W, g.capacity, 1), -1.0),
                              "color": torch.ones(W, g.capacity, 4)} for name, g in scene.groups.items()}
        self.camera_position = torch.zeros(W, A, 3)
        self.camera_rotation = torch.tensor([1.0, 0, 0, 0]).repeat(W, A, 1)
        self._views = torch.zeros(W * A, 4, 4)  # column-major mat4 per view (std430)

        self._instance_buffer = ctx.buffer(reserve=self._instances.numel() * 4, dynamic=True)
        self._view_buffer = ctx.buffer(reserve=self._views.numel() * 4, dynamic=True)
        self._eyes = torch.zeros(W * A, 4)  # each view's camera position (impostors)
        self._eye_buffer = ctx.buffer(reserve=self._eyes.numel() * 4, dynamic=True)
        lighting = scene.lighting
        to_light = -np.asarray(lighting.direction, dtype=np.float64)
        uniforms = {"agents": A, "tiles": self.tiles, "light_to": tuple(to_light / np.linalg.norm(to_light)),
                    "light_color": tuple(lighting.color), "ambient": tuple(lighting.ambient)}
        if "lighting" not in scene.effects:  # unlit: colour as given
            uniforms.update(light_color=(0.0, 0.0, 0.0), ambient=(1.0, 1.0, 1.0))
        world = torch.arange(W)[:, None]
        self._draws = []
        for mesh, table in mesh_rows.values():
            impostor = self.impostors and _round(mesh)
            smooth = not mesh.flat
            if impostor:
                positions = np.float32([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
                normals, triangles = np.zeros_like(positions), np.uint32([[0, 1, 2], [0, 2, 3]])
            elif smooth:
                positions, normals, triangles = mesh.positions, mesh.normals, mesh.triangles.astype(np.uint32)
            else:
                positions, normals, triangles = shared_corners(mesh)
            defines = ("#define SMOOTH\n" if smooth else "") + ("#define CULLED\n" if self.cull else "")
            vertex, fragment = (_IMPOSTOR_VERTEX, _IMPOSTOR_FRAGMENT) if impostor else (_VERTEX, _FRAGMENT)
            program = ctx.program(vertex_shader=vertex.replace("#version 430\n", "#version 430\n" + defines),
                                  fragment_shader=fragment.replace("#version 430\n", "#version 430\n" + defines))
            for name, value in uniforms.items():
                if name in program:
                    program[name].value = value
            program["per_view"].value = len(table)
            vertices = ctx.buffer(np.concatenate((positions, normals), 1).astype(np.float32))
            indices = ctx.buffer(triangles.astype(np.uint32))
            layout = [(vertices, "3f 12x", "corner")] if impostor else [(vertices, "3f 3f", "corner", "normal")]
            vao = ctx.vertex_array(program, layout, index_buffer=indices, index_element_size=4)
            table = torch.tensor(table, dtype=torch.int64)
            draw = _MeshDraw(vao, ctx.buffer(table.to(torch.int32).numpy()), len(table),
                             table[:, 0] + world * table[:, 1], float(np.linalg.norm(mesh.positions, axis=1).max()),
                             impostor=impostor)
            if self.cull:
                draw.pairs = ctx.buffer(reserve=max(4, 4 * scene.num_views * len(table)), dynamic=True)
            self._draws.append(draw)

        n = scene.num_views
        self._framebuffers = []
        for start in range(0, n, self.tiles):
            size = (Wpx, self.tiles * H)
            framebuffer = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, components=4)],
                                          depth_attachment=ctx.depth_renderbuffer(size))
            self._framebuffers.append((framebuffer, start, min(self.tiles, n - start)))
        self._framebuffer_starts = torch.tensor([start for _, start, _ in self._framebuffers] + [n], dtype=torch.int32)
        aspect = Wpx / H
        f = 1.0 / math.tan(scene.fov_y / 2)
        near, far = scene.near, scene.far
        # Camera frame (x right, y forward, z up) -> GL eye frame (x right, y up, looking down -z), then projection.
        axes = torch.tensor([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
        projection = torch.tensor([[f / aspect, 0, 0, 0], [0, f, 0, 0],
                                   [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
                                   [0, 0, -1, 0]])
        self._projection_3 = projection[:, :3] @ axes  # [4, 3]: acts on camera-frame vectors
        self._projection_t = projection[:, 3]
        mount = scene.camera_mount
        self._mount = None
        if mount is not None:
            half = 0.5 * mount.pitch
            self._mount = (mount.group, torch.tensor(mount.instance), torch.tensor(mount.offset),
                           torch.tensor([math.cos(half), math.sin(half), 0.0, 0.0]))
        self._agent = torch.arange(A, dtype=torch.float32)[None, :, None]

    # ------------------------------------------------------------------ state
    def set_instances(self, group: str, *, position=None, rotation=None, scale=None, color=None, active=None,
                      owner=None) -> None:
        """Per-instance state [W, C, ...] of an instance group (rotation: unit quaternions w, x, y, z)."""
        state = self._state[group]
        W, C = state["active"].shape[:2]
        for key, value in (("position", position), ("rotation", rotation), ("scale", scale), ("color", color)):
            if value is not None:
                value = torch.as_tensor(value, dtype=torch.float32)
                if key == "color" and value.shape[-1] == 3:
                    value = torch.cat((value, torch.ones_like(value[..., :1])), -1)
                state[key].copy_(value.expand(W, C, state[key].shape[-1]))
        for key, value in (("active", active), ("owner", owner)):
            if value is not None:
                state[key].copy_(torch.as_tensor(value).to(torch.float32).reshape(W, C, 1))

    def set_cameras(self, position, rotation) -> None:
        """Free cameras: position [W, A, 3], rotation [W, A, 4] (camera looks along its +y, z up)."""
        self.camera_position.copy_(torch.as_tensor(position, dtype=torch.float32))
        self.camera_rotation.copy_(torch.as_tensor(rotation, dtype=torch.float32))

    # ------------------------------------------------------------------ a frame
    def render(self) -> torch.Tensor:
        """Pack, (cull,) upload, draw every framebuffer, read each into the batch; returns the batch."""
        for name, block in self._blocks.items():
            s = self._state[name]
            torch.cat((s["position"], s["active"], s["rotation"], s["scale"], s["owner"], s["color"]), -1, out=block)
        view_projection = self._pack_views()
        pairs = None
        if self.cull:
            W, A = self.scene.num_worlds, self.scene.agents_per_world
            r0, r1, r2, r3 = view_projection.reshape(W, A, 4, 4).unbind(-2)
            planes = torch.stack((r3 + r0, r3 - r0, r3 + r1, r3 - r1, r3 + r2, r3 - r2), -2)  # [W, A, 6, 4]
            planes = planes / planes[..., :3].norm(dim=-1, keepdim=True)
            pairs = [self._visible(draw, planes) for draw in self._draws]
        with self.ctx:  # another context (Panda3D's) may be current in this thread
            ctx = self.ctx
            self._instance_buffer.write(self._instances.numpy())
            self._view_buffer.write(self._views.numpy())
            self._instance_buffer.bind_to_storage_buffer(0)
            self._view_buffer.bind_to_storage_buffer(1)
            if self.impostors:
                self._eye_buffer.write(self._eyes.numpy())
                self._eye_buffer.bind_to_storage_buffer(4)
            if pairs is not None:
                for draw, visible in zip(self._draws, pairs, strict=True):
                    if len(visible):
                        draw.pairs.write(visible.numpy())
            ctx.enable_only(ctx.DEPTH_TEST | ctx.CULL_FACE)
            ctx.front_face = "cw"  # the vertical flip reverses the winding
            ctx.enable_direct(0x3000)  # GL_CLIP_DISTANCE0
            ctx.enable_direct(0x3001)
            red, green, blue = self.scene.background[:3]
            for index, (framebuffer, start, count) in enumerate(self._framebuffers):
                framebuffer.use()
                framebuffer.clear(red, green, blue, 1.0, depth=1.0)
                for draw in self._draws:
                    draw.rows.bind_to_storage_buffer(2)
                    if draw.impostor:  # the quad faces the camera whatever its winding
                        ctx.disable(ctx.CULL_FACE)
                    else:
                        ctx.enable(ctx.CULL_FACE)
                    program = draw.vao.program
                    program["first_view"].value = start
                    if pairs is None:
                        draw.vao.render(instances=count * draw.per_view)
                        continue
                    first, visible = draw.ranges[index]
                    if visible:
                        draw.pairs.bind_to_storage_buffer(3)
                        program["first_pair"].value = first
                        draw.vao.render(instances=visible)
            H, Wpx = self.scene.resolution
            tile_bytes = H * Wpx * 3
            for framebuffer, start, count in self._framebuffers:
                out = self._flat_batch[start * tile_bytes:(start + count) * tile_bytes]
                framebuffer.read_into(out, viewport=(0, 0, Wpx, count * H), components=3, alignment=1)
        return self.batch

    def _pack_views(self) -> torch.Tensor:
        """view-projection per view into the upload array (column-major); returns them [V, 4, 4] row-major."""
        if self._mount is not None:
            group, instance, offset, tilt = self._mount
            s = self._state[group]
            body_position, body_rotation = s["position"][:, instance], s["rotation"][:, instance]
            position = body_position + _turn(body_rotation, offset.expand_as(body_position))
            rotation = _compose(body_rotation, tilt.expand_as(body_rotation))
        else:
            position, rotation = self.camera_position, self.camera_rotation
        self._eyes[:, :3] = position.reshape(-1, 3)
        camera_to_world = _matrix(rotation.reshape(-1, 4))  # [V, 3, 3]
        linear = self._projection_3 @ camera_to_world.transpose(1, 2)  # [V, 4, 3]
        shift = self._projection_t - (linear @ position.reshape(-1, 3, 1))[..., 0]  # [V, 4]
        views = self._views.view(-1, 4, 4)  # [V, column, row]
        views[:, :3] = linear.transpose(1, 2)
        views[:, 3] = shift
        return views.transpose(1, 2)

    def _visible(self, draw: _MeshDraw, planes: torch.Tensor) -> torch.Tensor:
        """int32 view * per_view + slot of the pairs whose bounding sphere meets the view's
        frustum (planes [W, A, 6, 4]), sorted by view; sets draw.ranges per framebuffer."""
        rows = self._instances[draw.row_index]  # [W, K, 16]
        radius = draw.radius * rows[..., 8:11].amax(-1)  # [W, K]
        distance = planes[..., :3] @ rows[:, None, :, 0:3].transpose(-1, -2) + planes[..., 3:]  # [W, A, 6, K]
        seen = (distance >= -radius[:, None, None]).all(-2)
        seen &= (rows[:, None, :, 3] != 0) & (rows[:, None, :, 11] != self._agent)
        pairs = seen.view(-1).nonzero().view(-1).to(torch.int32)
        if len(self._framebuffers) == 1:
            draw.ranges = [(0, len(pairs))]
            return pairs
        bounds = torch.searchsorted(pairs, self._framebuffer_starts * draw.per_view).tolist()
        draw.ranges = [(bounds[i], bounds[i + 1] - bounds[i]) for i in range(len(self._framebuffers))]
        return pairs

    def close(self) -> None:
        if self.ctx is not None:
            self.ctx.release()
            self.ctx = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _turn(q, v):
    u, w = q[..., 1:], q[..., :1]
    t = 2.0 * torch.cross(u, v, dim=-1)
    return v + w * t + torch.cross(u, t, dim=-1)


def _compose(a, b):
    """Quaternion product a * b (apply b first)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack((aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw), -1)


def _matrix(q):
    w, x, y, z = q.unbind(-1)
    return torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), -1).view(-1, 3, 3)


def from_env(env, **options) -> FloorGL:
    """A FloorGL of an env's scene holding the env's current bodies and cameras (options: FloorGL's;
    impostors where the env's renderer draws any)."""
    renderer = env.renderer
    options.setdefault("impostors", bool(renderer.impostor_groups))
    floor = FloorGL(renderer.scene, **options)
    for name in renderer.scene.groups:
        state = renderer.instance_state(name)
        floor.set_instances(name, **state)
    if renderer.scene.camera_mount is None:
        floor.set_cameras(renderer.camera_position, renderer.camera_rotation)
    return floor
