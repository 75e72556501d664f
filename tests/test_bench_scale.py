"""`python -m marl_render.bench scale`: files, and a memory reading that means what it says.

Speed is never asserted. Memory per view is the RSS a renderer and its last frame hold:
at least the frame's own bytes, also for a small point measured after a large one (whose
framebuffer the driver frees lazily: read in one process, that release made the small
point's memory negative).
"""
from __future__ import annotations

import json

from marl_render.bench import __main__ as bench


def test_scale_writes_its_files_and_positive_memory(tmp_path):
    argv = ["scale", "--views", "4096", "--resolution", "64", "--resolutions", "32", "--fixed-views", "256",
            "--steps", "1", "--json", "--out", str(tmp_path)]
    assert bench.main(argv) == 0
    result = json.loads((tmp_path / "scale.json").read_text())
    points = result["by_views"] + result["by_resolution"]
    assert [(p["views"], p["resolution"]) for p in points] == [(4096, 64), (256, 32)]
    for p in points:  # the frame alone is views * H * W * 3 bytes
        assert p["memory_per_view_kib"] * 1024 * p["views"] >= p["views"] * p["resolution"] ** 2 * 3, p
    for p in points:
        assert p["memory_per_view_kib"] == p["memory_mib"] * 1024 / p["views"]
    markdown = (tmp_path / "scale.md").read_text().splitlines()
    assert [cell.strip() for cell in markdown[0].split("|")[1:-1]] == [
        "views", "px", "passes", "views/s", "Mpixel/s", "ms/frame", "pack", "cull", "draw", "read", "copy", "KiB/view"]
    assert len(markdown) == 2 + len(points)  # header, alignment row, one row per point
    assert [int(row.split("|")[1]) for row in markdown[2:]] == [p["views"] for p in points]
    assert (tmp_path / "scale.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
