"""Environment throughput as a fraction of an independent raw-GL floor, in the same process.

The floor (marl_render/bench/floor_gl.py) is a minimal moderngl harness that shares no
code with the renderer: it draws the env's scene in the env's current state (bodies,
cameras, colours, lighting) with its own shaders, layout and readback, into a
preallocated batch. Per world size, the env (random actions, autoreset: physics +
render + readback, everything a training loop pays) and the floor (pack + upload +
draw + readback, no physics) run in alternating timed blocks, several rounds, and the
medians are compared: ratio = env-steps/s / floor frames/s (a frame = one step of every
world). The floor runs twice, without and with frustum culling, and the faster of the
two is the floor (culling pays in the arena scenes, not in cart-pole). Each env row
also carries the renderer's median stage times per step (pack,
cull, gl, copy; `update`: validating and storing the new poses), the task's physics and
rules (`physics`: Scenario.step) and the rest of the env's code outside the renderer
(`env`: the driver, actions, observations, instance data), the fixed cost that dominates
at small batches.
"""
from __future__ import annotations

import statistics
import time

import torch

from marl_render.util.threads import single_threaded

from .common import (
    env_spec_argument,
    machine,
    positive_int_argument,
    positive_seconds_argument,
    progress,
    write_report,
)

# update: BatchRenderer.update calls; the rest: last_timings
STAGES = ("update", "pack", "cull", "draw", "read", "copy")


def add_arguments(parser):
    # Every argument is checked here, before any env is built or timed.
    parser.add_argument("--env", nargs="+", default=["cartpole", "spread:4"], type=env_spec_argument,
                        help="environments as NAME or NAME:AGENTS, or 'all' (every registered env, default agents)")
    parser.add_argument("--worlds", type=positive_int_argument, nargs="+", default=[16, 64, 256, 1024])
    parser.add_argument("--resolution", type=positive_int_argument, default=64)
    parser.add_argument("--rounds", type=positive_int_argument, default=5, help="alternating env/floor blocks per size")
    parser.add_argument("--block-seconds", type=positive_seconds_argument, default=0.4,
                        help="about how long one timed block runs")
    parser.add_argument("--compile-physics", action="store_true",
                        help="make_env(compile_physics=True) for the tasks that have a compiled kernel (cartpole)")
    parser.add_argument("--out", default=None, help="also write DIR/floor.json")


def _timed_block(function, count: int) -> tuple[float, float]:
    """(wall, CPU) seconds per call; CPU time counts every thread of the process (the
    rasteriser's too) and is less disturbed by other processes than wall time."""
    start, cpu = time.perf_counter(), time.process_time()
    for _ in range(count):
        function()
    return (time.perf_counter() - start) / count, (time.process_time() - cpu) / count


