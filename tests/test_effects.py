"""Effects only on demand: shader variants contain exactly the declared effects, and each
effect renders its documented formula.

Camera frame: +Y forward, +Z up, X right. A box face seen head-on from a camera at the
origin looking +Y is its -Y face (normal (0, -1, 0)).
"""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import torch

import marl_render as mr
from marl_render import shaders

warnings.filterwarnings("ignore", message="The given NumPy array is not writable")

F64 = torch.float64
IDENTITY = torch.tensor([1.0, 0.0, 0.0, 0.0])


def ones(*shape) -> torch.Tensor:
    return torch.ones(*shape, dtype=torch.bool)


def to_byte(value) -> torch.Tensor:
    return torch.round(torch.as_tensor(value, dtype=F64).clamp(0, 1) * 255)


def background_rgb(scene: mr.Scene) -> torch.Tensor:
    return to_byte(scene.background[:3]).to(torch.uint8)


# ----------------------------------------------------------------------------- preprocessing
def preprocess(text: str) -> str:
    """The active lines of GLSL after #define/#ifdef/#ifndef/#if defined()/#elif/#else/#endif.

    Just enough of the C preprocessor for our shaders; unknown #if expressions fail loudly.
    """
    defined: set[str] = set()
    stack: list[list[bool]] = []  # [this branch active, some branch taken, parent active]
    out = []

    def active() -> bool:
        return all(frame[0] for frame in stack)

    def evaluate(expression: str) -> bool:
        expr = re.sub(r"defined\s*\(\s*(\w+)\s*\)", lambda m: str(m.group(1) in defined), expression)
        expr = re.sub(r"defined\s+(\w+)", lambda m: str(m.group(1) in defined), expr)
        expr = expr.replace("||", " or ").replace("&&", " and ")
        expr = re.sub(r"!(?!=)", " not ", expr)
        words = set(re.findall(r"\w+", expr))
        if not re.fullmatch(r"[\sA-Za-z()]*", expr) or words - {"True", "False", "and", "or", "not"}:
            raise AssertionError(f"test preprocessor cannot evaluate #if {expression!r}")
        return bool(eval(expr))  # noqa: S307 - only True/False/and/or/not left

    for line in text.splitlines():
        stripped = line.strip()
        directive = re.match(r"#\s*(\w+)\s*(.*)", stripped)
        if directive:
            name, rest = directive.group(1), directive.group(2).split("//")[0].strip()
            if name in ("ifdef", "ifndef", "if"):
                value = ((rest in defined) if name == "ifdef" else (rest not in defined) if name == "ifndef"
                         else evaluate(rest))
                stack.append([value, value])
                continue
            if name == "elif":
                frame = stack[-1]
                frame[0] = not frame[1] and evaluate(rest)
                frame[1] = frame[1] or frame[0]
                continue
            if name == "else":
                frame = stack[-1]
                frame[0] = not frame[1]
                frame[1] = True
                continue
            if name == "endif":
                stack.pop()
                continue
            if name == "define" and active():
                defined.add(rest.split()[0])
        if active():
            out.append(line)
    assert not stack, "unbalanced #if/#endif"
    return "\n".join(out)


def test_test_preprocessor_itself():
    text = "#define A\n#ifdef A\na\n#else\nnot_a\n#endif\n#if defined(B) || defined(A)\nab\n#endif\n" \
           "#ifndef B\nno_b\n#elif defined(A)\nx\n#endif\n#if defined(A) && defined(B)\nboth\n#endif\n"
    active = preprocess(text).split("\n")
    assert [line for line in active if not line.startswith("#")] == ["a", "ab", "no_b"]


# Identifiers that only the code of one effect uses, per stage.
EFFECT_MARKERS = {
    "fog": {"frag": ["fog_density", "fog_color", "exp("]},
    "lighting": {"frag": ["light_direction", "light_color", "ambient_color", "v_normal"],
                 "vert": ["v_normal", "vertex_normal / "]},
    "texture": {"frag": ["p3d_Texture0", "v_uv"], "vert": ["p3d_MultiTexCoord0", "v_uv"]},
    "depth": {"frag": ["out_depth"]},
    "segmentation": {"frag": ["out_segment", "v_segment"], "vert": ["v_segment", "segment_base +"]},
    "log_depth": {"frag": ["gl_FragDepth", "v_near_far", "log2"], "vert": ["v_near_far"]},
    "shadows": {"frag": ["shadow_atlas", "light_visibility", "v_light", "texelFetch"], "vert": ["v_light", "lights"]},
    "appearance": {"vert": ["samplerBuffer appearance", "APPEARANCE_TRANSFORM_A", "int role"]},
}


def active_code(stage: str, effects, *, static=False, textured=True) -> str:
    defines = shaders.defines_for(frozenset(effects), static=static, textured=textured)
    return preprocess(shaders.variant_source(stage, defines))


