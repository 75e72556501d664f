"""Render time of BatchRenderer(layered=True) against the default column of tiles, same scene,
both renderers in one process, renders alternated (the machine is shared: compare ratios).

    python tools/layered_cost.py --views 64 256 1024 --steps 15

Scene per world (one agent each): a floor plane, 3 boxes and 2 balls at random places, the
camera 0.3 m above the floor (the near plane clips the floor), lighting; 64 x 64 px.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

import marl_render as mr


def raster_thread_seconds() -> list[float]:
    """CPU seconds so far of each of llvmpipe's rasteriser threads (named llvmpipe-N) in this process."""
    tick = os.sysconf("SC_CLK_TCK")
    seconds = []
    for task in sorted(os.listdir("/proc/self/task")):
        with open(f"/proc/self/task/{task}/comm") as comm:
            if not comm.read().startswith("llvmpipe-"):
                continue
        with open(f"/proc/self/task/{task}/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
        seconds.append((int(fields[11]) + int(fields[12])) / tick)  # utime + stime
    return seconds


def build(worlds: int, size: int, layered: bool, effects) -> mr.BatchRenderer:
    scene = mr.Scene(num_worlds=worlds, agents_per_world=1, resolution=size, effects=effects)
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[30, 30, 1], color=[0.3, 0.6, 0.3])
    scene.add_group("boxes", "box", capacity=3)
    scene.add_group("balls", "sphere", capacity=2)
    renderer = mr.BatchRenderer(scene, layered=layered)
    g = torch.Generator().manual_seed(0)
    box = torch.rand(worlds, 3, 3, generator=g) * torch.tensor([3.0, 2.0, 0.0]) + torch.tensor([-1.5, 0.8, 0.3])
    ball = torch.rand(worlds, 2, 3, generator=g) * torch.tensor([3.0, 2.0, 0.0]) + torch.tensor([-1.5, 0.8, 0.4])
    renderer.update("boxes", position=box, scale=torch.full((worlds, 3, 3), 0.3),
                    active=torch.ones(worlds, 3, dtype=torch.bool))
    renderer.update("balls", position=ball, scale=torch.full((worlds, 2, 3), 0.4),
                    active=torch.ones(worlds, 2, dtype=torch.bool))
    position = torch.rand(worlds, 1, 3, generator=g) * torch.tensor([1.0, 1.0, 0.0]) + torch.tensor([0, -1.0, 0.3])
    renderer.set_cameras(position=position, look_at=position + torch.tensor([0.0, 3.0, -0.3]))
    return renderer


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--views", type=int, nargs="+", default=[64, 256, 1024])
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--steps", type=int, default=15)
    parser.add_argument("--effects", nargs="+", default=["lighting"])
    args = parser.parse_args()
    for views in args.views:
        renderers = {"tiles": build(views, args.size, False, args.effects),
                     "layers": build(views, args.size, True, args.effects)}
        frames = {name: r.render() for name, r in renderers.items()}  # warm up (compile, first upload)
        times = {name: [] for name in renderers}
        gl = {name: [] for name in renderers}
        cpu = {name: [] for name in renderers}  # process CPU seconds per wall second: the GL's threads at work
        raster = {name: [0.0] * len(raster_thread_seconds()) for name in renderers}  # per rasteriser thread
        for step in range(args.steps):
            for name in (("tiles", "layers") if step % 2 == 0 else ("layers", "tiles")):
                started, cpu_started = time.perf_counter(), sum(os.times()[:2])
                before = raster_thread_seconds()
                renderers[name].render()
                after = raster_thread_seconds()
                raster[name] = [r + a - b for r, a, b in zip(raster[name], after, before, strict=True)]
                times[name].append(time.perf_counter() - started)
                cpu[name].append((sum(os.times()[:2]) - cpu_started) / times[name][-1])
                gl[name].append(renderers[name].last_timings["gl"])
        ratios = [b / a for a, b in zip(times["tiles"], times["layers"], strict=True)]
        differ = (frames["tiles"].rgb != frames["layers"].rgb).any(-1).float().mean().item()
        t, lay = renderers["tiles"], renderers["layers"]
        print(f"{views:5d} views {args.size} px: tiles {statistics.median(times['tiles']) * 1e3:7.1f} ms "
              f"(gl {statistics.median(gl['tiles']) * 1e3:.1f}, {t.layout.num_passes} passes)  layers "
              f"{statistics.median(times['layers']) * 1e3:7.1f} ms (gl {statistics.median(gl['layers']) * 1e3:.1f}, "
              f"{lay.layout.num_passes} passes)  layers/tiles median {statistics.median(ratios):.2f}"
              f" (min {min(ratios):.2f} max {max(ratios):.2f})  px differing {differ * 100:.3f}%  cpu/wall tiles "
              f"{statistics.median(cpu['tiles']):.2f} layers {statistics.median(cpu['layers']):.2f}")
        for name in renderers:  # how the rasterising was shared among llvmpipe's threads
            total = sum(raster[name]) or 1.0
            print(f"      {name} rasteriser threads: {sum(raster[name]):.2f} s in all, busiest thread "
                  f"{max(raster[name]) / total * 100:.0f}% ({len(raster[name])} threads)")
        for r in renderers.values():
            r.close()


if __name__ == "__main__":
    main()
