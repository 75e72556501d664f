"""Shader variants: the GLSL in shaders/ with one #define per declared effect.

Every variant also gets the buffer layout's #defines (row_layouts.py: ROW_* for its instance
rows, VIEW_* for the view rows), generated from the table the packer writes with.

Code inside `#ifdef EFFECT_X` blocks is removed by the GLSL preprocessor when the scene
does not declare X, so an undeclared effect costs nothing at draw time. One Panda3D
Shader object is built per distinct set of defines and cached.
"""
from __future__ import annotations

import functools
from importlib import resources

from . import row_layouts

GLSL_VERSION = "#version 410\n"

# ITU-R BT.601 luma weights of the gray colour output (as torchvision's rgb_to_grayscale).
GRAY_WEIGHTS = (0.299, 0.587, 0.114)

# Effects a scene may declare, and the define each one turns on.
EFFECT_DEFINES = {
    "lighting": "EFFECT_LIGHTING",
    "texture": "EFFECT_TEXTURE",
    "fog": "EFFECT_FOG",
    "depth": "OUTPUT_DEPTH",
    "segmentation": "OUTPUT_SEGMENTATION",
    "log_depth": "LOG_DEPTH",
    "shadows": "EFFECT_SHADOWS",
    "appearance": "EFFECT_APPEARANCE",
}
EFFECTS = tuple(EFFECT_DEFINES)


@functools.cache
def source(name: str) -> str:
    return resources.files("marl_render.glsl").joinpath(name).read_text()


def defines_for(effects: frozenset, *, static: bool, textured: bool, flat: bool = False,
                corners: bool = False, gray: bool = False, shadow_pcf: bool = False,
                joints: int = 0, influences: int = 4, role: int = 0, surface: bool = False,
                exact: bool = False, layered: bool = False) -> tuple[str, ...]:
    """The sorted #define lines of one variant (texture only for groups that have one).

    Lighting runs per vertex for meshes whose faces each have one normal (flat), where
    it is exact, and per fragment otherwise. Depth needs each triangle's plane: from the
    corners that procedural meshes carry (`corners`, see triangle_corners.py), else from
    a geometry shader (model files, and skinned meshes, whose corners move with their own
    joints). gray: the colour output is its luma (GRAY_WEIGHTS).
    The colour is a flat varying in every variant, so a flat mesh may also be drawn from
    its welded corners (provoking.py) with the same defines. Shadows filter their edges
    (SHADOW_PCF) only when asked. joints > 0: a skinned group (the SKINNING variant), whose
    instances carry that many joint matrices and whose vertices follow up to `influences`
    joints each (1..4; each vertex blends only that many). Under the appearance effect, role is
    the code (scene.ROLES) of every instance of a moving group (static groups read theirs per
    instance), and surface says that some instance has a role: only then does the variant carry
    the floor and wall patterns (a world position per fragment). exact: the EXACT_TILES variant,
    whose geometry stage (exact.geom) makes a view's pixels independent of where its tile sits
    (BatchRenderer(exact_tiles=True)); it computes each triangle's depth plane itself. layered:
    each view is drawn into its own layer of an array texture (BatchRenderer(layered=True))."""
    defines = {EFFECT_DEFINES[e] for e in effects if e != "texture"}
    if "appearance" in effects:
        defines.update(row_layouts.appearance_defines())
        if role and not static:
            defines.add(f"GROUP_ROLE {role}")
        if surface:
            defines.add("APPEARANCE_SURFACE")
    if "lighting" in effects:
        defines.add("LIGHT_PER_VERTEX" if flat else "LIGHT_PER_FRAGMENT")
    if layered:
        defines.add("LAYERED_VIEWS")
    if exact:
        defines.add("EXACT_TILES")
    elif "depth" in effects:
        defines.add("DEPTH_PLANE_FROM_CORNERS" if corners else "DEPTH_PLANE_FROM_GEOMETRY")
    if "shadows" in effects and shadow_pcf:
        defines.add("SHADOW_PCF")
    if gray:
        defines.add("OUTPUT_GRAY")
    if "texture" in effects and textured:
        defines.add("EFFECT_TEXTURE")
    defines.update(_instance_defines(static, joints, influences))
    defines.update(_aux_locations(effects))
    return tuple(sorted(defines))