@pytest.mark.parametrize("effect", sorted(EFFECT_MARKERS))
@pytest.mark.parametrize("static", [False, True])
def test_variant_contains_an_effects_code_only_when_declared(effect, static):
    others = set(shaders.EFFECTS) - {effect}
    for stage, markers in EFFECT_MARKERS[effect].items():
        without_all = active_code(stage, (), static=static)
        without = active_code(stage, others, static=static)  # every other effect on
        with_it = active_code(stage, {effect}, static=static)
        for marker in markers:
            assert marker not in without_all, (stage, marker)
            assert marker not in without, (stage, marker)
            assert marker in with_it, (stage, marker)


def test_bare_variant_only_has_the_colour_path():
    """No effects: the fragment shader writes the flat instance colour and nothing else."""
    frag = active_code("frag", ())
    body = frag[frag.index("void main()"):]
    assert "texture(" not in body and "mix(" not in body and "gl_FragDepth" not in body
    assert "out_color" in body and "v_color" in body
    # No stray outputs or inputs from other effects.
    assert re.findall(r"^\s*(?:flat\s+)?in\s+\w+\s+(\w+)", frag, re.M) == ["v_color"]
    vert = active_code("vert", ())
    assert re.findall(r"^\s*(?:flat\s+)?out\s+\w+\s+(\w+)", vert, re.M) == ["v_color"]


@pytest.mark.parametrize("static", [False, True])
def test_surface_patterns_only_for_groups_with_floors_or_walls_under_the_appearance_effect(static):
    def code(stage, effects, surface):
        defines = shaders.defines_for(frozenset(effects), static=static, textured=False, surface=surface,
                                      role=0 if static else 2)
        return preprocess(shaders.variant_source(stage, defines))

    everything = set(shaders.EFFECTS)
    assert "surface_pattern" in code("frag", {"appearance"}, True)
    assert "v_surface" in code("vert", {"appearance"}, True)
    for effects, surface in ((everything, False), (everything - {"appearance"}, True)):
        assert "surface_pattern" not in code("frag", effects, surface)
        assert "v_surface" not in code("vert", effects, surface)
    lit = code("frag", {"appearance", "lighting"}, False)  # smooth meshes take the world's light from the vertex
    assert "v_look_light_direction" in lit and "uniform vec3 light_direction" not in lit


def test_texture_code_only_for_groups_that_have_a_texture():
    assert "p3d_Texture0" not in active_code("frag", {"texture"}, textured=False)
    assert "p3d_Texture0" in active_code("frag", {"texture"}, textured=True)
    assert "p3d_Texture0" not in active_code("frag", (), textured=True)


@pytest.mark.parametrize("effects", [(), ("lighting",), ("fog", "depth"), ("texture", "segmentation", "log_depth"),
                                     tuple(shaders.EFFECTS)])
def test_defines_for_is_exactly_the_declared_effects(effects):
    for static in (False, True):
        for textured in (False, True):
            defines = shaders.defines_for(frozenset(effects), static=static, textured=textured)
            names = {d.split()[0] for d in defines}
            effect_names = names & set(shaders.EFFECT_DEFINES.values())
            expected = {shaders.EFFECT_DEFINES[e] for e in effects if e != "texture" or textured}
            assert effect_names == expected
            assert ("STATIC_GROUP" in names) == static
            assert defines == tuple(sorted(defines))  # canonical: one cached variant per set


def test_renderer_compiles_variants_with_exactly_the_scenes_effects(monkeypatch):
    seen = []
    original = shaders.compiled

    def recording(defines):
        seen.append(defines)
        return original(defines)

    monkeypatch.setattr(shaders, "compiled", recording)
    checker = np.zeros((4, 4, 3), np.uint8)
    for effects in [(), ("fog",), ("lighting", "texture", "depth")]:
        seen.clear()
        scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=effects)
        scene.add_static("floor", "plane", position=[[0, 0, 0]])
        scene.add_group("plain", "box", capacity=1)
        scene.add_group("textured", "box", capacity=1, texture=checker)
        r = mr.BatchRenderer(scene)
        r.close()
        declared = {shaders.EFFECT_DEFINES[e] for e in effects}
        assert len(seen) == 3
        floor, plain, textured = ({d.split()[0] for d in defines} for defines in seen)
        for names, has_texture in ((floor, False), (plain, False), (textured, True)):
            wanted = declared - ({"EFFECT_TEXTURE"} if not has_texture else set())
            assert names & set(shaders.EFFECT_DEFINES.values()) == wanted, (effects, names)
        assert "STATIC_GROUP" in floor and "STATIC_GROUP" not in plain


