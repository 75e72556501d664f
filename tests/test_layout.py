"""One buffer layout table (layout.py) drives both the packer and the shaders, and the
packer (packing.py) turns state into plain tensors without any GL."""
import subprocess
import sys

import pytest
import torch

import marl_render as mr
from marl_render import layout, shaders
from marl_render.layout import Field, RowLayout
from marl_render.packing import FramePacker
from marl_render.tiling import column_layout


def test_generated_defines_are_the_table():
    for static, table in ((False, layout.INSTANCE), (True, layout.STATIC_INSTANCE)):
        defines = set(shaders.defines_for(frozenset({"lighting"}), static=static, textured=False))
        assert f"ROW_TEXELS {table.texels}" in defines
        assert f"VIEW_TEXELS {layout.VIEW.texels}" in defines
        for name, field in table.fields.items():
            assert f"ROW_{name.upper()} {field.texel}" in defines
            assert f"ROW_{name.upper()}_LANES {field.lanes}" in defines
        for name, field in layout.VIEW.fields.items():
            assert f"VIEW_{name.upper()} {field.texel}" in defines
    assert "ROW_POSITION_LO 4" in shaders.caster_defines(static=True)


def test_a_field_outside_its_row_is_refused():
    with pytest.raises(ValueError, match="outside its 2-texel row"):
        RowLayout("X", 2, {"a": Field(2)})
    with pytest.raises(ValueError, match="outside"):
        RowLayout("X", 2, {"a": Field(0, "xz")})  # lanes must be a run of xyzw


# A layout with every field moved: other texels, other lanes, longer rows.
SHUFFLED = {
    "INSTANCE": RowLayout("INSTANCE", 5, {
        "color": Field(0), "position": Field(1, "yzw"), "active": Field(1, "x"), "rotation": Field(4),
        "scale": Field(2, "yzw"), "owner": Field(2, "x")}),
    "STATIC_INSTANCE": RowLayout("STATIC", 6, {
        "position_lo": Field(0, "yzw"), "active": Field(0, "x"), "color": Field(1), "position": Field(5, "xyz"),
        "role": Field(5, "w"), "rotation": Field(2), "scale": Field(3, "yzw"), "owner": Field(3, "x")}),
    "VIEW": RowLayout("VIEW", 7, {
        "origin_lo": Field(0, "yzw"), "far": Field(0, "x"), "projection": Field(2), "origin_hi": Field(6, "xyz"),
        "near": Field(6, "w")}),
}


def shuffle(monkeypatch):
    for name, table in SHUFFLED.items():
        monkeypatch.setattr(layout, name, table)


def test_a_changed_table_changes_the_shader_source(monkeypatch):
    before = shaders.variant_source("vert", shaders.defines_for(frozenset(), static=True, textured=False))
    shuffle(monkeypatch)
    after = shaders.variant_source("vert", shaders.defines_for(frozenset(), static=True, textured=False))
    assert "#define ROW_POSITION 0\n" in before and "#define ROW_POSITION 5\n" in after
    assert "#define ROW_POSITION_LO_LANES yzw\n" in after and "#define VIEW_TEXELS 7\n" in after
    assert "#define ROW_COLOR 3\n" not in after


def far_scene():
    """Static floor and moving boxes far from 0 (hi + lo origins), lit, shadowed, with depth outputs."""
    scene = mr.Scene(num_worlds=2, agents_per_world=2, resolution=24,
                     effects=("lighting", "shadows", "depth", "segmentation", "log_depth"))
    offset = 5000.0
    scene.add_static("floor", "plane", position=[[offset, offset, 0.0]], scale=[[8.0, 8.0, 1.0]],
                     color=[[0.3, 0.7, 0.3, 1.0]])
    scene.add_group("boxes", "box", capacity=3)
    return scene, offset


