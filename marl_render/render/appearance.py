"""Per-world looks: what the "appearance" effect draws differently in each world, and the sampler of
train and held-out appearances.

A scene that declares the "appearance" effect gets one row per world (row_layouts.APPEARANCE) that the
shaders read in the same instanced pass as everything else:

- the directional light (direction, colour) and the ambient light;
- the sky: the world's background colour (a quad per view drawn behind everything, shaders/sky.*);
- the floor and wall colours and their procedural patterns (PATTERNS, computed in the fragment
  shader from the world position: no texture is uploaded), for instances whose role is "floor" or
  "wall" (``Scene.add_static(..., role=)``, ``Scene.add_group(..., role=)``);
- a colour transform of every other instance (agents, objects): a rotation of hue by the same
  angle for the whole world, and a scaling of saturation and value. Objects keep their hue order
  and the hue distances between them, so teams stay apart within a world; the default jitter
  (+-0.025 turns, 9 degrees) keeps each team colour within a band around its own hue.

``BatchRenderer.set_appearance(...)`` sets them ([W, ...] per argument; until then a world shows
the scene's lighting and background and its instances' own colours). Camera jitter is on the camera
side: ``set_cameras(fov_y=, mount_offset=, mount_pitch=)``.

``Appearance`` draws them from per-world ids (a pure function through marl_render.keyed_random):

    look = Appearance(split="train")            # or "heldout"
    params = look.sample(ids)                   # ids [W] int64 -> AppearanceParams of [W, ...] tensors
    renderer.set_appearance(**params.renderer_kwargs())

Splits: the hue circle is cut into HUE_SECTORS sectors; the sky, floor and wall hues of "train"
come from TRAIN_SECTORS and those of "heldout" from HELDOUT_SECTORS, which share none; floor and
wall patterns of "train" are TRAIN_PATTERNS (plain, checker, stripes) and those of "heldout"
HELDOUT_PATTERNS (dots, bricks). So no held-out sky, floor or wall has a hue sector or pattern that
appears in training. Light, object jitter and camera jitter are drawn alike in both splits.
"""
from __future__ import annotations

import dataclasses
import math

import torch

from ..util.keyed_random import KeyedRandom, as_keys, derive_keys
from ..util.threads import one_thread
from ..util.validation import as_tensor, check_finite, check_host, check_range, describe
from . import row_layouts

PATTERNS = ("plain", "checker", "stripes", "dots", "bricks")  # shaders/batch.frag's surface_pattern
TRAIN_PATTERNS = (0, 1, 2)
HELDOUT_PATTERNS = (3, 4)
# Per pattern: (cells along u per cell along v, shift along u per row, line threshold, weights of
# the terms a, b, ab: a and b are 1 past the threshold along u and along v within a cell) (cells are
# 1 / pattern_scale metres along v). The rows hold the factors they leave (pattern_factors), which
# batch.frag's surface_pattern picks from.
PATTERN_TERMS = torch.tensor([
    [1.0, 0.0, 0.5, 0.0, 0.0, 0.0],  # plain
    [1.0, 0.0, 0.5, 1.0, 1.0, -2.0],  # checker: a xor b
    [1.0, 0.0, 0.5, 1.0, 0.0, 0.0],  # stripes across u
    [1.0, 0.0, 0.65, 0.0, 0.0, 1.0],  # dots: a and b past 0.65, a square in each cell's corner
    [0.5, 0.5, 0.88, 1.0, 1.0, -1.0],  # bricks: mortar lines (a or b), cells twice as long, rows shifted
], dtype=torch.float64)
HUE_SECTORS = 12  # 30 degrees each
HELDOUT_SECTORS = (1, 4, 7, 10)
TRAIN_SECTORS = tuple(s for s in range(HUE_SECTORS) if s not in HELDOUT_SECTORS)
SPLITS = ("train", "heldout")

GREY = torch.full((3, 3), 1.0 / 3.0, dtype=torch.float64)  # projection onto the grey axis