def test_aux_outputs_only_on_demand():
    cases = [((), False, False), (("depth",), True, False), (("segmentation",), False, True),
             (("depth", "segmentation"), True, True)]
    for effects, has_depth, has_segmentation in cases:
        scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=8, effects=effects)
        scene.add_group("boxes", "box", capacity=1)
        r = mr.BatchRenderer(scene)
        frame = r.render()
        r.close()
        assert (frame.depth is not None) == has_depth
        assert (frame.segmentation is not None) == has_segmentation


def test_unknown_effect_is_rejected_naming_effects():
    with pytest.raises(ValueError, match=r"effects.*'bloom'"):
        mr.Scene(num_worlds=1, agents_per_world=1, effects=("lighting", "bloom"))
    with pytest.raises(TypeError, match="effects"):
        mr.Scene(num_worlds=1, agents_per_world=1, effects="lighting")


# ----------------------------------------------------------------------------- rendered formulas
def one_box_scene(effects, views, *, color, lighting=None, fog=None, res=(32, 32)):
    """A unit box at the origin, cameras from `views` (eye positions) looking at it."""
    A = len(views)
    kwargs = {k: v for k, v in (("lighting", lighting), ("fog", fog)) if v is not None}
    scene = mr.Scene(num_worlds=1, agents_per_world=A, resolution=res, effects=effects, **kwargs)
    scene.add_group("box", "box", capacity=1)
    r = mr.BatchRenderer(scene)
    r.update("box", position=torch.zeros(1, 1, 3, dtype=F64), color=torch.tensor([[color]]), active=ones(1, 1))
    r.set_cameras(position=torch.tensor([views], dtype=F64), look_at=torch.zeros(1, A, 3, dtype=F64))
    frame = r.render()
    r.close()
    return scene, frame


FRONT_LEFT_ABOVE = [-1.6, -2.4, 2.0]  # sees faces -X, -Y, +Z
BACK_RIGHT_ABOVE = [2.0, 2.4, 1.6]  # sees faces +X, +Y, +Z
FACE_NORMALS = {"-X": (-1, 0, 0), "-Y": (0, -1, 0), "+Z": (0, 0, 1), "+X": (1, 0, 0), "+Y": (0, 1, 0)}
VISIBLE = [("-X", "-Y", "+Z"), ("+X", "+Y", "+Z")]
# Components chosen so that colour * 255 is not close to a rounding boundary.
COLOR = [0.8, 0.25, 0.65]


def test_lighting_off_gives_exact_flat_colours():
    scene, frame = one_box_scene((), [FRONT_LEFT_ABOVE, BACK_RIGHT_ABOVE], color=COLOR)
    expected = to_byte(COLOR).to(torch.uint8)
    assert expected.tolist() == [204, 64, 166]
    rgb = frame.rgb[0]
    box = (rgb != background_rgb(scene)).any(-1)
    assert (box.sum(dim=(1, 2)) > 30).all()
    assert (rgb[box] == expected).all(), rgb[box].unique(dim=0).tolist()  # every box pixel, every face


def test_lighting_on_matches_lambert_per_face():
    """colour * (ambient + light * max(0, n . -direction)) per face, within 1 unit, per channel
    (distinct light/ambient channels catch swizzles); faces turned away get ambient only."""
    lighting = mr.Lighting(direction=(-0.3, 0.4, -1.0), color=(0.7, 0.5, 0.3), ambient=(0.2, 0.3, 0.1))
    scene, frame = one_box_scene(("lighting",), [FRONT_LEFT_ABOVE, BACK_RIGHT_ABOVE], color=COLOR, lighting=lighting)
    to_light = -torch.tensor(lighting.direction, dtype=F64)
    to_light = to_light / to_light.norm()

    def shade(face):
        lambert = max(0.0, float(torch.tensor(FACE_NORMALS[face], dtype=F64) @ to_light))
        return to_byte(torch.tensor(COLOR, dtype=F64) * (torch.tensor(lighting.ambient, dtype=F64)
                                                          + torch.tensor(lighting.color, dtype=F64) * lambert))

    ambient_only = to_byte(torch.tensor(COLOR, dtype=F64) * torch.tensor(lighting.ambient, dtype=F64)).tolist()
    assert shade("-X").tolist() == shade("+Y").tolist() == ambient_only  # turned away from the light
    assert len({tuple(shade(face).tolist()) for face in FACE_NORMALS}) == 4  # -X and +Y alike, rest distinct
    background = background_rgb(scene)
    for view, faces in enumerate(VISIBLE):
        rgb = frame.rgb[0, view]
        pixels = rgb[(rgb != background).any(-1)].to(F64)
        expected = torch.stack([shade(face) for face in faces])  # [3 faces, 3]
        distance = (pixels[:, None, :] - expected[None]).abs().amax(-1)  # [pixels, faces]
        assert (distance.amin(1) <= 1).all(), pixels[distance.amin(1) > 1].unique(dim=0).tolist()
        for k, face in enumerate(faces):
            assert (distance[:, k] <= 1).sum() >= 10, f"view {view}: face {face} {expected[k].tolist()} not seen"


