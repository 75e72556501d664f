"""The appearance effect (marl_render/appearance.py, sky.py): each world's sky, light, floor and wall
looks and patterns, object colour transform and camera jitter, drawn in the one pass; the sampler's
train and held-out splits; and the env option appearance=.

Camera frame: +Y forward, +Z up. Pixels are compared exactly where the formula is exact (flat
colours, no lighting) and to the byte elsewhere.
"""
from __future__ import annotations

import colorsys
import json
import math
import subprocess
import sys
import warnings

import pytest
import torch

import marl_render as mr
from marl_render import appearance as looks
from marl_render.envs import make_env, make_parallel_env, make_sb3_env, make_torchrl_env, make_vec_env

warnings.filterwarnings("ignore", message="The given NumPy array is not writable")

F64 = torch.float64
IDENTITY = torch.tensor([1.0, 0.0, 0.0, 0.0])
UP = mr.quat_from_yaw_pitch_roll(torch.tensor(0.0), torch.tensor(math.pi / 2))  # looks straight up
DOWN = mr.quat_from_yaw_pitch_roll(torch.tensor(0.0), torch.tensor(-math.pi / 2))  # looks straight down


def to_byte(value) -> torch.Tensor:
    return torch.round(torch.as_tensor(value, dtype=F64).clamp(0, 1) * 255).to(torch.uint8)


def free_scene(worlds, agents=1, effects=("appearance",), resolution=8, **kwargs) -> mr.Scene:
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=resolution, effects=effects, **kwargs)
    scene.add_group("boxes", "box", capacity=1)  # never activated unless a test says so
    return scene


def look_from(renderer, position, rotation):
    W, A = renderer.scene.num_worlds, renderer.scene.agents_per_world
    renderer.set_cameras(position=torch.tensor(position, dtype=F64).expand(W, A, 3),
                         rotation=torch.as_tensor(rotation, dtype=torch.float32).expand(W, A, 4))


SKIES = torch.tensor([[0.9, 0.1, 0.2], [0.2, 0.7, 0.3], [0.25, 0.35, 0.95]], dtype=F64)


# ----------------------------------------------------------------------------- the sky
@pytest.mark.parametrize("passes", [1, 3])
def test_each_world_shows_its_own_sky_in_every_tile(passes):
    """Nothing in view: every pixel of world w is its sky colour, across framebuffers (passes)."""
    scene = free_scene(3, agents=2)
    max_size = 8 * 2 if passes == 3 else None  # two views per framebuffer: three of them
    with mr.BatchRenderer(scene, max_framebuffer_size=max_size) as r:
        assert r.layout.num_passes == passes
        look_from(r, [0, 0, 0], UP)
        r.set_appearance(sky=SKIES)
        rgb = r.render().rgb
        for w in range(3):
            assert (rgb[w] == to_byte(SKIES[w])).all(), (w, rgb[w].unique(dim=0 if rgb.ndim == 1 else -2))
        # One world's sky changes: only its tiles change (its rows are uploaded again).
        r.set_appearance(sky=torch.cat((SKIES[:1], torch.tensor([[0.0, 0.0, 0.0]], dtype=F64), SKIES[2:])))
        again = r.render().rgb
        assert (again[1] == 0).all()
        assert torch.equal(again[0], rgb[0]) and torch.equal(again[2], rgb[2])
        # The sky copied in for the next frame right after a read: what a box drew is gone once it leaves.
        for active in (True, False):
            r.update("boxes", position=torch.tensor([0.0, 0.0, 2.0], dtype=F64).expand(3, 1, 3),
                     active=torch.full((3, 1), active))
            boxed = r.render().rgb
            assert torch.equal(boxed, again) != active


def test_gray_output_and_aux_outputs_show_the_sky_as_background():
    scene = free_scene(2, effects=("appearance", "depth", "segmentation"))
    with mr.BatchRenderer(scene) as r, mr.BatchRenderer(free_scene(2), color="gray") as gray:
        for renderer in (r, gray):
            look_from(renderer, [0, 0, 0], UP)
            renderer.set_appearance(sky=SKIES[:2])
        frame, gray_frame = r.render(), gray.render()
    assert (frame.rgb[1] == to_byte(SKIES[1])).all()
    assert torch.isinf(frame.depth).all() and (frame.segmentation == 0).all()
    luma = to_byte(SKIES[:2] @ torch.tensor([0.299, 0.587, 0.114], dtype=F64))
    assert gray_frame.rgb.shape[-1] == 1
    assert (gray_frame.rgb[0] == luma[0]).all() and (gray_frame.rgb[1] == luma[1]).all()


