"""Impostor quads per GL instance, one against impostors.QUADS_PER_INSTANCE, in one run:

    python tools/impostor_batches.py WORLDS [TASK[:AGENTS]] [RESOLUTION]

Two envs of the task (seed 0, the same random actions), built with QUADS_PER_INSTANCE = 1 and 16,
step in alternating timed blocks (7 rounds, medians of process CPU time per step); the pixels of
their first 5 steps must be the same bytes.
"""
from __future__ import annotations

import statistics
import sys
import time

import torch

import marl_render.render.impostors as impostors
from marl_render.envs import make_env


def main(worlds: int, spec: str = "commons:7", resolution: int = 88) -> None:
    task, _, agents = spec.partition(":")
    kwargs = {"num_agents": int(agents)} if agents else {}
    envs = {}
    for quads in (1, 16):
        impostors.QUADS_PER_INSTANCE = quads  # read when a renderer builds its groups
        envs[quads] = make_env(task, num_worlds=worlds, seed=0, resolution=resolution, **kwargs)
        envs[quads].reset(seed=0)
    generators = {quads: torch.Generator().manual_seed(0) for quads in envs}
    same = True
    for _ in range(5):
        pixels = {quads: env.step(env.random_actions(generators[quads]))[0]["pixels"] for quads, env in envs.items()}
        same &= torch.equal(pixels[1], pixels[16])
    steps, times = max(3, 240 // worlds), {quads: [] for quads in envs}
    for _ in range(7):
        for quads, env in envs.items():
            start = time.process_time()
            for _ in range(steps):
                env.step(env.random_actions(generators[quads]))
            times[quads].append((time.process_time() - start) / steps * 1e3)
    one, batched = (statistics.median(times[quads]) for quads in (1, 16))
    print(f"{task} {worlds} worlds {resolution} px ({len(envs[16].renderer._passes)} passes): same pixels {same}; "
          f"step CPU ms, 1 quad per instance {one:.2f}, 16: {batched:.2f} (ratio {batched / one:.3f})")
    for env in envs.values():
        env.close()


if __name__ == "__main__":
    main(int(sys.argv[1]), *sys.argv[2:3], *(int(a) for a in sys.argv[3:4]))
