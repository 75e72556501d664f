"""The envs' three ways to draw the agents' views: a column of tiles (the default), one layer per
view (layered=True) and exactly placed tiles (exact_tiles=True); docs/levels.md.

    python tools/layered_envs.py slots TASK... [--resolution 64]
    python tools/layered_envs.py cost TASK... [--worlds 64] [--resolution 64] [--steps 21]

slots: test levels 7, 8, 9 reset into several slots of batches of 2, 5 and 3 worlds (appearance
"train", seed 123, 2 random steps first: tests/test_levels.py's plan) -> per level, how many
pixels differ from its first picture, in each mode.
cost: the three envs open at once, steps taken in turn (the order alternating step by step); per
mode the median of the renderer's own wall time per frame (last_timings: draw and read back) and
of the process's CPU time per step (all threads: llvmpipe rasterises on threads of its own), and
each median's ratio to the tiles'.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from marl_render.envs import make_env

SLOT_PLAN = ((2, {0: 7, 1: 8}), (5, {4: 7, 2: 9, 1: 8}), (3, {2: 9}))  # tests/test_levels.py
MODES = {"tiles": {}, "layers": {"layered": True}, "exact": {"exact_tiles": True}}


def slots(task: str, resolution: int) -> None:
    for mode, options in MODES.items():
        seen = {}
        for worlds, plan in SLOT_PLAN:
            with make_env(task, num_worlds=worlds, resolution=resolution, levels="test", seed=123,
                          appearance="train", **options) as e:
                e.reset()
                for _ in range(2):
                    e.step(e.random_actions())
                mask = torch.zeros(worlds, dtype=torch.bool)
                ids = torch.zeros(worlds, dtype=torch.int64)
                for slot, level in plan.items():
                    mask[slot], ids[slot] = True, level
                pixels = e.reset_to_level(mask, ids)["pixels"]
                for slot, level in plan.items():
                    seen.setdefault(level, []).append(pixels[slot].clone())
        report = {level: [int((p != pictures[0]).any(-1).sum()) for p in pictures[1:]]
                  for level, pictures in sorted(seen.items())}
        print(f"{task} {resolution} px {mode}: pixels differing from the level's first picture {report}", flush=True)


def cost(task: str, worlds: int, resolution: int, steps: int) -> None:
    envs = {mode: make_env(task, num_worlds=worlds, resolution=resolution, seed=0, **options)
            for mode, options in MODES.items()}
    frame = {mode: [] for mode in envs}
    cpu = {mode: [] for mode in envs}
    try:
        for e in envs.values():
            e.reset()
        for step in range(steps):
            for mode in (list(envs) if step % 2 == 0 else list(envs)[::-1]):
                started = time.process_time()
                envs[mode].step(envs[mode].random_actions())
                cpu[mode].append((time.process_time() - started) * 1000)
                frame[mode].append(sum(envs[mode].renderer.last_timings.values()) * 1000)
    finally:
        for e in envs.values():
            e.close()
    parts = []
    for mode in envs:
        f, c = statistics.median(frame[mode]), statistics.median(cpu[mode])
        parts.append(f"{mode} frame {f:.1f} ms (x{f / statistics.median(frame['tiles']):.2f}), "
                     f"step CPU {c:.1f} ms (x{c / statistics.median(cpu['tiles']):.2f})")
    print(f"{task} {worlds} worlds {resolution} px: " + "; ".join(parts), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("slots", "cost"))
    parser.add_argument("tasks", nargs="+")
    parser.add_argument("--worlds", type=int, default=64)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--steps", type=int, default=21)
    args = parser.parse_args()
    for task in args.tasks:
        slots(task, args.resolution) if args.what == "slots" else cost(task, args.worlds, args.resolution, args.steps)


if __name__ == "__main__":
    main()