def test_until_set_a_world_shows_the_scenes_background_and_lighting_bit_for_bit():
    """Declared but never set, the effect draws today's pixels: background, lighting, own colours."""
    def scene(effects):
        s = mr.Scene(num_worlds=2, agents_per_world=2, resolution=16, effects=effects)
        s.add_static("ground", "box", position=[[0, 0, -0.05], [2, 0, 0.2]], scale=[[8, 8, 0.1], [0.1, 4, 0.4]],
                     color=[[0.4, 0.45, 0.4], [0.6, 0.5, 0.4]], role=["floor", "wall"])
        s.add_group("agents", mr.capsule(0.2, 0.5, segments=8, rings=2), capacity=2)
        s.mount_cameras("agents", [0, 1], offset=(0, 0, 0.1))
        return s

    frames = []
    for effects in (("lighting",), ("lighting", "appearance")):
        with mr.BatchRenderer(scene(effects)) as r:
            position = torch.tensor([[[0.0, 0.0, 0.3], [0.3, 1.0, 0.3]]]).expand(2, 2, 3)
            yaw = torch.tensor([[-1.0, 0.5], [0.3, 2.0]])
            r.update("agents", position=position, rotation=mr.quat_from_yaw_pitch_roll(yaw),
                     color=torch.tensor([[0.9, 0.3, 0.25], [0.25, 0.55, 0.9]]).expand(2, 2, 3),
                     active=torch.ones(2, 2, dtype=torch.bool))
            frames.append(r.render().rgb)
    assert torch.equal(frames[0], frames[1])


# ----------------------------------------------------------------------------- surfaces and objects
def top_down_floor(worlds, role="floor"):
    scene = mr.Scene(num_worlds=worlds, agents_per_world=1, resolution=16, effects=("appearance",))
    scene.add_static("floor", "plane", position=[[0, 0, 0]], scale=[[20, 20, 1]], color=[[0.5, 0.5, 0.5]], role=role)
    scene.add_group("walls", "box", capacity=1, role="wall")
    r = mr.BatchRenderer(scene)
    look_from(r, [0.13, 0.07, 3.0], DOWN)
    return r


def test_floors_and_walls_take_their_worlds_colour():
    floors = torch.tensor([[0.2, 0.4, 0.6], [0.7, 0.3, 0.1]], dtype=F64)
    walls = torch.tensor([[0.9, 0.8, 0.1], [0.1, 0.2, 0.3]], dtype=F64)
    with top_down_floor(2) as r:
        r.update("walls", position=torch.tensor([[[0.13, 0.07, 1.0]]], dtype=F64).expand(2, 1, 3),
                 scale=torch.tensor([[[0.3, 0.3, 0.3]]]).expand(2, 1, 3), active=torch.ones(2, 1, dtype=torch.bool))
        own = r.render().rgb
        assert (own[:, 0, 0, 0] == to_byte([0.5] * 3)).all()  # not set yet: the instance's own colour
        r.set_appearance(floor=floors, wall=walls)
        rgb = r.render().rgb[:, 0]
    for w in range(2):
        assert (rgb[w, 0, 0] == to_byte(floors[w])).all() and (rgb[w, -1, -1] == to_byte(floors[w])).all()
        assert (rgb[w, 8, 8] == to_byte(walls[w])).all()  # the box right under the camera
        values = {tuple(v) for v in rgb[w].reshape(-1, 3).tolist()}
        assert values == {tuple(to_byte(floors[w]).tolist()), tuple(to_byte(walls[w]).tolist())}


def test_a_checker_darkens_every_other_cell_by_the_contrast():
    floor = torch.tensor([0.6, 0.4, 0.8], dtype=F64)
    with top_down_floor(3) as r:
        r.set_appearance(floor=floor, floor_pattern=torch.tensor([0, 1, 2]), pattern_scale=torch.tensor([2.0, 2.0]),
                         pattern_contrast=0.5)
        rgb = r.render().rgb[:, 0]
    plain, dark = tuple(to_byte(floor).tolist()), tuple(to_byte(floor * 0.5).tolist())
    assert {tuple(v) for v in rgb[0].reshape(-1, 3).tolist()} == {plain}
    for w in (1, 2):  # checker and stripes: the two shades, each on a good share of the view
        pixels = [tuple(v) for v in rgb[w].reshape(-1, 3).tolist()]
        assert set(pixels) == {plain, dark} and 0.25 < pixels.count(dark) / len(pixels) < 0.75
    assert not torch.equal(rgb[1], rgb[2])
    # Stripes run across x: a column of pixels is one shade, a row alternates.
    stripes = rgb[2].int().sum(-1)
    assert (stripes == stripes[:1]).all() and len(stripes[0].unique()) == 2


