"""Impostors: a sphere drawn as one quad whose fragments cast the pixel's ray at the sphere.

A sphere mesh costs its triangles in every view it shows in, however few pixels it covers:
commons' 45 apples of 80 triangles are 89% of its triangles, and vertex work is two thirds
of its render (`python -m marl_render.bench profile`, docs/performance.md). An impostor is
one quad per instance (shaders/impostor.vert) across the cone of rays from the camera that
meet the sphere; its fragment stage (shaders/impostor.frag) intersects each pixel's ray with
the sphere and writes the depth (gl_FragDepth), the analytic normal's lighting, the depth and
segmentation outputs. The picture is the sphere itself, not its faceted mesh: exact where the
mesh is an approximation (the difference, against the meshes, is in docs/accuracy.md).

The renderer chooses: BatchRenderer(impostors="auto") draws every group whose mesh is a sphere
(is_sphere: meshes.sphere() of any subdivision) as impostors where the scene's effects and
the renderer's options allow, and as meshes where they do not; impostors=True asks for them
and refuses (ValueError, saying why) what they cannot do; False (BatchRenderer's default)
draws meshes. The envs pass "auto" (envs/rendering.py). What they cannot do: shadows (the
shadow pass draws meshes into the light's map, and the sphere would receive its facets'
shadow), textures (no uvs on a ray-cast sphere), multisamples (MSAA would sample the quad's
coverage, not the sphere's: use supersample), exact_tiles (its geometry stage places each
triangle in its tile) and floor or wall roles under the appearance effect (patterns). With
layered=True the quads go to their view's layer, as every mesh does.
"""
from __future__ import annotations

import functools

import numpy as np

from ..assets.meshes import MeshData
from ..util.validation import describe
from . import row_layouts, shaders

MODES = (False, True, "auto")

# Quads per GL instance. llvmpipe runs its vertex pipeline once per instance (fetch, a vertex shader
# call over 8 lanes, clipping, primitive setup), half empty for one 4-corner quad; a batch of them per
# instance shares that. Measured: 2-5% of a commons step at 64 worlds (tools/impostor_batches.py).
QUADS_PER_INSTANCE = 16


def check_mode(impostors) -> bool | str:
    """impostors: False, True or "auto" (a bool-like numpy value counts as its bool)."""
    if isinstance(impostors, (bool, np.bool_)):
        return bool(impostors)
    if isinstance(impostors, str) and impostors == "auto":
        return "auto"
    raise ValueError(f"impostors must be one of {list(MODES)}, got {describe(impostors)}")


def is_sphere(mesh) -> bool:
    """A procedural sphere (meshes.sphere(), any segments and rings): every vertex at radius
    0.5 from the origin, with its normal pointing straight out."""
    if type(mesh) is not MeshData or mesh.name != "sphere" or not len(mesh.positions):
        return False
    radius = np.linalg.norm(mesh.positions, axis=1)
    return bool(np.abs(radius - 0.5).max() < 1e-5 and np.abs(mesh.normals - 2.0 * mesh.positions).max() < 1e-4)


def refusal(group, effects, *, multisamples: int, exact_tiles: bool) -> str | None:
    """Why `group` cannot be drawn as impostors in this renderer, or None when it can."""
    if "shadows" in effects:
        return ("the 'shadows' effect draws meshes into the light's map, and an impostor would receive its "
                "own facets' shadow")
    if group.texture is not None and "texture" in effects:
        return "the 'texture' effect needs the mesh's uvs, which a ray-cast sphere has not"
    if multisamples:
        return "multisamples would sample the quad's coverage, not the sphere's (use supersample)"
    if exact_tiles:
        return "exact_tiles places every triangle in its tile with a geometry stage of its own"
    role = group.role
    if "appearance" in effects and (bool(role.any()) if hasattr(role, "any") else role is not None):
        return "floor and wall roles draw the appearance effect's patterns, which impostors do not"
    return None


def choose(scene, impostors, *, multisamples: int, exact_tiles: bool) -> frozenset:
    """Names of the groups to draw as impostors: spheres, where refusal() finds nothing. With
    impostors=True a refused sphere group is a ValueError naming the group and the reason."""
    mode = check_mode(impostors)
    if mode is False:
        return frozenset()
    chosen = set()
    for group in list(scene.static.values()) + list(scene.groups.values()):
        if not is_sphere(group.mesh):
            continue
        reason = refusal(group, scene.effects, multisamples=multisamples, exact_tiles=exact_tiles)
        if reason is None:
            chosen.add(group.name)
        elif mode is True:
            raise ValueError(f"impostors=True cannot draw the sphere group {group.name!r}: {reason}; "
                             f"pass impostors='auto' to draw it as a mesh instead")
    return frozenset(chosen)


def defines(effects, *, static: bool, gray: bool, layered: bool = False) -> tuple[str, ...]:
    """The sorted #define lines of an impostor variant: the declared effects it draws, the
    instance and view layouts (row_layouts.py), where the aux outputs go, and whether each view
    is a layer (BatchRenderer(layered=True)) rather than a tile."""
    names = {shaders.EFFECT_DEFINES[e] for e in effects if e in ("lighting", "fog", "depth", "segmentation",
                                                                  "log_depth", "appearance")}
    if "appearance" in effects:
        names.update(row_layouts.appearance_defines())
    if gray:
        names.add("OUTPUT_GRAY")
    if static:
        names.add("STATIC_GROUP")
    if layered:
        names.add("LAYERED_VIEWS")
    names.update(row_layouts.glsl_defines(static=static))
    names.add(f"QUADS_PER_INSTANCE {QUADS_PER_INSTANCE}")
    names.update(f"{name.upper()}_LOCATION {location}"
                 for location, name in enumerate([n for n in ("depth", "segmentation") if n in effects], start=1))
    return tuple(sorted(names))


def _stage(name: str, variant: tuple[str, ...]) -> str:
    return shaders.GLSL_VERSION + "".join(f"#define {d}\n" for d in variant) + shaders.source(name)


@functools.cache
def compiled(variant: tuple[str, ...]):
    """Cached Panda3D Shader of one impostor variant (defines())."""
    from panda3d.core import Shader

    shader = Shader.make(Shader.SL_GLSL, _stage("impostor.vert", variant), _stage("impostor.frag", variant))
    if shader is None:
        raise RuntimeError(f"impostor variant {variant} failed to parse; see the GL log above")
    return shader


def quad_node():
    """A NodePath of QUADS_PER_INSTANCE impostor quads: corners (+-1, +-1, k) for the k-th quad of
    an instance, two triangles each, drawn from either side (the vertex stage turns each to face the
    camera and draws pair instance * QUADS_PER_INSTANCE + k, or nothing past the pass's pair count)."""
    from panda3d.core import CullFaceAttrib, NodePath

    from ..assets.meshes import to_panda_geom

    corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float32)
    positions = np.tile(corners, (QUADS_PER_INSTANCE, 1))
    positions[:, 2] = np.repeat(np.arange(QUADS_PER_INSTANCE, dtype=np.float32), 4)
    triangles = np.array([[0, 1, 2], [0, 2, 3]], np.int32)[None] + 4 * np.arange(QUADS_PER_INSTANCE)[:, None, None]
    quads = MeshData("impostor_quads", positions, np.tile(np.float32([0, 0, 1]), (len(positions), 1)),
                     (positions[:, :2] * 0.5 + 0.5).astype(np.float32), triangles.reshape(-1, 3).astype(np.int32))
    node = NodePath(to_panda_geom(quads))
    node.set_attrib(CullFaceAttrib.make(CullFaceAttrib.M_cull_none))
    return node
