"""Environment throughput: physics + render + readback with random actions.

`--env all` runs every registered environment. env-steps/s counts world steps
(W per batched step); agent-frames/s counts rendered agent views.
"""
from __future__ import annotations

import time

import torch

from .common import machine, progress


def add_arguments(parser):
    parser.add_argument("--env", default="cartpole", help="environment name, or 'all'")
    parser.add_argument("--worlds", type=int, default=256)
    parser.add_argument("--agents", type=int, default=None, help="agents per world (env default if omitted)")
    parser.add_argument("--resolution", type=int, nargs="+", default=[64])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--continuous", action="store_true")


def measure(name: str, worlds: int, resolution: int, steps: int, agents=None, continuous=False) -> dict:
    from marl_render.envs import make_env

    kwargs = {"num_worlds": worlds, "resolution": resolution, "continuous": continuous, "seed": 0, "autoreset": True}
    if agents is not None:
        kwargs["num_agents"] = agents
    env = make_env(name, **kwargs)
    try:
        generator = torch.Generator().manual_seed(0)
        env.reset(seed=0)
        for _ in range(3):
            env.step(env.random_actions(generator))
        render_seconds = 0.0
        start = time.perf_counter()
        for _ in range(steps):
            env.step(env.random_actions(generator))
            render_seconds += sum(env.renderer.last_timings.values())
        seconds = (time.perf_counter() - start) / steps
        return {"env": name, "worlds": worlds, "agents": env.num_agents, "resolution": resolution,
                "ms_per_step": seconds * 1e3, "env_steps_per_s": worlds / seconds,
                "agent_frames_per_s": worlds * env.num_agents / seconds,
                "render_share": render_seconds / steps / seconds}
    finally:
        env.close()


def run(args) -> dict:
    from marl_render.envs import list_envs

    names = list_envs() if args.env == "all" else [args.env]
    rows = []
    for name in names:
        for resolution in args.resolution:
            progress(f"env {name}: {args.worlds} worlds at {resolution}px, {args.steps} steps")
            rows.append(measure(name, args.worlds, resolution, args.steps, args.agents, args.continuous))
    return {"benchmark": "env", "machine": machine(), "results": rows}
