"""Spike: the envs' agents' views with BatchRenderer(layered=True) (PROTOTYPE, not an env option).

    python tools/layered_envs.py slots TASK... [--resolution 64]
    python tools/layered_envs.py cost TASK... [--worlds 64] [--resolution 64] [--steps 15]

The envs have no `layered` option: this tool swaps marl_render.BatchRenderer for one that turns
the agents' views' renderer (the one make_env gives `exact_tiles`) into a layered one.
slots: test levels 7, 8, 9 reset into several slots of batches of 2, 5 and 3 worlds (appearance
"train", seed 123, 2 random steps first: tests/test_levels.py's plan) -> per level, how many
pixels differ from its first picture, for the column of tiles and for layers.
cost: default, layered and exact_tiles envs open at once, steps alternated among them; the median
of the renderer's own time per frame (last_timings: draw and read back).
"""
from __future__ import annotations

import argparse
import statistics

import torch

import marl_render as mr
from marl_render.envs import make_env

SLOT_PLAN = ((2, {0: 7, 1: 8}), (5, {4: 7, 2: 9, 1: 8}), (3, {2: 9}))  # tests/test_levels.py
TILED_RENDERER = mr.BatchRenderer
MODE = {"views": "tiles"}  # how the next env's agents' views are drawn: tiles, layers or exact


def renderer(scene, **options):
    if "exact_tiles" in options:  # the agents' views (the overview renderer gets no such option)
        options["exact_tiles"] = MODE["views"] == "exact"
        options["layered"] = MODE["views"] == "layers"
    return TILED_RENDERER(scene, **options)


mr.BatchRenderer = renderer


def env(task, mode, **options):
    MODE["views"] = mode
    return make_env(task, exact_tiles=False, **options)


def slots(task: str, resolution: int) -> None:
    for mode in ("tiles", "layers"):
        seen = {}
        for worlds, plan in SLOT_PLAN:
            with env(task, mode, num_worlds=worlds, resolution=resolution, levels="test", seed=123,
                     appearance="train") as e:
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
        blank = any(p[0].float().std() == 0 for p in seen.values())
        print(f"{task} {resolution} px {mode}: pixels differing from the level's first picture {report}"
              f"{' BLANK PICTURE' if blank else ''}", flush=True)


def cost(task: str, worlds: int, resolution: int, steps: int) -> None:
    envs = {mode: env(task, mode, num_worlds=worlds, resolution=resolution, seed=0)
            for mode in ("tiles", "layers", "exact")}
    times = {mode: [] for mode in envs}
    try:
        for e in envs.values():
            e.reset()
        for step in range(steps):
            order = list(envs) if step % 2 == 0 else list(envs)[::-1]
            for mode in order:
                envs[mode].step(envs[mode].random_actions())
                times[mode].append(sum(envs[mode].renderer.last_timings.values()) * 1000)
    finally:
        for e in envs.values():
            e.close()
    med = {mode: statistics.median(t) for mode, t in times.items()}
    ratio = {mode: statistics.median([a / b for a, b in zip(times[mode], times["tiles"], strict=True)])
             for mode in ("layers", "exact")}
    print(f"{task} {worlds} worlds {resolution} px: tiles {med['tiles']:.1f} ms, layers {med['layers']:.1f} ms "
          f"(x{ratio['layers']:.2f}), exact_tiles {med['exact']:.1f} ms (x{ratio['exact']:.2f}) per frame", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("slots", "cost"))
    parser.add_argument("tasks", nargs="+")
    parser.add_argument("--worlds", type=int, default=64)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--steps", type=int, default=15)
    args = parser.parse_args()
    for task in args.tasks:
        slots(task, args.resolution) if args.what == "slots" else cost(task, args.worlds, args.resolution, args.steps)


if __name__ == "__main__":
    main()
