"""bench profile (the GL stage split into vertex and fragment work) and bench accuracy-geometry."""
import numpy as np
import torch

import marl_render as mr
from marl_render.bench.__main__ import main
from marl_render.bench.profile import subdivided


def _area(mesh) -> float:
    a, b, c = (mesh.positions[mesh.triangles[:, k]] for k in range(3))
    return float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2)


def test_subdivided_keeps_the_surface_with_four_times_the_triangles():
    box = mr.box()
    for levels in (1, 2):
        finer = subdivided(box, levels)
        assert len(finer.triangles) == len(box.triangles) * 4 ** levels
        assert abs(_area(finer) - _area(box)) < 1e-5  # 6 faces of 1 m^2
        assert np.abs(finer.positions).max() <= 0.5 + 1e-7  # on the cube, not beyond
        assert finer.flat and np.allclose(np.abs(finer.normals).sum(1), 1)  # still one axis normal per face


def test_bench_profile_writes_the_split_per_env_and_resolution(tmp_path, capsys):
    assert main(["profile", "--json", "--env", "spread", "--resolution", "16", "--worlds", "1", "--rounds", "1",
                 "--block-seconds", "0.01", "--subdivide", "0", "1", "--coverage", "0.5", "1",
                 "--out", str(tmp_path)]) == 0
    result = __import__("json").loads(capsys.readouterr().out)
    (row,) = result["results"]
    assert (row["env"], row["resolution"], row["agents"]) == ("spread", 16, 3)
    assert [(v["subdivide"], v["resolution"]) for v in row["variants"]] == [(0, 16), (1, 16), (0, 8)]
    base, finer, smaller = row["variants"]
    assert finer["triangles"] == 4 * base["triangles"] and smaller["pixels"] * 4 == base["pixels"] == 3 * 16 * 16
    assert result["machine"]["cpu_model"] and "| spread | 3 | 16 |" in (tmp_path / "profile.md").read_text()


def test_bench_profile_groups_times_each_switch_and_checks_the_frames(tmp_path, capsys):
    assert main(["profile", "--json", "--env", "commons:2", "--resolution", "16", "--worlds", "1", "--rounds", "1",
                 "--block-seconds", "0.01", "--subdivide", "0", "--coverage", "1", "--impostors", "auto", "--groups",
                 "--out", str(tmp_path)]) == 0
    (row,) = __import__("json").loads(capsys.readouterr().out)["results"]
    groups = row["groups"]
    assert list(groups["step_cpu_ms"]) == ["base", "hide arena", "hide agents", "hide noses", "hide apples",
                                           "hide all", "static last", "impostors unculled"]
    assert all(ms > 0 for ms in groups["step_cpu_ms"].values()) and groups["delta_ms"]["base"] == 0.0
    # Neither drawing order nor skipping the impostors' frustum test may change a pixel.
    assert groups["same_frame"] == {"static last": True, "impostors unculled": True}
    text = (tmp_path / "profile.md").read_text()
    assert "| commons | 16 | impostors unculled |" in text
    # One setting (--subdivide 0 --coverage 1) fits no split: empty, not NaN (which JSON cannot hold).
    assert row["vertex_ms"] is None and row["ns_per_pixel"] is None and "nan" not in text
    assert "NaN" not in (tmp_path / "profile.json").read_text()


def test_group_variants_hide_reorder_and_restore(capsys):
    from marl_render.bench.profile import _GroupVariants
    from marl_render.envs import make_env

    with make_env("commons", num_worlds=1, num_agents=2, resolution=16, seed=0) as env:
        env.reset(seed=0)
        base = env.renderer.render().rgb.clone()
        variants = _GroupVariants(env.renderer)
        variants.set("hide all")
        sky = env.renderer.render().rgb
        assert (sky == sky[:, :1, :1]).all() and not torch.equal(sky, base)  # nothing drawn: one colour
        variants.set("static last")
        arena = env.renderer._groups["arena"].pass_nodes[0][0]
        assert arena.get_bin_draw_order() == 4  # after agents, noses and apples (orders 1-3)
        assert env.renderer.packer.groups["apples"].frustum_pause == 0
        variants.set("impostors unculled")
        assert env.renderer.packer.groups["apples"].frustum_pause > 1000 and arena.get_bin_draw_order() == 0
        variants.set("base")
        assert torch.equal(env.renderer.render().rgb, base)