# The sampler's ranges. Surfaces are (sky, floor, wall): saturation and value of their HSV colours,
# floors darker than walls so that geometry reads at a glance.
SURFACE_SATURATION = ((0.15, 0.1, 0.1), (0.5, 0.45, 0.45))
SURFACE_VALUE = ((0.65, 0.25, 0.5), (0.95, 0.5, 0.8))
LIGHT_ELEVATION = (math.radians(35.0), math.radians(75.0))  # above the horizon
LIGHT_INTENSITY = ((0.55, 0.25), (0.9, 0.45))  # (directional, ambient)
TINT_SATURATION = torch.tensor([0.25, 0.15], dtype=torch.float64)  # of the (directional, ambient) light's colour
PATTERN_SCALE = ((1.5, 4.0), (4.0, 8.0))  # cells per metre: lows (floor, wall), highs (floor, wall)
PATTERN_CONTRAST = (0.15, 0.35)

# The sampler's one draw of uniforms per world (keyed_random: element i of stream "look"), taken
# apart in this order: name -> how many.
COLUMNS = {"sector": 3, "within_sector": 3, "saturation": 3, "value": 3, "light": 2, "intensity": 2, "tint_hue": 2,
           "tint_saturation": 2, "pattern": 2, "pattern_scale": 2, "pattern_contrast": 2, "jitter": 6}
DRAWS = sum(COLUMNS.values())


def pattern_factors(weights: torch.Tensor) -> torch.Tensor:
    """[..., 3] float32: the factors a pattern leaves of a surface's colour past its line threshold
    along u only, v only and both, 1 - (weights . (a, b, ab)) for the weights [..., 3] of its terms a,
    b and ab. In float32, as batch.frag once computed them per fragment: each partial sum of the
    weights (multiples of one contrast by 0, +-1 or -2) is exact, so the factors are bit for bit
    what that formula gave."""
    a, b, ab = weights.to(torch.float32).unbind(-1)
    return torch.stack((1 - a, 1 - b, 1 - (a + b + ab)), -1)