def _aux_locations(effects) -> set[str]:
    """Aux attachments are numbered in declaration order after the colour target."""
    names = [name for name in ("depth", "segmentation") if name in effects]
    return {f"{name.upper()}_LOCATION {location}" for location, name in enumerate(names, start=1)}


def variant_source(stage: str, defines: tuple[str, ...]) -> str:
    """Full GLSL text of one stage ("vert", "geom" or "frag") for the given defines."""
    header = GLSL_VERSION + "".join(f"#define {d}\n" for d in defines)
    return header + source(f"batch.{stage}")


_COMPILED: dict = {}  # ("view" | "caster", defines) -> Panda3D Shader


def forget_compiled() -> None:
    """Drop every cached variant: after a variant failed to compile or link, its Shader object
    keeps its error flag, and a cached one would make every later renderer draw nothing."""
    _COMPILED.clear()


def compiled(defines: tuple[str, ...]):
    """Cached Panda3D Shader for one variant (compiled by the driver on first draw)."""
    key = ("view", defines)
    if key not in _COMPILED:
        _COMPILED[key] = _compile_view(defines)
    return _COMPILED[key]


def _compile_view(defines: tuple[str, ...]):
    from panda3d.core import Shader

    geometry = ""
    if "EXACT_TILES" in defines:
        geometry = GLSL_VERSION + "".join(f"#define {d}\n" for d in defines) + source("exact.geom")
    elif "DEPTH_PLANE_FROM_GEOMETRY" in defines:
        geometry = variant_source("geom", defines)
    shader = Shader.make(Shader.SL_GLSL, variant_source("vert", defines), variant_source("frag", defines), geometry)
    if shader is None:
        raise RuntimeError(f"shader variant {defines} failed to parse; see the GL log above")
    return shader


def _instance_defines(static: bool, joints: int, influences: int) -> set[str]:
    """The instance layout of a group (row_layouts.py: where the packer put each value, joints
    included), and whether it is static or skinned."""
    if joints and static:
        raise ValueError("static groups cannot be skinned: their instances have no joints")
    defines = set(row_layouts.glsl_defines(static=static, joints=joints))
    if joints:
        if not 1 <= influences <= 4:
            raise ValueError(f"influences must be in [1, 4], got {influences}")
        defines.update(("SKINNING", f"SKIN_INFLUENCES {influences}"))
    if static:
        defines.add("STATIC_GROUP")
    return defines


def caster_defines(*, static: bool, joints: int = 0, influences: int = 4) -> tuple[str, ...]:
    """#defines of the shadow-map pass: positions only, no effect (see shadows.py); a skinned
    group's casters are skinned like its views (same joints, same influences)."""
    return tuple(sorted(_instance_defines(static, joints, influences) | {"SHADOW_CASTER"}))


def compiled_caster(defines: tuple[str, ...]):
    """Cached Panda3D Shader of the depth-only shadow pass: batch.vert, an empty fragment stage."""
    key = ("caster", defines)
    if key not in _COMPILED:
        _COMPILED[key] = _compile_caster(defines)
    return _COMPILED[key]


def _compile_caster(defines: tuple[str, ...]):
    from panda3d.core import Shader

    fragment = GLSL_VERSION + source("shadow_caster.frag")
    shader = Shader.make(Shader.SL_GLSL, variant_source("vert", defines), fragment)
    if shader is None:
        raise RuntimeError(f"shadow caster variant {defines} failed to parse; see the GL log above")
    return shader
