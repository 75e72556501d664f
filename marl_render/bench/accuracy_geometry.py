"""What impostors change: pixel and depth error of the tasks' pictures against their meshes.

For every task whose scene has a sphere group (impostors.is_sphere) and every resolution, three
copies of the env play the same episode (same seed, same random actions, `--steps` steps of
`--worlds` worlds, depth on), differing only in how spheres are drawn:
- mesh: the task's own sphere meshes (impostors=False);
- impostor: the default, impostors="auto" (marl_render/render/impostors.py);
- fine: the spheres replaced by 64 x 32 meshes (impostors=False), the nearest a mesh gets to the
  sphere that both of the others stand for.
Per pair, over every frame: the mean absolute error per channel (0-255), the share of pixels
that differ by more than 8 levels in some channel, and the depth error (metres, where both
are finite: mean and 99.9th percentile), and the share of pixels where one sees something and
the other the sky. The render time of the mesh and impostor copies (BatchRenderer.render on the
same state, alternating, medians) comes from the same run.
--policies RUN_FOLDER...: published actors (python -m marl_render.baselines run folders) play their
task's env drawn with meshes, greedily, for `--steps` steps of `--worlds` worlds; on every step the
same actor (a second copy, its own frame stack) also decides from the impostor frame of the same
state. Reported: the share of (step, world, agent) decisions that agree, on the steps where the
actor decides (action_repeat).
"""
from __future__ import annotations

import contextlib
import os
import statistics
import time

import numpy as np
import torch

from ..assets.meshes import MeshData, sphere
from ..render.impostors import is_sphere
from .common import machine, positive_int_argument, progress, write_report
from .profile import cpu_model

TASKS = ("commons", "forage", "push")  # the built-in tasks with sphere groups


def add_arguments(parser):
    parser.add_argument("--env", nargs="*", default=list(TASKS), help="tasks (none: only --policies)")
    parser.add_argument("--resolution", nargs="+", type=positive_int_argument, default=[64, 88])
    parser.add_argument("--worlds", type=positive_int_argument, default=8)
    parser.add_argument("--steps", type=positive_int_argument, default=30)
    parser.add_argument("--policies", nargs="*", default=[], help="run folders of published actors (agreement)")
    parser.add_argument("--out", default=None, help="also write DIR/accuracy_geometry.json and .md")


@contextlib.contextmanager
def fine_spheres():
    """Envs built inside draw every sphere group with a 64 x 32 sphere mesh."""
    from marl_render.envs.rendering import EnvRenderer

    original = EnvRenderer._scene

    def scene(self, overview, resolution, effects):
        built = original(self, overview, resolution, effects)
        for group in list(built.static.values()) + list(built.groups.values()):
            if is_sphere(group.mesh):
                group.mesh = sphere(segments=64, rings=32)
        return built

    EnvRenderer._scene = scene
    try:
        yield
    finally:
        EnvRenderer._scene = original


def _pair_errors(a: list, b: list) -> dict:
    rgb_a, rgb_b = torch.stack([f[0] for f in a]).float(), torch.stack([f[0] for f in b]).float()
    depth_a, depth_b = torch.stack([f[1] for f in a]), torch.stack([f[1] for f in b])
    difference = (rgb_a - rgb_b).abs()
    finite = torch.isfinite(depth_a) & torch.isfinite(depth_b)
    depth_error = (depth_a - depth_b)[finite].abs().numpy()
    return {"mae": float(difference.mean()), "pixels_over_8": float((difference.amax(-1) > 8).float().mean()),
            "depth_mae_m": float(depth_error.mean()) if depth_error.size else 0.0,
            "depth_p999_m": float(np.quantile(depth_error, 0.999)) if depth_error.size else 0.0,
            "silhouette_pixels": float((torch.isfinite(depth_a) != torch.isfinite(depth_b)).float().mean())}