def test_plain_worlds_take_the_variant_without_patterns_and_keep_their_pixels(monkeypatch):
    """Floors and walls whose pattern leaves every factor 1 (plain, or no contrast) are drawn by the
    variant without patterns, after the patterned pairs of their pass: the same pixels as drawing every
    pair with the patterns."""
    scene = mr.Scene(num_worlds=4, agents_per_world=1, resolution=12, effects=("lighting", "appearance"))
    scene.add_static("floor", "plane", position=[[0, 0, 0]], scale=[[20, 20, 1]], role="floor")
    scene.add_static("walls", "box", position=[[0, 2, 0.5], [2, 0, 0.5]], scale=[[4, 0.2, 1], [0.2, 4, 1]], role="wall")
    looked = {"floor_pattern": torch.tensor([1, 0, 2, 3]), "wall_pattern": torch.tensor([0, 4, 1, 2]),
              "pattern_contrast": torch.tensor([[0.4, 0.4], [0.4, 0.4], [0.4, 0.4], [0.4, 0.0]]), "pattern_scale": 3.0}
    frames, nowhere_plain = [], lambda rows: torch.zeros(4, 2, dtype=torch.bool)
    for split in (True, False):
        if not split:  # every pair through the patterns, as before the split
            monkeypatch.setattr(looks.AppearanceRows, "plain_surfaces", nowhere_plain)
        with mr.BatchRenderer(scene) as r:
            look_from(r, [-1.0, -1.5, 1.0], mr.quat_from_yaw_pitch_roll(torch.tensor(-0.6), torch.tensor(-0.3)))
            r.set_appearance(**looked)
            frames.append(r.render().rgb)
            plain = [r.packer.groups[name].plain_counts for name in ("floor", "walls")]
        assert plain == ([[1], [2 * 2]] if split else [[0], [0]])  # floor: world 1; walls: worlds 0 and 3
    assert torch.equal(frames[0], frames[1])
    assert len({frames[0][w].numpy().tobytes() for w in range(4)}) == 4


def test_patterned_floors_drawn_last_still_win_the_exact_ties_they_won_first():
    """Patterned floors and walls are drawn after the other groups, so that the depth test skips what
    those hide before the pattern is shaded. Added first, a floor won exact depth ties, and still does:
    a red rug laid exactly over it in a later group stays hidden (also in the world without a pattern,
    drawn by the plain variant)."""
    frames = []
    for rug in (False, True):
        scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=8, effects=("appearance",))
        scene.add_static("floor", "plane", position=[[0, 0, 0]], scale=[[20, 20, 1]], role="floor")
        if rug:
            scene.add_static("rug", "plane", position=[[0, 0, 0]], scale=[[20, 20, 1]], color=[[1.0, 0.0, 0.0]])
        with mr.BatchRenderer(scene) as r:
            look_from(r, [0.13, 0.07, 3.0], DOWN)
            r.set_appearance(floor_pattern=torch.tensor([1, 0]), pattern_scale=2.0, pattern_contrast=0.5)
            frames.append(r.render().rgb)
    assert len(frames[0][0].reshape(-1, 3).unique(dim=0)) == 2  # the checker shows in world 0
    assert torch.equal(frames[0], frames[1])


def test_a_scene_without_surface_patterns_compiles_none_and_refuses_them(monkeypatch):
    compiled = []
    original = mr.shaders.compiled
    monkeypatch.setattr(mr.shaders, "compiled", lambda defines: compiled.append(defines) or original(defines))
    scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=8, effects=("appearance",), surface_patterns=False)
    scene.add_static("floor", "plane", position=[[0, 0, 0]], scale=[[20, 20, 1]], role="floor")
    with mr.BatchRenderer(scene) as r:
        assert not any("APPEARANCE_SURFACE" in defines for defines in compiled)
        with pytest.raises(ValueError, match=r"floor_pattern must be 0 \(plain\): the scene was built with "
                                             r"surface_patterns=False, got kinds \[0, 1\]"):
            r.set_appearance(floor_pattern=torch.tensor([0, 1]), floor=(0.1, 0.2, 0.3))
        assert r.packer.appearance.values["floor"] is None  # nothing was stored
        r.set_appearance(floor_pattern=0, floor=(0.1, 0.2, 0.3))
    with pytest.raises(TypeError, match="surface_patterns must be a bool"):
        mr.Scene(num_worlds=1, agents_per_world=1, surface_patterns="no")
    with make_env("spread", appearance=mr.Appearance(textures=False), resolution=8) as env:
        assert env.renderer.scene.surface_patterns is False


