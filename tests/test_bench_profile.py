"""bench profile (the GL stage split into vertex and fragment work) and bench accuracy-geometry."""
import numpy as np

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