def measure(name: str, resolution: int, worlds: int, steps: int) -> dict:
    from marl_render.envs import make_env

    kwargs = dict(num_worlds=worlds, resolution=resolution, seed=0, depth=True, autoreset="next_step")
    envs = {"mesh": make_env(name, impostors=False, **kwargs), "impostor": make_env(name, **kwargs)}
    with fine_spheres():
        envs["fine"] = make_env(name, impostors=False, **kwargs)
    frames = {key: [] for key in envs}
    times = {"mesh": [], "impostor": []}
    try:
        if not envs["impostor"].renderer.impostor_groups:
            raise ValueError(f"{name} draws no sphere group as impostors")
        observations = {key: env.reset(seed=0) for key, env in envs.items()}
        generators = {key: torch.Generator().manual_seed(1) for key in envs}
        for _ in range(steps):
            for key, env in envs.items():
                observations[key] = env.step(env.random_actions(generators[key]))[0]
                frames[key].append((observations[key]["pixels"].clone(), observations[key]["depth"].clone()))
            for key in times:  # the same state drawn again: render time alone
                start = time.perf_counter()
                envs[key].renderer.render()
                times[key].append(time.perf_counter() - start)
        groups = sorted(envs["impostor"].renderer.impostor_groups)
        spheres = {g: len(envs["mesh"].renderer.scene.groups[g].mesh.triangles) for g in groups
                   if isinstance(envs["mesh"].renderer.scene.groups[g].mesh, MeshData)}
    finally:
        for env in envs.values():
            env.close()
    mesh_ms, impostor_ms = (1e3 * statistics.median(times[k]) for k in ("mesh", "impostor"))
    return {"env": name, "resolution": resolution, "worlds": worlds, "steps": steps, "impostor_groups": groups,
            "sphere_triangles": spheres, "render_ms_mesh": mesh_ms, "render_ms_impostor": impostor_ms,
            "impostor_vs_mesh": _pair_errors(frames["impostor"], frames["mesh"]),
            "impostor_vs_fine": _pair_errors(frames["impostor"], frames["fine"]),
            "mesh_vs_fine": _pair_errors(frames["mesh"], frames["fine"])}


def policy_agreement(run_folder: str, worlds: int, steps: int) -> dict:
    """Share of the actor's greedy decisions that are the same from impostor frames as from mesh frames."""
    from marl_render.envs import make_env
    from marl_render.populations.policies import joint_actions, load_policy

    on_meshes, on_impostors = load_policy(run_folder), load_policy(run_folder)
    kwargs = dict(on_meshes.env_kwargs, num_worlds=worlds, seed=0, autoreset="next_step")
    envs = (make_env(on_meshes.task, impostors=False, **kwargs), make_env(on_meshes.task, **kwargs))
    agree = decided = 0
    try:
        observations = [env.reset(seed=0) for env in envs]
        for _ in range(steps):
            decides = envs[0].step_count % on_meshes.action_repeat == 0
            actions = joint_actions(on_meshes, envs[0], observations[0])
            other = joint_actions(on_impostors, envs[1], observations[1])
            agree += int((actions == other)[decides].sum())
            decided += int(decides.sum()) * envs[0].num_agents
            on_impostors.held.copy_(on_meshes.held)  # both hold the actions the env played
            observations = [env.step(actions)[0] for env in envs]
    finally:
        for env in envs:
            env.close()
    return {"run": run_folder, "task": on_meshes.task, "worlds": worlds, "steps": steps, "decisions": decided,
            "agreement": agree / max(decided, 1)}


def run(args) -> dict:
    load_before = os.getloadavg()[0]
    results = []
    for name in args.env:
        for resolution in args.resolution:
            progress(f"accuracy of impostors: {name} at {resolution} px")
            results.append(measure(name, resolution, args.worlds, args.steps))
    result = {"machine": {**machine(), "cpu_model": cpu_model(), "cpus": os.cpu_count()},
              "load_average_before": load_before, "load_average_after": os.getloadavg()[0], "results": results,
              "policies": [policy_agreement(folder, args.worlds, args.steps) for folder in args.policies]}
    if args.out:
        write_report(args.out, "accuracy_geometry", result, markdown=markdown(result))
    return result


def markdown(result: dict) -> list[str]:
    m = result["machine"]
    lines = [f"CPU: {m['cpu_model']}, {m['cpus']} CPUs; load average {result['load_average_before']:.1f} before, "
             f"{result['load_average_after']:.1f} after.", "",
             "| env | px | spheres as | against | MAE (0-255) | pixels > 8 levels | depth MAE (m) "
             "| depth p99.9 (m) | silhouette pixels | render ms mesh -> impostor |",
             "|---|---:|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in result["results"]:
        for pair, (drawn, against) in (("impostor_vs_mesh", ("impostor", "task's mesh")),
                                       ("impostor_vs_fine", ("impostor", "64x32 mesh")),
                                       ("mesh_vs_fine", ("task's mesh", "64x32 mesh"))):
            e = r[pair]
            timing = f"{r['render_ms_mesh']:.2f} -> {r['render_ms_impostor']:.2f}" if pair == "impostor_vs_mesh" else ""
            lines.append(f"| {r['env']} | {r['resolution']} | {drawn} | {against} | {e['mae']:.3f} "
                         f"| {e['pixels_over_8']:.4%} | {e['depth_mae_m']:.5f} | {e['depth_p999_m']:.4f} "
                         f"| {e['silhouette_pixels']:.4%} | {timing} |")
    if result.get("policies"):
        lines += ["", "| actor | task | decisions | same greedy action from impostor frames |", "|---|---|---:|---:|"]
        lines += [f"| {p['run']} | {p['task']} | {p['decisions']:,} | {p['agreement']:.2%} |"
                  for p in result["policies"]]
    return lines