def test_every_pattern_draws_something_different():
    with top_down_floor(len(looks.PATTERNS)) as r:
        r.set_appearance(floor=(0.5, 0.5, 0.5), floor_pattern=torch.arange(len(looks.PATTERNS)), pattern_scale=3.0,
                         pattern_contrast=0.6)
        rgb = r.render().rgb[:, 0]
    images = {rgb[w].numpy().tobytes() for w in range(len(looks.PATTERNS))}
    assert len(images) == len(looks.PATTERNS)


def test_pattern_factors_are_the_weighted_sum_bit_for_bit():
    """The factor past the threshold along u only, v only and both is, in float32, exactly
    1 - (weights . (a, b, ab)) for every pattern and contrast: what the shader computed per fragment."""
    contrast = torch.tensor([0.15, 0.2345678, 0.35, 1 / 3, 1.0], dtype=F64)
    weights = (looks.PATTERN_TERMS[:, None, 3:] * contrast[None, :, None]).to(torch.float32)  # [patterns, C, 3]
    factors = looks.pattern_factors(weights)
    assert factors.dtype == torch.float32 and factors.shape == (len(looks.PATTERNS), len(contrast), 3)
    for column, (a, b) in enumerate(((1.0, 0.0), (0.0, 1.0), (1.0, 1.0))):
        terms = torch.tensor([a, b, a * b], dtype=torch.float32)
        summed = weights[..., 0] * terms[0] + weights[..., 1] * terms[1] + weights[..., 2] * terms[2]
        assert torch.equal(factors[..., column], 1 - summed)
    assert torch.equal(factors[0], torch.ones(len(contrast), 3))  # plain leaves every colour as it is


def test_the_colour_transform_rotates_hue_and_scales_saturation_and_value():
    """A third of a turn permutes the channels (r, g, b) -> (b, r, g); saturation 0 leaves the grey of
    the mean; value scales; floors and walls (roles) are not transformed."""
    color = torch.tensor([0.8, 0.25, 0.65], dtype=F64)
    scene = free_scene(4)
    with mr.BatchRenderer(scene) as r:
        look_from(r, [0, -3, 0], IDENTITY)
        r.update("boxes", position=torch.zeros(4, 1, 3, dtype=F64), color=color.expand(4, 1, 3),
                 scale=torch.full((4, 1, 3), 4.0), active=torch.ones(4, 1, dtype=torch.bool))
        r.set_appearance(hue_shift=torch.tensor([0.0, 1 / 3, 0.0, 0.0]), saturation=torch.tensor([1.0, 1.0, 0.0, 1.0]),
                         value=torch.tensor([1.0, 1.0, 1.0, 0.5]))
        centre = r.render().rgb[:, 0, 4, 4]
    assert centre[0].tolist() == to_byte(color).tolist()
    assert (centre[1].int() - to_byte(color[[2, 0, 1]]).int()).abs().max() <= 1
    assert (centre[2].int() - to_byte(color.mean().expand(3)).int()).abs().max() <= 1
    assert (centre[3].int() - to_byte(color * 0.5).int()).abs().max() <= 1
    matrix = looks.color_transform(torch.tensor([0.1]), torch.tensor([0.7]), torch.tensor([0.9]))[0]
    terms = looks.color_transform_terms(torch.tensor([0.1]), torch.tensor([0.7]), torch.tensor([0.9]))[0]
    c = color
    assert torch.allclose(matrix @ c, terms[0] * c + terms[1] * c.mean() + terms[2] * (c[[2, 0, 1]] - c[[1, 2, 0]]))


def test_each_world_is_lit_by_its_own_light():
    """The -Y face of a box seen head-on: lit fully from behind the camera, ambient only, or not at all."""
    color = torch.tensor([0.6, 0.5, 0.4], dtype=F64)
    scene = free_scene(3, effects=("lighting", "appearance"))
    with mr.BatchRenderer(scene) as r:
        look_from(r, [0, -3, 0], IDENTITY)
        r.update("boxes", position=torch.zeros(3, 1, 3, dtype=F64), color=color.expand(3, 1, 3),
                 active=torch.ones(3, 1, dtype=torch.bool))
        r.set_appearance(light_direction=torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]),
                         light_color=torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]),
                         ambient=torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.0, 0.0, 0.0]]))
        centre = r.render().rgb[:, 0, 4, 4].int()
    assert (centre[0] - to_byte(color).int()).abs().max() <= 1
    assert (centre[1] - to_byte(color * 0.5).int()).abs().max() <= 1
    assert centre[2].tolist() == [0, 0, 0]


