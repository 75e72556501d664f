"""The packed-buffer layout: where each value sits in the instance and view buffers.

One table for both sides. The packer (packing.py) writes through `Field.index`, and
the shaders read through the `#define`s that `glsl_defines()` generates from the same
table (shaders.py prepends them to every variant), so the two cannot drift apart.

Every buffer is a buffer texture of RGBA32F texels: a row of TEXELS texels per
instance (or per view), each field one texel and some of its lanes.
"""
from __future__ import annotations

from dataclasses import dataclass

LANES = "xyzw"


@dataclass(frozen=True)
class Field:
    """One value of a row: texel `texel`, lanes `lanes` (a run of "xyzw", as GLSL swizzles them)."""

    texel: int
    lanes: str = "xyzw"

    @property
    def index(self) -> tuple:
        """(texel, lanes) index into a row viewed as [..., TEXELS, 4]; one lane is an int, several a slice."""
        first = LANES.index(self.lanes[0])
        lanes = first if len(self.lanes) == 1 else slice(first, first + len(self.lanes))
        return self.texel, lanes


@dataclass(frozen=True)
class RowLayout:
    """The fields of one kind of row; `prefix` names its GLSL defines."""

    prefix: str
    texels: int
    fields: dict

    def __post_init__(self):
        for name, field in self.fields.items():
            if not 0 <= field.texel < self.texels or field.lanes not in LANES:
                raise ValueError(f"field {name} of {self.prefix} is outside its {self.texels}-texel row: {field}")

    def __getitem__(self, name: str) -> tuple:
        return self.fields[name].index

    def defines(self, prefix: str | None = None) -> tuple[str, ...]:
        """`PREFIX_TEXELS n`, `PREFIX_NAME texel` and `PREFIX_NAME_LANES swizzle` for every
        field (PREFIX: `prefix`, else the table's own)."""
        prefix = prefix or self.prefix
        lines = [f"{prefix}_TEXELS {self.texels}"]
        for name, field in self.fields.items():
            define = f"{prefix}_{name.upper()}"
            lines += [f"{define} {field.texel}", f"{define}_LANES {field.lanes}"]
        return tuple(lines)


# One row per instance of a moving group and world: position relative to its world's origin.
INSTANCE = RowLayout("INSTANCE", 4, {
    "position": Field(0, "xyz"),
    "active": Field(0, "w"),  # read by culling only
    "rotation": Field(1),  # unit quaternion (w, x, y, z)
    "scale": Field(2, "xyz"),
    "owner": Field(2, "w"),  # read by culling only
    "color": Field(3),
})

# A skinned group's rows carry one 3x4 bind-to-pose matrix (JOINT_TEXELS texels, one row of
# the matrix each) per joint, after the INSTANCE fields.
JOINT_TEXELS = 3

# One row per instance of a static group, shared by every world: the absolute position
# in two float32s (hi + lo) so that scenes far from 0 keep sub-millimetre precision.
STATIC_INSTANCE = RowLayout("STATIC", 5, {
    "position": Field(0, "xyz"),
    "role": Field(0, "w"),  # scene.ROLES code, read by the "appearance" effect (with the position: no fetch more)
    "rotation": Field(1),
    "scale": Field(2, "xyz"),
    "owner": Field(2, "w"),
    "color": Field(3),
    "position_lo": Field(4, "xyz"),
    "active": Field(4, "w"),
})

# One row per view (and per world in the shadow pass's light buffer): the view-projection
# by columns (texel j = column j), the world's origin as hi + lo, the view's near / far.
VIEW = RowLayout("VIEW", 6, {
    "projection": Field(0),  # texels 0-3
    "origin_hi": Field(4, "xyz"),
    "near": Field(4, "w"),
    "origin_lo": Field(5, "xyz"),
    "far": Field(5, "w"),
})
VIEW_PROJECTION_TEXELS = 4

# One row per world of the "appearance" effect (appearance.py): its light, sky, the colours and
# patterns of its floor and walls (rgb, w = 1: replaces the instance colour; a pattern is two
# texels: cells per metre along u and v, row shift, line threshold; the factors it leaves past the
# threshold along u, v and both, appearance.pattern_factors) and the
# colour transform of everything else, rgb' = a rgb + b mean(rgb) + c ((1, 1, 1) x rgb)
# (appearance.color_transform_terms: hue, saturation and value in three numbers). a, b and c sit
# beside the light, whose texels a lit vertex fetches anyway.
APPEARANCE = RowLayout("APPEARANCE", 10, {
    "light_direction": Field(0, "xyz"),  # unit, pointing from the light
    "transform_a": Field(0, "w"),
    "light_color": Field(1, "xyz"),
    "transform_b": Field(1, "w"),
    "ambient": Field(2, "xyz"),
    "transform_c": Field(2, "w"),
    "sky": Field(3, "xyz"),
    "floor": Field(4),
    "wall": Field(5),
    "floor_pattern": Field(6),  # texels 6-7
    "wall_pattern": Field(8),  # texels 8-9
})
PATTERN_TEXELS = 2


def instance_texels(*, static: bool, joints: int = 0) -> int:
    """Texels of one instance row: a static one, or a moving one with `joints` joint matrices."""
    return STATIC_INSTANCE.texels if static else INSTANCE.texels + JOINT_TEXELS * joints


def glsl_defines(*, static: bool, joints: int = 0) -> tuple[str, ...]:
    """The layout's #define lines (without "#define ") for a shader variant: the rows of its
    instance buffer as ROW_* (STATIC_INSTANCE for static groups, else INSTANCE), ROW_TEXELS
    with the joints of a skinned group (FIRST_JOINT_TEXEL, JOINT_TEXELS), and VIEW_*."""
    table = STATIC_INSTANCE if static else INSTANCE
    row = tuple(line for line in table.defines("ROW") if not line.startswith("ROW_TEXELS "))
    row += (f"ROW_TEXELS {instance_texels(static=static, joints=joints)}",)
    if joints:
        row += (f"FIRST_JOINT_TEXEL {INSTANCE.texels}", f"JOINT_TEXELS {JOINT_TEXELS}")
    return row + VIEW.defines()


def appearance_defines() -> tuple[str, ...]:
    """The APPEARANCE_* #define lines of the per-world appearance rows (variants of the effect only)."""
    return APPEARANCE.defines()
