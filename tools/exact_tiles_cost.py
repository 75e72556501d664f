"""Render time of the agents' views with and without exact_tiles (docs/levels.md, docs/renderer.md).

    .venv/bin/python tools/exact_tiles_cost.py [--worlds 64] [--resolution 64] [--steps 20] TASK...

Per task: the median over `steps` random steps of the renderer's own time for one frame
(BatchRenderer.last_timings: draw and read back), default and exact_tiles=True, in one process.
"""
from __future__ import annotations

import argparse
import statistics

from marl_render.envs import make_env


def frame_ms(task: str, worlds: int, resolution: int, steps: int, exact: bool) -> float:
    with make_env(task, num_worlds=worlds, resolution=resolution, seed=0, exact_tiles=exact) as env:
        env.reset()
        times = []
        for _ in range(steps):
            env.step(env.random_actions())
            times.append(sum(env.renderer.last_timings.values()) * 1000)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tasks", nargs="+")
    parser.add_argument("--worlds", type=int, default=64)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args()
    for task in args.tasks:
        default, exact = (frame_ms(task, args.worlds, args.resolution, args.steps, e) for e in (False, True))
        print(f"{task}: default {default:.1f} ms, exact_tiles {exact:.1f} ms per frame ({exact / default:.1f}x)")


if __name__ == "__main__":
    main()