# ----------------------------------------------------------------------------- cameras
def mounted_scene(worlds):
    scene = mr.Scene(num_worlds=worlds, agents_per_world=1, resolution=16, effects=("appearance",))
    scene.add_static("floor", "plane", position=[[0, 0, 0]], scale=[[40, 40, 1]], color=[[0.3, 0.6, 0.3]])
    scene.add_group("agents", "box", capacity=1)
    scene.add_group("marks", "box", capacity=1)
    scene.mount_cameras("agents", [0], offset=(0.0, 0.0, 0.5), pitch=-0.2)
    r = mr.BatchRenderer(scene)
    W = worlds
    r.update("agents", position=torch.zeros(W, 1, 3, dtype=F64), active=torch.ones(W, 1, dtype=torch.bool))
    r.update("marks", position=torch.tensor([[[0.0, 4.0, 0.5]]], dtype=F64).expand(W, 1, 3),
             color=torch.tensor([[[1.0, 0.0, 0.0]]]).expand(W, 1, 3), active=torch.ones(W, 1, dtype=torch.bool))
    return r


def test_mounted_cameras_take_a_height_and_pitch_per_view():
    with mounted_scene(3) as r:
        before = r.render().rgb
        r.set_cameras(mount_offset=torch.tensor([0.0, 0.0, 0.5]), mount_pitch=-0.2)  # the mount's own values
        same = r.render().rgb
        r.set_cameras(mount_offset=torch.tensor([[[0.0, 0.0, 0.5]], [[0.0, 0.0, 1.5]], [[0.0, 0.0, 0.5]]]),
                      mount_pitch=torch.tensor([[-0.2], [-0.2], [0.3]]))
        after = r.render().rgb
    assert torch.equal(before, same)
    assert torch.equal(after[0], before[0])
    assert not torch.equal(after[1], before[1]) and not torch.equal(after[2], before[2])
    red = (after[..., 0] > 200) & (after[..., 1] < 50)
    rows = [red[w, 0].nonzero()[:, 0].float().mean().item() for w in range(3)]
    assert rows[1] > rows[0] and rows[2] > rows[0]  # higher, or looking up: the mark sits lower in the view


# ----------------------------------------------------------------------------- the sampler and its splits
def test_train_and_heldout_share_no_hue_sector_and_no_pattern():
    ids = torch.arange(20_000, dtype=torch.int64) * 7_919 - 10 ** 9
    train, heldout = looks.Appearance("train").sample(ids), looks.Appearance("heldout").sample(ids)
    for surface in ("sky", "floor", "wall"):
        sectors = {split: set((getattr(p, f"{surface}_hue") * looks.HUE_SECTORS).floor().long().tolist())
                   for split, p in (("train", train), ("heldout", heldout))}
        assert sectors["train"] == set(looks.TRAIN_SECTORS) and sectors["heldout"] == set(looks.HELDOUT_SECTORS)
        assert not sectors["train"] & sectors["heldout"]
        # The colours themselves have the hue drawn (HSV round trip).
        rgb = getattr(train, surface)
        hue = torch.tensor([colorsys.rgb_to_hsv(*c)[0] for c in rgb[:200].tolist()], dtype=F64)
        assert torch.allclose(hue, getattr(train, f"{surface}_hue")[:200], atol=1e-9)
    for surface in ("floor", "wall"):
        patterns = {split: set(getattr(p, f"{surface}_pattern").tolist()) for split, p in (("train", train),
                                                                                          ("heldout", heldout))}
        assert patterns == {"train": set(looks.TRAIN_PATTERNS), "heldout": set(looks.HELDOUT_PATTERNS)}
    assert not set(looks.TRAIN_PATTERNS) & set(looks.HELDOUT_PATTERNS)
    assert not set(looks.TRAIN_SECTORS) & set(looks.HELDOUT_SECTORS)


def test_the_sampler_is_a_pure_function_of_the_id():
    ids = torch.tensor([5, -3, 2 ** 62, 7])
    sampler = looks.Appearance("train")
    whole = sampler.sample(ids)
    alone = sampler.sample(ids[2:3])
    again = sampler.sample(ids.flip(0))
    for field in looks.AppearanceParams.__dataclass_fields__:
        assert torch.equal(getattr(whole, field)[2:3], getattr(alone, field)), field
        assert torch.equal(getattr(whole, field).flip(0), getattr(again, field)), field
    assert not torch.equal(whole.sky[0], whole.sky[3])  # other ids, other looks