def test_fog_follows_the_exponential_formula_and_grows_with_distance():
    """mix(fog, colour, exp(-density * depth)) per pixel (depth read from the depth output),
    within 1 unit; the far box is closer to the fog colour than the near one."""
    fog = mr.Fog(color=(1.0, 0.0, 0.5), density=0.1)
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=(24, 32), effects=("fog", "depth"), fog=fog)
    scene.add_group("boxes", "box", capacity=2)
    r = mr.BatchRenderer(scene)
    color = [0.0, 1.0, 0.2]  # full contrast with the fog colour: 1 unit = 1/255 of exp(...)
    r.update("boxes", position=torch.tensor([[[-0.8, 3.0, 0.0], [3.0, 13.0, 0.0]]], dtype=F64),
             scale=torch.tensor([[[1.0, 1.0, 1.0], [3.0, 3.0, 3.0]]]),
             rotation=mr.quat_from_yaw_pitch_roll(torch.tensor([[0.0, 0.6]])),
             color=torch.tensor([[color, color]]), active=ones(1, 2))
    r.set_cameras(position=torch.zeros(1, 1, 3), rotation=IDENTITY.expand(1, 1, 4))
    frame = r.render()
    r.close()
    rgb, depth = frame.rgb[0, 0].to(F64), frame.depth[0, 0].to(F64)
    drawn = torch.isfinite(depth)
    assert drawn.sum() > 30
    keep = torch.exp(-fog.density * depth[drawn])[:, None]
    expected = to_byte(torch.tensor(fog.color, dtype=F64) * (1 - keep) + torch.tensor(color, dtype=F64) * keep)
    assert ((rgb[drawn] - expected).abs() <= 1).all()
    fog_byte = to_byte(fog.color)
    near, far = drawn & (depth < 5), drawn & (depth > 9)
    assert near.sum() > 10 and far.sum() > 10
    near_gap = (rgb[near] - fog_byte).abs().sum(-1).mean()
    far_gap = (rgb[far] - fog_byte).abs().sum(-1).mean()
    assert far_gap < 0.5 * near_gap
    # Without the fog effect the same colour is drawn flat at every distance.
    assert (background_rgb(scene) != to_byte(color).to(torch.uint8)).any()


def checker_quadrants() -> tuple[np.ndarray, list]:
    quadrant_colors = [[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0]]  # TL, TR, BL, BR
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[:4, :4], tex[:4, 4:], tex[4:, :4], tex[4:, 4:] = quadrant_colors
    return tex, quadrant_colors


@pytest.mark.parametrize("declared", [True, False])
def test_texture_shows_the_checker_colours_only_when_declared(declared):
    """A box textured with an 8x8 uint8 image of four 4x4 blocks, seen head-on: with the
    texture effect each block's colour shows, upright (image row 0 at the top, column 0 at
    the left of the -Y face); without it the face is the flat instance colour."""
    tex, quadrant_colors = checker_quadrants()
    scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=(32, 32),
                     effects=("texture",) if declared else ())
    scene.add_group("boxes", "box", capacity=1, texture=tex)
    r = mr.BatchRenderer(scene)
    r.set_cameras(position=torch.zeros(1, 1, 3), rotation=IDENTITY.expand(1, 1, 4))
    r.update("boxes", position=torch.tensor([[[0.0, 2.0, 0.0]]], dtype=F64), color=torch.ones(1, 1, 3),
             active=ones(1, 1))
    rgb = r.render().rgb[0, 0].int()
    r.close()
    face = (rgb != background_rgb(scene).int()).any(-1)
    rows, cols = face.nonzero().unbind(1)
    top, bottom, left, right = rows.min(), rows.max(), cols.min(), cols.max()
    assert bottom - top >= 10 and right - left >= 10
    quarter_r, quarter_c = (bottom - top) // 4, (right - left) // 4
    samples = [rgb[top + quarter_r, left + quarter_c], rgb[top + quarter_r, right - quarter_c],
               rgb[bottom - quarter_r, left + quarter_c], rgb[bottom - quarter_r, right - quarter_c]]
    if declared:
        for sample, wanted in zip(samples, quadrant_colors, strict=True):
            assert (sample - torch.tensor(wanted)).abs().max() <= 1, (sample.tolist(), wanted)
        for wanted in quadrant_colors:  # each block covers a patch of pixels, not a lone one
            assert ((rgb - torch.tensor(wanted)).abs().amax(-1) <= 1).sum() >= 9
    else:
        assert (rgb[face] == 255).all()
