"""Scaling: throughput, memory per view and time per stage against views and resolution.

Two sweeps on the arena scene (floor + 10 instances per world, 4 agents per world):
views 16..4096 at --resolution, and resolutions 32..512 at --fixed-views. Stages are the
renderer's own timings: pack (poses, view matrices, instance buffers), cull, draw
(Panda3D's frame), read (the GL reads into the batch, which wait for the drawing) and copy
(copies after the reads: only for channels-first, supersampling or the "copy" readback, so
0 here). Published tables before the split (docs/scale) have one column "gl" = draw + read.

Memory per view: the resident memory (RSS, after garbage collection and malloc_trim) held
while a renderer and its last frame are alive, above the reading just before the renderer
was made, divided by the views. Every point runs in a fresh process: the GL driver and
Panda3D free a closed renderer's framebuffer lazily, during later GL work, so in one
process a small point after a large one read the large one's release (a negative
number). In its process a 1-view renderer first takes the one-time costs (GL context,
shader compilation).
Writes scale.md, scale.json and scale.png into --out.
"""
from __future__ import annotations

import multiprocessing
import os
import time

from tabulate import tabulate

import marl_render as mr

from .common import RandomMotion, apply, arena_scene, machine, progress, settled_rss_mb, write_report
from .common import positive_int_argument as count_argument  # a count >= 1
from .figures import pyplot

STAGES = ("pack", "cull", "draw", "read", "copy")


def add_arguments(parser):
    parser.add_argument("--views", type=count_argument, nargs="+", default=[16, 64, 256, 1024, 4096])
    parser.add_argument("--resolutions", type=count_argument, nargs="+", default=[32, 64, 128, 256, 512])
    parser.add_argument("--resolution", type=count_argument, default=64, help="resolution of the views sweep")
    parser.add_argument("--fixed-views", type=count_argument, default=256, help="views of the resolution sweep")
    parser.add_argument("--agents", type=count_argument, default=4)
    parser.add_argument("--steps", type=count_argument, default=10)
    parser.add_argument("--out", default="out/scale")


def measure(views: int, resolution: int, agents: int, steps: int) -> dict:
    """One point of a sweep, measured in a fresh process (see the module docstring)."""
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(_measure_in_this_process, (views, resolution, agents, steps))


def _measure_in_this_process(views: int, resolution: int, agents: int, steps: int) -> dict:
    with mr.BatchRenderer(arena_scene(1, 1, 8)) as warm_up:  # GL context and shaders: not this point's memory
        warm_up.render()
    worlds = max(1, views // agents)
    scene = arena_scene(worlds, agents, resolution)
    before_mb = settled_rss_mb()
    with mr.BatchRenderer(scene) as renderer:
        motion = RandomMotion(scene, seed=0)
        for _ in range(2):
            apply(renderer, motion.next())
            renderer.render()
        totals = dict.fromkeys(STAGES, 0.0)
        start = time.perf_counter()
        for _ in range(steps):
            apply(renderer, motion.next())
            frame = renderer.render()
            for stage in STAGES:
                totals[stage] += renderer.last_timings[stage]
        seconds = (time.perf_counter() - start) / steps
        held_mb = settled_rss_mb() - before_mb  # renderer + the frame still referenced here
        del frame
        passes = renderer.layout.num_passes
    return {"views": scene.num_views, "resolution": resolution, "passes": passes, "ms_per_frame": seconds * 1e3,
            "views_per_s": scene.num_views / seconds, "pixels_per_s": scene.num_views * resolution ** 2 / seconds,
            "memory_mib": held_mb, "memory_per_view_kib": held_mb * 1024 / scene.num_views,
            "stage_ms": {stage: totals[stage] / steps * 1e3 for stage in STAGES}}


def run(args) -> dict:
    result = {"benchmark": "scale", "machine": machine(), "by_views": [], "by_resolution": []}
    for views in args.views:
        progress(f"views sweep: {views} views of {args.resolution}px")
        result["by_views"].append(measure(views, args.resolution, args.agents, args.steps))
    for resolution in args.resolutions:
        progress(f"resolution sweep: {args.fixed_views} views of {resolution}px")
        result["by_resolution"].append(measure(args.fixed_views, resolution, args.agents, args.steps))
    _write(args.out, result)
    return result


def _write(out: str, result: dict) -> None:
    rows = [[r["views"], r["resolution"], r["passes"], r["views_per_s"], r["pixels_per_s"] / 1e6, r["ms_per_frame"],
             *(r["stage_ms"][stage] for stage in STAGES), r["memory_per_view_kib"]]
            for r in result["by_views"] + result["by_resolution"]]
    table = tabulate(rows, ["views", "px", "passes", "views/s", "Mpixel/s", "ms/frame", *STAGES, "KiB/view"],
                     tablefmt="pipe", floatfmt=["", "", "", ",.0f", ",.0f", ".1f", ".1f", ".1f", ".1f", ".1f", ".0f"])
    write_report(out, "scale", result, table.splitlines())
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    for ax, rows, key, label in ((axes[0], result["by_views"], "views", "views per frame"),
                                 (axes[1], result["by_resolution"], "resolution", "resolution (px per side)")):
        xs = [r[key] for r in rows]
        bottom = [0.0] * len(rows)
        for stage in STAGES:
            values = [r["stage_ms"][stage] / r["views"] * 1e3 for r in rows]
            ax.bar([str(x) for x in xs], values, bottom=bottom, label=stage)
            bottom = [b + v for b, v in zip(bottom, values, strict=True)]
        ax.set_xlabel(label)
        ax.set_ylabel("µs per view (stacked stages)")
        twin = ax.twinx()
        twin.plot([str(x) for x in xs], [r["views_per_s"] for r in rows], "k.-")
        twin.set_ylabel("views / s")
        ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "scale.png"), dpi=110)
    plt.close(fig)