def render_far_scene():
    scene, offset = far_scene()
    with mr.BatchRenderer(scene) as renderer:
        W, A, C = 2, 2, 3
        generator = torch.Generator().manual_seed(3)
        position = torch.rand(W, C, 3, generator=generator, dtype=torch.float64) * 2 - 1
        position[..., 1] += 3.0
        position[..., 2] = 0.5
        renderer.update("boxes", position=position + torch.tensor([offset, offset, 0.0], dtype=torch.float64),
                        rotation=torch.nn.functional.normalize(torch.rand(W, C, 4, generator=generator), dim=-1),
                        scale=torch.rand(W, C, 3, generator=generator) * 0.5 + 0.3,
                        color=torch.rand(W, C, 3, generator=generator), active=torch.tensor([[1, 1, 0], [1, 0, 1]]) > 0,
                        owner=torch.tensor([[0, -1, -1], [-1, -1, 1]]))
        eye = torch.tensor([offset, offset - 1.0, 1.5], dtype=torch.float64).expand(W, A, 3).clone()
        eye[:, 1, 0] += 0.7
        renderer.set_cameras(position=eye, look_at=eye + torch.tensor([0.0, 4.0, -1.0], dtype=torch.float64),
                             near=torch.tensor([[0.05, 0.1], [0.2, 0.05]]), far=torch.tensor([[30.0, 40], [50, 60]]))
        return renderer.render()


def test_a_changed_table_renders_the_same_pixels(monkeypatch):
    reference = render_far_scene()
    assert len(reference.segmentation.unique()) >= 3  # background, floor and boxes are all in view
    shuffle(monkeypatch)
    shuffled = render_far_scene()
    assert torch.equal(shuffled.rgb, reference.rgb)
    assert torch.equal(shuffled.depth, reference.depth)
    assert torch.equal(shuffled.segmentation, reference.segmentation)


class Targets:
    """Plain tensors as the packer's destinations, counting what it asked for."""

    def __init__(self, packer: FramePacker):
        self.memory = {"views": torch.zeros(packer.view_texels() * 4)}
        for name in packer.groups:
            self.memory[f"instances:{name}"] = torch.zeros(packer.instance_texels(name) * 4)
            self.memory[f"pairs:{name}"] = torch.full((packer.pair_capacity(name),), -1, dtype=torch.int32)
        self.asked = []

    def _get(self, key):
        self.asked.append(key)
        return self.memory[key]

    def views(self):
        return self._get("views")

    def instances(self, group):
        return self._get(f"instances:{group}")

    def pairs(self, group):
        return self._get(f"pairs:{group}")


def test_the_packer_writes_rows_pairs_and_pass_ranges_without_a_gl():
    scene = mr.Scene(num_worlds=2, agents_per_world=2, resolution=8, effects=())
    scene.add_group("boxes", "box", capacity=2)
    packer = FramePacker(scene, column_layout(scene.num_views, 8, 8, 24))  # 3 views per pass: 2 passes
    targets = Targets(packer)
    position = torch.tensor([[[0.0, 3.0, 0.0], [0.0, -3.0, 0.0]], [[0.5, 3.0, 0.0], [0.0, 3.0, 0.5]]])
    packer.update("boxes", position=position, color=torch.ones(2, 2, 3) * 0.5,
                  active=torch.ones(2, 2, dtype=torch.bool), owner=torch.tensor([[-1, -1], [-1, 0]]))
    packer.set_cameras(position=torch.zeros(2, 2, 3), rotation=torch.tensor([1.0, 0, 0, 0]).repeat(2, 2, 1))
    timings = packer.prepare(targets)
    assert timings["packed"] == ["boxes"]
    rows = targets.memory["instances:boxes"].view(2, 2, layout.INSTANCE.texels, 4)
    assert torch.equal(rows[(slice(None), slice(None), *layout.INSTANCE["position"])], position)
    assert torch.equal(rows[(slice(None), slice(None), *layout.INSTANCE["owner"])], torch.tensor([[-1.0, -1], [-1, 0]]))
    assert torch.equal(rows[(slice(None), slice(None), *layout.INSTANCE["color"])], torch.tensor([0.5, 0.5, 0.5, 1.0])
                       .expand(2, 2, 4))
    views = targets.memory["views"].view(4, layout.VIEW.texels, 4)
    assert torch.equal(views[(slice(None), *layout.VIEW["far"])], torch.full((4,), float(scene.far)))
    # Box 1 of world 0 is behind both cameras; box 1 of world 1 is agent 0's own body.
    pairs = targets.memory["pairs:boxes"]
    assert pairs[:5].tolist() == [0, 2, 4, 6, 7]
    assert packer.groups["boxes"].pass_ranges == [(0, 3), (3, 2)]  # views 0-2, then view 3
    # Nothing changed: nothing is written again.
    targets.asked.clear()
    packer.prepare(targets)
    assert targets.asked == []


def test_packing_does_not_import_panda3d():
    code = ("import sys, marl_render.packing, marl_render.layout; "
            "assert 'panda3d' not in sys.modules and 'panda3d.core' not in sys.modules, 'imported panda3d'")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
