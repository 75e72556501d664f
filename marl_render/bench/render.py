"""Batched renderer against the plain Panda3D way on the same scene, in the same run.

Scene: a floor plane and --instances per world (the agents' capsules with their cameras
mounted, plus boxes), random poses every frame. The plain way: one buffer, one camera
and display region per view, one scene root per world with ordinary nodes moved by
Python calls, one readback (marl_render.bench.naive). Reports views/s of both and the ratio.
"""
from __future__ import annotations

from .common import RandomMotion, apply, arena_scene, machine, positive_int_argument, progress, time_per_call


def add_arguments(parser):
    parser.add_argument("--worlds", type=positive_int_argument, default=256)
    parser.add_argument("--agents", type=positive_int_argument, default=4)
    parser.add_argument("--resolution", type=positive_int_argument, default=64)
    parser.add_argument("--instances", type=positive_int_argument, default=10,
                        help="instances per world (agents included)")
    parser.add_argument("--steps", type=positive_int_argument, default=30)
    parser.add_argument("--baseline-steps", type=positive_int_argument, default=5)
    parser.add_argument("--no-baseline", action="store_true", help="skip the plain Panda3D way")


def run(args) -> dict:
    import marl_render as mr
    from marl_render.bench.naive import NaiveRenderer

    scene = arena_scene(args.worlds, args.agents, args.resolution, args.instances)
    views = scene.num_views
    result = {"benchmark": "render", "worlds": args.worlds, "agents": args.agents, "resolution": args.resolution,
              "instances_per_world": args.instances, "views": views, "machine": machine()}

    def measure(renderer, steps):
        motion = RandomMotion(scene, seed=0)

        def frame():
            apply(renderer, motion.next())
            renderer.render()

        return time_per_call(frame, steps)

    progress(f"batched: {views} views of {args.resolution}px, {args.steps} frames")
    with mr.BatchRenderer(scene) as renderer:
        seconds = measure(renderer, args.steps)
        result["passes"] = renderer.layout.num_passes
    result["batched"] = {"ms_per_frame": seconds * 1e3, "views_per_s": views / seconds}
    if not args.no_baseline:
        progress(f"plain Panda3D way: building {views} cameras, {args.baseline_steps} frames")
        naive = NaiveRenderer(scene)
        seconds = measure(naive, args.baseline_steps)
        naive.close()
        result["plain_panda3d"] = {"ms_per_frame": seconds * 1e3, "views_per_s": views / seconds}
        result["speedup"] = result["batched"]["views_per_s"] / result["plain_panda3d"]["views_per_s"]
    return result