def color_transform_terms(hue_shift: torch.Tensor, saturation: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """[W, 3] (a, b, c) float64 of the colour transform rgb' = a rgb + b mean(rgb) + c ((1, 1, 1) x rgb):
    hue rotated by hue_shift turns about the grey axis, the distance from it scaled by saturation,
    everything scaled by value (all [W]). It is the matrix value (P + saturation (cos t (I - P) +
    sin t [u]x)), P the projection onto the grey axis u = (1, 1, 1) / sqrt 3, written out."""
    angle = 2 * math.pi * hue_shift.to(torch.float64)
    chroma = saturation.to(torch.float64) * value.to(torch.float64)
    a = chroma * torch.cos(angle)
    return torch.stack((a, value.to(torch.float64) - a, chroma * torch.sin(angle) / math.sqrt(3)), -1)


def color_transform(hue_shift: torch.Tensor, saturation: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """[W, 3, 3] float64 matrices M with rgb' = M rgb (the transform of color_transform_terms)."""
    a, b, c = color_transform_terms(hue_shift, saturation, value).unbind(-1)
    cross = torch.tensor([[0.0, -1.0, 1.0], [1.0, 0.0, -1.0], [-1.0, 1.0, 0.0]], dtype=torch.float64)
    return (a[:, None, None] * torch.eye(3, dtype=torch.float64) + b[:, None, None] * GREY
            + c[:, None, None] * cross)


def hsv_to_rgb(hue: torch.Tensor, saturation: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """[..., 3] RGB of HSV colours (hue in turns, saturation and value in [0, 1]), as matplotlib's."""
    h6 = torch.remainder(hue, 1.0) * 6
    k = torch.remainder(torch.tensor([5.0, 3.0, 1.0], dtype=h6.dtype) + h6[..., None], 6)
    return value[..., None] - (value * saturation)[..., None] * torch.clamp(torch.minimum(k, 4 - k), 0, 1)


# ---------------------------------------------------------------------- the renderer's rows
# set_appearance's arguments: (shape per world, kind, low, high); kind "float" or "int".
ARGUMENTS = {
    "light_direction": ((3,), "float", None, None),
    "light_color": ((3,), "float", 0.0, None),
    "ambient": ((3,), "float", 0.0, None),
    "sky": ((3,), "float", 0.0, 1.0),
    "floor": ((3,), "float", 0.0, 1.0),
    "wall": ((3,), "float", 0.0, 1.0),
    "floor_pattern": ((), "int", 0, len(PATTERNS) - 1),
    "wall_pattern": ((), "int", 0, len(PATTERNS) - 1),
    "pattern_scale": ((2,), "float", 1e-3, 1e3),
    "pattern_contrast": ((2,), "float", 0.0, 1.0),
    "hue_shift": ((), "float", -1e3, 1e3),
    "saturation": ((), "float", 0.0, 1e3),
    "value": ((), "float", 0.0, 1e3),
}


class AppearanceRows:
    """Every world's APPEARANCE row (float32 [W, texels, 4]) and the arguments it was made from;
    kept by the FramePacker of a scene with the "appearance" effect. Until set, a world shows the
    scene's lighting and background, floors and walls keep their own colours, nothing is patterned
    and the colour transform is the identity."""

    def __init__(self, scene):
        W = scene.num_worlds
        direction = torch.tensor(scene.lighting.direction, dtype=torch.float64)
        self.values = {
            "light_direction": direction.expand(W, 3).clone(),
            "light_color": torch.tensor(scene.lighting.color, dtype=torch.float64).expand(W, 3).clone(),
            "ambient": torch.tensor(scene.lighting.ambient, dtype=torch.float64).expand(W, 3).clone(),
            "sky": torch.tensor(scene.background[:3], dtype=torch.float64).expand(W, 3).clone(),
            "floor": None, "wall": None,  # None: the instances' own colours
            "floor_pattern": torch.zeros(W, dtype=torch.int64), "wall_pattern": torch.zeros(W, dtype=torch.int64),
            "pattern_scale": torch.ones(W, 2, dtype=torch.float64),
            "pattern_contrast": torch.zeros(W, 2, dtype=torch.float64),
            "hue_shift": torch.zeros(W, dtype=torch.float64), "saturation": torch.ones(W, dtype=torch.float64),
            "value": torch.ones(W, dtype=torch.float64),
        }
        self.num_worlds = W
        self.rows = torch.zeros(W, row_layouts.APPEARANCE.texels, 4)
        self._write()
        self.dirty = True  # not yet packed
        self.version = 0  # counts the changes (what a renderer's sky images follow)

    def set(self, check=None, **kwargs) -> None:
        """Validate every given argument ([W, ...] or broadcastable to it), then store them all;
        check(staged) may refuse the checked values first (a renderer's shadow pass does)."""
        unknown = sorted(set(kwargs) - set(ARGUMENTS))
        if unknown:
            raise TypeError(f"set_appearance got unknown argument(s) {unknown}; accepted: {sorted(ARGUMENTS)}")
        staged = {name: self._checked(name, value) for name, value in kwargs.items() if value is not None}
        if check is not None:
            check(staged)
        self.values.update(staged)
        if staged:
            self._write()
            self.dirty = True
            self.version += 1

    def plain_surfaces(self) -> torch.Tensor:
        """[W, 2] bool: whether each world's floor and wall pattern leaves every factor 1 (plain, or no
        contrast), so that a variant without patterns draws them to the same pixels."""
        field = row_layouts.APPEARANCE.fields
        texels = [field[f"{surface}_pattern"].texel + 1 for surface in ("floor", "wall")]
        factors = self.rows[:, texels, :3]  # [W, 2, 3]
        return (factors == 1).all(-1)

    def light_directions(self) -> torch.Tensor:
        """[W, 3] float64 unit directions of each world's light (pointing from it)."""
        direction = self.values["light_direction"]
        return direction / direction.norm(dim=-1, keepdim=True)

    def _checked(self, name: str, value) -> torch.Tensor:
        shape, kind, low, high = ARGUMENTS[name]
        want = [self.num_worlds, *shape]
        tensor = as_tensor(name, value, dtype_kind=kind)
        check_host(name, tensor)
        try:
            tensor = torch.broadcast_to(tensor, want)
        except RuntimeError:
            raise ValueError(f"{name} must have shape {want} (or broadcast to it), got {list(tensor.shape)}") from None
        if kind == "float":
            tensor = tensor.to(torch.float64)
            check_finite(name, tensor)
        else:
            tensor = tensor.to(torch.int64)
        check_range(name, tensor, low, high)
        if name == "light_direction":
            length = tensor.norm(dim=-1)
            if bool(((length < 1e-30) | (length > 1e30)).any()):
                raise ValueError(f"light_direction must be non-zero vectors of length in [1e-30, 1e30], got "
                                 f"lengths in [{length.min().item():.3g}, {length.max().item():.3g}]")
        return tensor.clone()

    def _write(self) -> None:
        rows, v = self.rows, self.values
        field = row_layouts.APPEARANCE.fields
        rows.zero_()

        def put(name, values):
            texel, lanes = row_layouts.APPEARANCE[name]
            rows[:, texel, lanes] = values.to(torch.float32)

        put("light_direction", self.light_directions())
        for name in ("light_color", "ambient", "sky"):
            put(name, v[name])
        for index, surface in enumerate(("floor", "wall")):
            if v[surface] is not None:  # lane w = 1: the shader replaces the instance's colour
                put(surface, torch.cat((v[surface], torch.ones(self.num_worlds, 1, dtype=torch.float64)), -1))
            terms = PATTERN_TERMS[v[f"{surface}_pattern"]]  # [W, 6]
            scale = v["pattern_scale"][:, index]
            first = field[f"{surface}_pattern"].texel
            rows[:, first] = torch.stack((scale * terms[:, 0], scale, terms[:, 1], terms[:, 2]), -1).to(torch.float32)
            rows[:, first + 1, :3] = pattern_factors(terms[:, 3:] * v["pattern_contrast"][:, index:index + 1])
        terms = color_transform_terms(v["hue_shift"], v["saturation"], v["value"])
        for index, name in enumerate(("transform_a", "transform_b", "transform_c")):
            put(name, terms[:, index])


# ---------------------------------------------------------------------- the sampler
@dataclasses.dataclass(frozen=True)
class AppearanceParams:
    """Per-world appearance drawn by Appearance.sample: [W, ...] tensors (float64 unless said)."""

    light_direction: torch.Tensor  # [W, 3] unit, pointing from the light
    light_color: torch.Tensor  # [W, 3]
    ambient: torch.Tensor  # [W, 3]
    sky: torch.Tensor  # [W, 3] RGB in [0, 1]
    floor: torch.Tensor  # [W, 3]
    wall: torch.Tensor  # [W, 3]
    floor_pattern: torch.Tensor  # [W] int64 index into PATTERNS
    wall_pattern: torch.Tensor  # [W] int64
    pattern_scale: torch.Tensor  # [W, 2] cells per metre (floor, wall)
    pattern_contrast: torch.Tensor  # [W, 2] in [0, 1]
    hue_shift: torch.Tensor  # [W] turns, of every instance that is not a floor or wall
    saturation: torch.Tensor  # [W] scale
    value: torch.Tensor  # [W] scale
    sky_hue: torch.Tensor  # [W] turns: the hues the splits are made of
    floor_hue: torch.Tensor  # [W]
    wall_hue: torch.Tensor  # [W]
    fov_scale: torch.Tensor  # [W] factor of the cameras' fov_y
    camera_height: torch.Tensor  # [W] metres added to the cameras' height
    camera_pitch: torch.Tensor  # [W] radians added to the cameras' pitch (positive looks up)

    def renderer_kwargs(self) -> dict:
        """The keyword arguments of BatchRenderer.set_appearance (everything but the hues and cameras)."""
        return {name: getattr(self, name) for name in ARGUMENTS}


def _fraction(name: str, value, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= high:
        raise ValueError(f"{name} must be a number in [0, {high:g}], got {describe(value)}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class Appearance:
    """A distribution of per-world appearances and its split; see the module docstring.

    split: "train" or "heldout". textures: draw floor and wall patterns (else all plain). camera:
    jitter the agents' cameras (fov_y scaled by U(1 - fov_jitter, 1 + fov_jitter), height moved by
    U(-height_jitter, height_jitter) metres, pitch by U(-pitch_jitter, pitch_jitter) radians).
    hue_jitter (turns), saturation_jitter and value_jitter (fractions): the colour transform of
    everything but floors and walls."""

    split: str = "train"
    textures: bool = True
    camera: bool = True
    fov_jitter: float = 0.1
    height_jitter: float = 0.05
    pitch_jitter: float = math.radians(5.0)
    hue_jitter: float = 0.025
    saturation_jitter: float = 0.15
    value_jitter: float = 0.15

    def __post_init__(self):
        if not isinstance(self.split, str) or self.split not in SPLITS:
            raise ValueError(f"split must be one of {list(SPLITS)}, got {describe(self.split)}")
        for name in ("textures", "camera"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be a bool, got {describe(getattr(self, name))}")
        for name, high in (("fov_jitter", 0.5), ("height_jitter", 10.0), ("pitch_jitter", math.pi / 4),
                           ("hue_jitter", 0.5), ("saturation_jitter", 1.0), ("value_jitter", 1.0)):
            object.__setattr__(self, name, _fraction(name, getattr(self, name), high))

    @one_thread  # small tensors: torch's thread pool would cost more than the work (threads.py)
    def sample(self, ids) -> AppearanceParams:
        """The appearance of each world of ids [W] (int64): a pure function of (id, this Appearance),
        on the CPU (where the renderer packs). One draw of DRAWS uniforms per world, taken apart by
        rows of its transpose: every quantity below is [k, W] and contiguous (torch runs elementwise
        ops on strided columns far slower, by milliseconds with two threads)."""
        ids = as_keys(ids, "ids").cpu()
        u = KeyedRandom(derive_keys(ids, "appearance")).uniform("look", (DRAWS,), dtype=torch.float64)
        draw = {name: rows for name, rows in zip(COLUMNS, u.T.contiguous().split(list(COLUMNS.values())),
                                                  strict=True)}
        train = self.split == "train"
        sectors = torch.tensor(TRAIN_SECTORS if train else HELDOUT_SECTORS, dtype=torch.float64)
        patterns = torch.tensor(TRAIN_PATTERNS if train else HELDOUT_PATTERNS)

        def between(values, low, high):  # values [k, W] in [0, 1) -> [low, high) (numbers or one per row)
            low, high = (torch.as_tensor(v, dtype=torch.float64).reshape(-1, 1) for v in (low, high))
            return low + values * (high - low)

        def pick(values, options):  # one of options per value in [0, 1)
            return options[(values * len(options)).long()]

        # Sky, floor and walls: a hue in one of the split's sectors, then a saturation and value.
        hues = (pick(draw["sector"], sectors) + draw["within_sector"]) / HUE_SECTORS  # [3, W]
        colors = hsv_to_rgb(hues, between(draw["saturation"], *SURFACE_SATURATION),
                            between(draw["value"], *SURFACE_VALUE))  # [3 surfaces, W, 3]
        azimuth, elevation = 2 * math.pi * draw["light"][0], between(draw["light"][1:], *LIGHT_ELEVATION)[0]
        direction = -torch.stack((torch.cos(elevation) * torch.cos(azimuth), torch.cos(elevation) * torch.sin(azimuth),
                                  torch.sin(elevation)), -1)
        intensity = between(draw["intensity"], *LIGHT_INTENSITY)  # [2, W]: the light's and the ambient's
        tints = hsv_to_rgb(draw["tint_hue"], between(draw["tint_saturation"], 0.0, TINT_SATURATION),
                           torch.ones_like(intensity))  # [2, W, 3]
        lights = intensity[..., None] * tints
        if self.textures:
            surface_patterns = pick(draw["pattern"], patterns)  # [2, W]
        else:
            surface_patterns = torch.zeros(2, len(ids), dtype=torch.int64)
        amounts = torch.tensor([self.hue_jitter, self.saturation_jitter, self.value_jitter, self.fov_jitter,
                                self.height_jitter, self.pitch_jitter], dtype=torch.float64)
        if not self.camera:
            amounts[3:] = 0.0
        jitter = (2 * draw["jitter"] - 1) * amounts[:, None]  # [6, W] in [-amount, amount)
        return AppearanceParams(
            light_direction=direction, light_color=lights[0], ambient=lights[1],
            sky=colors[0], floor=colors[1], wall=colors[2],
            floor_pattern=surface_patterns[0], wall_pattern=surface_patterns[1],
            pattern_scale=between(draw["pattern_scale"], *PATTERN_SCALE).T.contiguous(),
            pattern_contrast=between(draw["pattern_contrast"], *PATTERN_CONTRAST).T.contiguous(),
            hue_shift=jitter[0], saturation=1 + jitter[1], value=1 + jitter[2],
            sky_hue=hues[0], floor_hue=hues[1], wall_hue=hues[2],
            fov_scale=1 + jitter[3], camera_height=jitter[4], camera_pitch=jitter[5])