def test_sampled_values_stay_in_their_ranges_and_switches_turn_parts_off():
    ids = torch.arange(5_000)
    p = looks.Appearance("heldout").sample(ids)
    assert torch.allclose(p.light_direction.norm(dim=-1), torch.ones(5_000, dtype=F64))
    assert (p.light_direction[:, 2] < -math.sin(math.radians(34))).all()  # from above the horizon
    for name in ("sky", "floor", "wall", "light_color", "ambient"):
        assert (getattr(p, name) >= 0).all() and (getattr(p, name) <= 1).all()
    assert p.hue_shift.abs().max() <= 0.025 and (p.saturation - 1).abs().max() <= 0.15
    assert (p.fov_scale - 1).abs().max() <= 0.1 and p.camera_height.abs().max() <= 0.05
    assert 0.8 * 0.1 < (p.fov_scale - 1).abs().max()  # the jitter is used, not only bounded
    plain = looks.Appearance("train", textures=False, camera=False).sample(ids)
    assert (plain.floor_pattern == 0).all() and (plain.wall_pattern == 0).all()
    assert (plain.fov_scale == 1).all() and (plain.camera_height == 0).all() and (plain.camera_pitch == 0).all()


def test_team_hues_stay_apart_under_the_default_jitter():
    """Red and orange, the closest hues of the palette's first teams, never swap under any world's shift
    (hues as signed turns: red sits just above 0)."""
    shifts = looks.Appearance().sample(torch.arange(10_000)).hue_shift
    extreme = torch.stack((shifts.min(), shifts.max()))
    colors = torch.tensor([[0.85, 0.25, 0.20], [0.95, 0.55, 0.15]], dtype=F64)  # red team, orange palette
    hues = []
    for shift in extreme:
        transform = looks.color_transform(shift[None], torch.ones(1), torch.ones(1))[0]
        hues.append([(colorsys.rgb_to_hsv(*(transform @ c).clamp(0, 1).tolist())[0] + 0.5) % 1 - 0.5
                     for c in colors])
    low_red, high_red = hues[0][0], hues[1][0]
    assert max(high_red, low_red) < min(hues[0][1], hues[1][1])  # every red stays below every orange


# ----------------------------------------------------------------------------- bad input
@pytest.fixture(scope="module")
def renderer():
    r = mr.BatchRenderer(free_scene(2))
    yield r
    r.close()


@pytest.mark.parametrize("kwargs, error, message", [
    ({"sky": torch.ones(3, 3)}, ValueError, r"sky must have shape \[2, 3\]"),
    ({"sky": torch.full((2, 3), 1.5)}, ValueError, r"sky must be <= 1"),
    ({"light_color": -torch.ones(2, 3)}, ValueError, r"light_color must be >= 0"),
    ({"light_direction": torch.zeros(2, 3)}, ValueError, r"light_direction must be non-zero"),
    ({"floor_pattern": torch.tensor([0, 9])}, ValueError, r"floor_pattern must be <= 4"),
    ({"floor_pattern": torch.tensor([0.5, 1.0])}, TypeError, r"floor_pattern must have an integer dtype"),
    ({"hue_shift": torch.tensor([float("nan"), 0.0])}, ValueError, r"hue_shift must be finite"),
    ({"pattern_scale": torch.zeros(2, 2)}, ValueError, r"pattern_scale must be >= 0.001"),
    ({"glow": 1.0}, TypeError, r"unknown argument\(s\) \['glow'\]"),
    ({"sky": "blue"}, TypeError, r"sky must be"),
])
def test_bad_appearance_raises_naming_the_argument_and_changes_nothing(renderer, kwargs, error, message):
    look_from(renderer, [0, 0, 0], UP)
    renderer.set_appearance(sky=SKIES[:2])
    before = renderer.render().rgb
    with pytest.raises(error, match=message):
        renderer.set_appearance(value=torch.tensor([0.5, 0.5]), **kwargs)  # a valid argument beside it
    assert torch.equal(renderer.render().rgb, before)
    assert (renderer.packer.appearance.values["value"] == 1).all()


def test_the_effect_must_be_declared_and_excludes_msaa():
    with mr.BatchRenderer(free_scene(1, effects=("lighting",))) as r:
        with pytest.raises(ValueError, match="set_appearance needs a scene that declares the 'appearance' effect"):
            r.set_appearance(sky=(0.1, 0.2, 0.3))
    with pytest.raises(ValueError, match="multisamples cannot be combined with the appearance effect"):
        mr.BatchRenderer(free_scene(1), multisamples=4)


