"""Environment throughput as a fraction of a raw OpenGL floor, in the same run.

For each environment: the env is reset and stepped with random actions (physics +
pose upload + render + readback, everything a training loop pays). The floor renders
the same scene — geometry, shaders, tile layout, resolution, the env's current
instance data and cameras — through marl_render.rawgl (moderngl on EGL, no Panda3D,
no physics, no Python per object): clear + draw + one readback per frame. Reported:
env-steps/s, floor frames/s (a frame = one step of every world) and their ratio.
Runs alternate in blocks so that both see the same machine load.
"""
from __future__ import annotations

import statistics
import time

import torch

from ..threads import single_threaded
from .common import machine, progress


def add_arguments(parser):
    parser.add_argument("--env", nargs="+", default=["spread", "cartpole"])
    parser.add_argument("--worlds", type=int, default=256)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--steps", type=int, default=20, help="steps per timed block")
    parser.add_argument("--repeats", type=int, default=3, help="alternating blocks per side")


def _floor_renderer(env):
    """A raw-GL renderer of the env's scene holding the env's current instances and cameras."""
    from marl_render.rawgl import RawGLRenderer

    source = env.renderer
    floor = RawGLRenderer(source.scene)
    for name in source.scene.groups:
        floor.update(name, **source.instance_state(name))
    if source.scene.camera_mount is None:
        floor.set_cameras(position=source.camera_position, rotation=source.camera_rotation)
    floor.set_cameras(fov_y=source.fov_y, near=source.near, far=source.far)
    return floor


def measure(name: str, worlds: int, resolution: int, steps: int, repeats: int) -> dict:
    from marl_render.envs import make_env

    # next_step: one render per step, like the floor (same_step draws twice on a step where a world ends)
    env = make_env(name, num_worlds=worlds, resolution=resolution, seed=0, autoreset="next_step")
    generator = torch.Generator().manual_seed(0)
    try:
        env.reset(seed=0)
        for _ in range(3):
            env.step(env.random_actions(generator))
        floor = _floor_renderer(env)
        for _ in range(3):
            floor.render()
        env_times, floor_times = [], []
        for _ in range(repeats):
            start = time.perf_counter()
            for _ in range(steps):
                env.step(env.random_actions(generator))
            env_times.append((time.perf_counter() - start) / steps)
            start = time.perf_counter()
            with single_threaded():  # as the project's renderer does
                for _ in range(steps):
                    floor.render()
            floor_times.append((time.perf_counter() - start) / steps)
        floor.close()
    finally:
        env.close()
    env_seconds, floor_seconds = statistics.median(env_times), statistics.median(floor_times)
    return {"env": name, "worlds": worlds, "agents": env.num_agents, "resolution": resolution,
            "env_steps_per_s": worlds / env_seconds, "agent_frames_per_s": worlds * env.num_agents / env_seconds,
            "floor_frames_per_s": worlds / floor_seconds, "ms_per_step": env_seconds * 1e3,
            "floor_ms_per_frame": floor_seconds * 1e3, "ratio_to_floor": floor_seconds / env_seconds}


def run(args) -> dict:
    rows = []
    for name in args.env:
        progress(f"floor: {name}, {args.worlds} worlds at {args.resolution}px")
        rows.append(measure(name, args.worlds, args.resolution, args.steps, args.repeats))
    return {"benchmark": "floor", "machine": machine(), "results": rows}