def _timed(function, spent: dict, key: str):
    """`function`, adding the seconds each call takes to spent[key]."""
    def timed(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            spent[key] += time.perf_counter() - start
    return timed


def measure(name: str, worlds: int, agents: int | None, resolution: int, rounds: int, block_seconds: float,
            compile_physics: bool = False) -> dict:
    from marl_render.envs import make_env, registry

    from .floor_gl import from_env

    kwargs = dict(num_worlds=worlds, resolution=resolution, seed=0, autoreset="next_step")
    if agents is not None:
        kwargs["num_agents"] = agents
    if compile_physics and registry.has_compiled_physics(name):
        kwargs["compile_physics"] = True
    env = make_env(name, **kwargs)
    floors = {}
    generator = torch.Generator().manual_seed(0)
    stages = {key: [] for key in STAGES + ("physics", "env")}

    # Instrumentation of this benchmark only: seconds spent in the renderer's pose updates and
    # in the task's physics and rules (Scenario.step) during one env step.
    spent = {"update": 0.0, "physics": 0.0}
    env.renderer.update = _timed(env.renderer.update, spent, "update")
    env.scenario.step = _timed(env.scenario.step, spent, "physics")

    def env_step():
        spent.update(update=0.0, physics=0.0)
        start = time.perf_counter()
        env.step(env.random_actions(generator))
        total = time.perf_counter() - start
        timings = dict(env.renderer.last_timings, update=spent["update"])
        for key in STAGES:
            stages[key].append(timings.get(key, 0.0))
        stages["physics"].append(spent["physics"])
        stages["env"].append(total - spent["physics"] - sum(timings.get(key, 0.0) for key in STAGES))

    try:
        env.reset(seed=0)
        for _ in range(3):
            env_step()
        for cull in (False, True):
            floors[cull] = from_env(env, cull=cull)
            with single_threaded():
                for _ in range(3):
                    floors[cull].render()
        probe, _ = _timed_block(env_step, 3)
        count = max(3, min(200, round(block_seconds / probe)))
        for values in stages.values():
            values.clear()
        env_times, floor_times = [], {cull: [] for cull in floors}
        for _ in range(rounds):
            env_times.append(_timed_block(env_step, count))
            for cull, floor in floors.items():
                with single_threaded():  # as the env runs its own torch work
                    floor_times[cull].append(_timed_block(floor.render, count))
    finally:
        for floor in floors.values():
            floor.close()
        env.close()
    env_seconds, env_cpu = (statistics.median(t[i] for t in env_times) for i in (0, 1))
    floor_by_cull = {cull: statistics.median(t[0] for t in times) for cull, times in floor_times.items()}
    cull = min(floor_by_cull, key=floor_by_cull.get)
    floor_seconds = floor_by_cull[cull]
    floor_cpu = statistics.median(t[1] for t in floor_times[cull])
    return {"env": name, "worlds": worlds, "agents": env.num_agents, "resolution": resolution,
            "physics_compiled": env.physics_compiled,
            "steps_per_block": count, "rounds": rounds,
            "env_steps_per_s": worlds / env_seconds, "floor_frames_per_s": worlds / floor_seconds,
            "ratio": floor_seconds / env_seconds, "env_ms_per_step": 1e3 * env_seconds,
            "floor_ms_per_frame": 1e3 * floor_seconds, "floor_culls": cull,
            "floor_ms_without_culling": 1e3 * floor_by_cull[False], "floor_ms_with_culling": 1e3 * floor_by_cull[True],
            "cpu_ratio": floor_cpu / env_cpu, "env_cpu_ms_per_step": 1e3 * env_cpu,
            "floor_cpu_ms_per_frame": 1e3 * floor_cpu,
            "best_ratio": min(t[0] for t in floor_times[cull]) / min(t[0] for t in env_times),
            "stages_ms": {key: 1e3 * statistics.median(values) for key, values in stages.items()}}


def run(args) -> dict:
    from marl_render.envs import list_envs

    specs = list_envs() if args.env == ["all"] else args.env
    rows = []
    for worlds in args.worlds:
        for spec in specs:
            name, _, agents = spec.partition(":")
            progress(f"floor: {spec}, {worlds} worlds at {args.resolution}px")
            rows.append(measure(name, worlds, int(agents) if agents else None, args.resolution, args.rounds,
                                args.block_seconds, args.compile_physics))
    result = {"benchmark": "floor", "machine": machine(), "results": rows}
    if args.out:
        write_report(args.out, "floor", result, markdown(rows))
    return result


def markdown(rows: list[dict]) -> list[str]:
    """The ratio table and the per-step stage table of a run."""
    lines = ["| env | agents | worlds | env-steps/s | floor frames/s | ratio | ratio of best blocks | CPU-time ratio |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {_label(r)} | {r['agents']} | {r['worlds']} | {r['env_steps_per_s']:,.0f} | "
              f"{r['floor_frames_per_s']:,.0f} | **{r['ratio']:.2f}** | {r['best_ratio']:.2f} | {r['cpu_ratio']:.2f} |"
              for r in rows]
    lines += ["", "| env | agents | worlds | ms/step | " + " | ".join(STAGES + ("physics", "env")) + " |",
              "|---|---:|---:|---:|" + "---:|" * (len(STAGES) + 2)]
    lines += [f"| {_label(r)} | {r['agents']} | {r['worlds']} | {r['env_ms_per_step']:.2f} | "
              + " | ".join(f"{r['stages_ms'][k]:.2f}" for k in STAGES + ("physics", "env")) + " |" for r in rows]
    return lines


def _label(row: dict) -> str:
    return row["env"] + (" (compiled physics)" if row.get("physics_compiled") else "")