@pytest.mark.parametrize("make, error, message", [
    (lambda s: s.add_static("x", "box", position=[0, 0, 0], role="ceiling"), ValueError, r"role must be one of"),
    (lambda s: s.add_static("x", "box", position=[[0, 0, 0]] * 2, role=["floor"]), ValueError,
     r"role must be one of .* or a list of 2"),
    (lambda s: s.add_static("x", "box", position=[[0, 0, 0]] * 2, role=["floor", 3]), ValueError, r"role\[1\]"),
    (lambda s: s.add_group("x", "box", capacity=1, role="sky"), ValueError, r"role must be one of"),
])
def test_bad_roles_name_the_argument_and_add_nothing(make, error, message):
    scene = free_scene(1)
    with pytest.raises(error, match=message):
        make(scene)
    assert "x" not in scene.static and "x" not in scene.groups


@pytest.mark.parametrize("kwargs, error, message", [
    ({"mount_pitch": 2.0}, ValueError, r"mount_pitch must be <= "),
    ({"mount_offset": torch.ones(2, 2, 3)}, ValueError, r"mount_offset must have shape \[3, 1, 3\]"),
    ({"mount_offset": torch.tensor([0.0, float("inf"), 0.0])}, ValueError, r"mount_offset must be finite"),
])
def test_bad_mount_jitter_raises_and_changes_nothing(kwargs, error, message):
    with mounted_scene(3) as r:
        before = r.render().rgb
        with pytest.raises(error, match=message):
            r.set_cameras(fov_y=1.0, **kwargs)
        assert torch.equal(r.render().rgb, before)
    with mr.BatchRenderer(free_scene(1)) as free, pytest.raises(ValueError, match="mount_offset and mount_pitch apply"):
        free.set_cameras(mount_pitch=0.1)


@pytest.mark.parametrize("make, error, message", [
    (lambda: looks.Appearance(split="test"), ValueError, r"split must be one of \['train', 'heldout'\]"),
    (lambda: looks.Appearance(textures="yes"), TypeError, r"textures must be a bool"),
    (lambda: looks.Appearance(hue_jitter=0.7), ValueError, r"hue_jitter must be a number in \[0, 0.5\]"),
    (lambda: looks.Appearance().sample(torch.zeros(3)), TypeError, r"ids must be an integer tensor"),
    (lambda: looks.Appearance().sample([1, 2]), TypeError, r"ids must be an int64 tensor"),
    (lambda: make_env("spread", appearance="test"), ValueError, r"appearance must be None, one of \['train', "),
    (lambda: make_env("spread", appearance=1), TypeError, r"appearance must be None"),
])
def test_bad_appearance_options_name_the_argument(make, error, message):
    with pytest.raises(error, match=message):
        make()


# ----------------------------------------------------------------------------- the env option
def test_env_looks_follow_the_worlds_ids_in_any_slot_and_batch_size():
    """Worlds drawn with appearance ids show their sky; the state of world 0 of a 1-world env, put
    into world 2 of a 3-world env with the same id, renders the same pixels there."""
    kw = dict(appearance="train", resolution=12, seed=3)
    with make_env("spread", num_worlds=1, **kw) as one, make_env("spread", num_worlds=3, **kw) as three:
        single = one.reset()["pixels"]
        three.reset()
        state, source = three.get_state(), one.get_state()
        assert state["appearance_ids"].dtype == torch.int64 and state["appearance_ids"].shape == (3,)
        for key, value in source.items():
            if key != "rng":
                state[key][2] = value[0]
        three.set_state(state)
        pixels = three.step(torch.zeros(3, three.num_agents, dtype=torch.int64))[0]["pixels"]
        one_step = one.step(torch.zeros(1, one.num_agents, dtype=torch.int64))[0]["pixels"]
        assert torch.equal(pixels[2], one_step[0])
        assert not torch.equal(pixels[0], pixels[2]) and not torch.equal(pixels[1], pixels[2])
        assert torch.equal(single[0], one.reset(seed=3)["pixels"][0])  # the same seed, the same first look
        sky = looks.Appearance("train").sample(three.appearance_ids).sky
        top = pixels[:, 0, 0, 6]  # the top row of each world's first view: sky
        assert ((top.int() - to_byte(sky).int()).abs() <= 1).all()


def test_appearance_ids_are_drawn_per_reset_world_and_keep_layouts_of_the_first_reset():
    with make_env("forage", num_worlds=4, resolution=8, seed=11) as plain, \
            make_env("forage", num_worlds=4, resolution=8, seed=11, appearance="heldout") as looked:
        plain.reset(), looked.reset()
        assert plain.appearance_ids is None
        assert torch.equal(plain.sim.pos, looked.sim.pos)  # drawn after spawn
        ids = looked.appearance_ids.clone()
        assert len(set(ids.tolist())) == 4
        looked.reset_worlds(torch.tensor([False, True, False, True]))
        assert torch.equal(looked.appearance_ids[[0, 2]], ids[[0, 2]])
        assert not bool((looked.appearance_ids[[1, 3]] == ids[[1, 3]]).any())
        # Only the reset worlds were sampled again, and every world shows the look of its id.
        expected = looks.Appearance("heldout").sample(looked.appearance_ids)
        shown = looked.renderer.packer.appearance.values
        assert torch.equal(shown["sky"], expected.sky) and torch.equal(shown["floor_pattern"], expected.floor_pattern)
        assert "appearance_ids" not in plain.get_state()


def test_camera_jitter_reaches_free_cameras_and_the_overview_gets_the_looks():
    with make_env("cartpole", num_worlds=2, resolution=12, seed=0) as plain, \
            make_env("cartpole", num_worlds=2, resolution=12, seed=0, appearance="train") as looked:
        plain.reset(), looked.reset()
        base = plain.renderer.camera_position
        moved = looked.renderer.camera_position
        look = looks.Appearance("train").sample(looked.appearance_ids)
        assert torch.allclose(moved[:, 0, 2] - base[:, 0, 2], look.camera_height)
        assert torch.allclose(looked.renderer.fov_y[:, 0], plain.renderer.fov_y[:, 0] * look.fov_scale)
        overview = looked.render_overview(resolution=16)
        assert ((overview[:, 0, 0].int() - to_byte(look.sky).int()).abs() <= 1).all()


@pytest.mark.parametrize("make", [
    lambda: make_parallel_env("spread", appearance="heldout", resolution=8),
    lambda: make_torchrl_env("spread", num_worlds=2, appearance="heldout", resolution=8),
    lambda: make_vec_env("spread", num_worlds=2, appearance="heldout", resolution=8),
    lambda: make_sb3_env("spread", num_worlds=2, appearance="heldout", resolution=8),
], ids=["pettingzoo", "torchrl", "vector", "sb3"])
def test_front_ends_pass_the_option_through(make):
    env = make()
    try:
        env.reset()
        core = env.venv.core if hasattr(env, "venv") else env.core  # SB3's VecEnv wraps the vector env
        assert core.appearance == looks.Appearance("heldout")
        assert core.appearance_ids is not None and core.appearance_ids.shape == (core.num_worlds,)
    finally:
        env.close()


def test_bench_effects_measures_the_appearance_effect(tmp_path):
    out = subprocess.run([sys.executable, "-m", "marl_render.bench", "effects", "--json", "--sections", "appearance",
                          "--worlds", "2", "--agents", "2", "--resolution", "8", "--steps", "2", "--rounds", "1",
                          "--out", str(tmp_path)], capture_output=True, text=True, timeout=300, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])["appearance"]
    assert result["views"] == 4 and len(result["load_average"]) == 3
    for label in ("off", "on", "no_patterns"):
        assert result[f"{label}_views_per_s"] > 0 and result[f"{label}_cpu_ms_per_frame"] > 0
    assert len(result["time_ratios_on_off"]) == 1 and result["cost_vs_off"] == result["time_ratio_on_off"] - 1
    report = (tmp_path / "effects.md").read_text()
    assert report.count("lighting + appearance") == 1 and report.count("without patterns") == 1


def test_layered_views_show_each_worlds_sky_and_its_changes():
    """layered=True: the sky is copied into every view's layer (one array image per pass)."""
    scene = free_scene(3, agents=2)
    with mr.BatchRenderer(scene, layered=True) as r:
        look_from(r, [0, 0, 0], UP)
        r.set_appearance(sky=SKIES)
        rgb = r.render().rgb
        for w in range(3):
            assert (rgb[w] == to_byte(SKIES[w])).all(), w
        r.set_appearance(sky=torch.cat((SKIES[:1], torch.tensor([[0.0, 0.0, 0.0]], dtype=F64), SKIES[2:])))
        again = r.render().rgb
        assert (again[1] == 0).all()
        assert torch.equal(again[0], rgb[0]) and torch.equal(again[2], rgb[2])
        for active in (True, False):  # the next frame's sky replaces what a box drew
            r.update("boxes", position=torch.tensor([0.0, 0.0, 2.0], dtype=F64).expand(3, 1, 3),
                     active=torch.full((3, 1), active))
            boxed = r.render().rgb
            assert torch.equal(boxed, again) != active
