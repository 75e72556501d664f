"""Where the GL stage's time goes: vertex work against fragment work, per task and resolution.

For each env and resolution the same state (seed 0, three steps of the same random actions) is
drawn by several copies of the env that differ in one thing only:
- triangles at fixed coverage: every mesh of the scene subdivided `k` times (each triangle split
  into 4 at its edge midpoints: the same surface, the same pixels, 4**k the triangles);
- coverage at fixed triangles: the resolution scaled (the same meshes, f**2 the pixels).
The copies' renders (`BatchRenderer.render()`: pack, draw, read back) alternate in timed blocks
(several rounds, medians), so the ratios come from one run on however loaded a machine. llvmpipe bins
triangles in the calling thread and rasterises on its own threads until a read waits for them,
so the renderer's "draw" and "read" clocks split the GL work at no fixed place: the split is of
the whole render. A line fitted through render time against triangles submitted gives the
per-triangle cost (vertex shading, clipping, culling, binning: "vertex work"), one through render
time against pixels the per-pixel cost (rasterisation, fragment shading, clears, the readback:
"fragment work"); at the base setting vertex = slope x triangles, fragment = slope x pixels,
and the rest is what depends on neither (packing, draw calls, state changes between groups,
the sky copy). A full env step of the base setting (random actions, physics included) is timed
in the same rounds, to say what share of a step the render is. Times are CPU time of the
process (all threads), which a loaded machine disturbs far less than wall time (both kept).
Subdivided triangles are smaller than the originals, so the per-triangle slope is that of small
triangles (a lower bound for large ones, whose rasterisation the pixel slope counts).
"""
from __future__ import annotations

import contextlib
import math
import os
import statistics
import subprocess
import time

import numpy as np
import torch

from ..assets.meshes import MeshData
from ..render.impostors import is_sphere
from .common import (
    env_spec_argument,
    machine,
    positive_int_argument,
    positive_seconds_argument,
    progress,
    write_report,
)


def add_arguments(parser):
    parser.add_argument("--env", nargs="+", default=["commons", "capture_flag", "spread"], type=env_spec_argument,
                        help="environments as NAME or NAME:AGENTS")
    parser.add_argument("--resolution", nargs="+", type=positive_int_argument, default=[64, 88],
                        help="base resolutions (the tasks' default is 64)")
    parser.add_argument("--worlds", type=positive_int_argument, default=16)
    parser.add_argument("--subdivide", nargs="+", type=int, default=[0, 1, 2], choices=range(4),
                        help="subdivision levels of every mesh (4**k triangles, same coverage)")
    parser.add_argument("--coverage", nargs="+", type=float, default=[0.5, 1.0, 1.5],
                        help="resolution factors at the base triangles (must include 1)")
    parser.add_argument("--impostors", choices=["off", "auto"], default="off",
                        help="spheres as meshes (off: the split before impostors) or as impostors (the env default)")
    parser.add_argument("--rounds", type=positive_int_argument, default=5)
    parser.add_argument("--block-seconds", type=positive_seconds_argument, default=0.3)
    parser.add_argument("--groups", action="store_true",
                        help="also time an env step with each draw group hidden, with static groups drawn last and "
                             "with impostor groups never frustum-tested (what each group and choice costs)")
    parser.add_argument("--out", default=None, help="also write DIR/profile.json and DIR/profile.md")


def subdivided(mesh: MeshData, levels: int) -> MeshData:
    """`mesh` with each triangle split into 4 at its edge midpoints, `levels` times: the same
    surface (positions, normals and uvs interpolated linearly), 4**levels the triangles."""
    positions, normals, uvs, triangles = mesh.positions, mesh.normals, mesh.uvs, mesh.triangles
    for _ in range(levels):
        corners = [arrays[triangles] for arrays in (positions, normals, uvs)]  # each [T, 3, n]
        # per triangle: corners a b c, midpoints ab bc ca -> 6 vertices, 4 triangles
        six = [np.concatenate([c, 0.5 * (c + np.roll(c, -1, axis=1))], axis=1) for c in corners]
        positions, normals, uvs = (s.reshape(-1, s.shape[-1]) for s in six)
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        base = 6 * np.arange(len(triangles))[:, None, None]
        local = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])
        triangles = (base + local).reshape(-1, 3)
    return MeshData(mesh.name, np.ascontiguousarray(positions, np.float32), np.ascontiguousarray(normals, np.float32),
                    np.ascontiguousarray(uvs, np.float32), np.ascontiguousarray(triangles, np.int32))


@contextlib.contextmanager
def meshes_subdivided(levels: int, keep_spheres: bool = False):
    """Envs built inside get every procedural or loaded mesh of their agents' scene subdivided
    (but spheres, with keep_spheres: drawn as impostors, they are quads whatever their mesh)."""
    from marl_render.envs.rendering import EnvRenderer

    original = EnvRenderer._scene

    def scene(self, overview, resolution, effects):
        built = original(self, overview, resolution, effects)
        for group in list(built.static.values()) + list(built.groups.values()):
            if isinstance(group.mesh, MeshData) and not (keep_spheres and is_sphere(group.mesh)):
                group.mesh = subdivided(group.mesh, levels)
        return built

    EnvRenderer._scene = scene
    try:
        yield
    finally:
        EnvRenderer._scene = original


def submitted_triangles(renderer) -> int:
    """Triangles handed to the GL per frame before culling: every view draws its world's instances
    (an impostor instance is 2)."""
    scene = renderer.scene

    def triangles(group) -> int:
        return 2 if group.name in renderer.impostor_groups else len(group.mesh.triangles)
    per_view = sum(triangles(g) * g.count for g in scene.static.values() if isinstance(g.mesh, MeshData))
    per_view += sum(triangles(g) * g.capacity for g in scene.groups.values() if isinstance(g.mesh, MeshData))
    return per_view * scene.num_views


def cpu_model() -> str:
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return next((line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("Model name")),
                "unknown")


def _block(function, count: int) -> tuple[float, float]:
    """(wall, CPU) seconds per call; CPU time counts every thread of the process (llvmpipe's
    rasteriser threads too) and is far less disturbed by other processes than wall time."""
    start, cpu = time.perf_counter(), time.process_time()
    for _ in range(count):
        function()
    return (time.perf_counter() - start) / count, (time.process_time() - cpu) / count


def _slope(xs, ys) -> float:
    """The fitted cost per unit; NaN from a single setting (--subdivide 0 or --coverage 1 alone: no split)."""
    if len(set(xs)) < 2:
        return float("nan")
    return float(np.polyfit(np.asarray(xs, float), np.asarray(ys, float), 1)[0])


def profile(name: str, agents: int | None, worlds: int, resolution: int, levels, factors, rounds: int,
            block_seconds: float, impostors: str = "off") -> dict:
    from marl_render.envs import make_env

    variants = [(k, resolution) for k in levels]
    variants += [(0, max(8, round(resolution * f))) for f in factors if f != 1.0]
    kwargs = dict(num_worlds=worlds, seed=0, autoreset="next_step", impostors=impostors == "auto")
    if agents is not None:
        kwargs["num_agents"] = agents
    envs, stepper = {}, None
    try:
        for level, res in variants:
            with meshes_subdivided(level, keep_spheres=impostors == "auto"):
                env = envs[level, res] = make_env(name, resolution=res, **kwargs)
            env.reset(seed=0)
            generator = torch.Generator().manual_seed(0)
            for _ in range(3):
                env.step(env.random_actions(generator))
        stepper = make_env(name, resolution=resolution, **kwargs)
        stepper.reset(seed=0)
        generator = torch.Generator().manual_seed(1)

        def step():
            stepper.step(stepper.random_actions(generator))

        timings = {key: {"render": [], "render_cpu": [], "draw": [], "read": []} for key in variants}
        step_times = []
        counts = {}
        for key, env in envs.items():
            env.renderer.render()
            counts[key] = max(2, min(200, round(block_seconds / _block(env.renderer.render, 2)[0])))
        step_count = max(2, min(200, round(block_seconds / _block(step, 2)[0])))
        for _ in range(rounds):
            for key, env in envs.items():
                draws, reads = [], []

                def render(renderer=env.renderer, draws=draws, reads=reads):
                    renderer.render()
                    draws.append(renderer.last_timings["draw"])
                    reads.append(renderer.last_timings["read"])
                wall, cpu = _block(render, counts[key])
                timings[key]["render"].append(wall)
                timings[key]["render_cpu"].append(cpu)
                timings[key]["draw"].append(statistics.median(draws))
                timings[key]["read"].append(statistics.median(reads))
            step_times.append(_block(step, step_count)[1])
        rows = []
        for (level, res), env in envs.items():
            medians = {stage: 1e3 * statistics.median(values) for stage, values in timings[level, res].items()}
            rows.append({"subdivide": level, "resolution": res, "triangles": submitted_triangles(env.renderer),
                         "pixels": env.renderer.scene.num_views * res * res,
                         **{f"{stage}_ms": value for stage, value in medians.items()}})
        num_agents = envs[variants[0]].num_agents
    finally:
        for env in envs.values():
            env.close()
        if stepper is not None:
            stepper.close()
    base = next(r for r in rows if r["subdivide"] == 0 and r["resolution"] == resolution)
    by_triangles = [r for r in rows if r["resolution"] == resolution]
    by_pixels = [r for r in rows if r["subdivide"] == 0]
    per_triangle = _slope([r["triangles"] for r in by_triangles], [r["render_cpu_ms"] for r in by_triangles])
    per_pixel = _slope([r["pixels"] for r in by_pixels], [r["render_cpu_ms"] for r in by_pixels])
    vertex = per_triangle * base["triangles"]
    fragment = per_pixel * base["pixels"]
    split = {"ns_per_triangle": 1e6 * per_triangle, "ns_per_pixel": 1e6 * per_pixel, "vertex_ms": vertex,
             "fragment_ms": fragment, "rest_ms": base["render_cpu_ms"] - vertex - fragment,
             "vertex_share": vertex / base["render_cpu_ms"], "fragment_share": fragment / base["render_cpu_ms"]}
    split = {key: None if math.isnan(value) else value for key, value in split.items()}  # JSON has no NaN
    return {"env": name, "agents": num_agents, "worlds": worlds, "resolution": resolution,
            "step_cpu_ms": 1e3 * statistics.median(step_times), "render_ms": base["render_ms"],
            "render_cpu_ms": base["render_cpu_ms"],
            "draw_ms": base["draw_ms"], "read_ms": base["read_ms"], "triangles": base["triangles"],
            "pixels": base["pixels"], **split,
            "variants": rows}


def run(args) -> dict:
    if 1.0 not in args.coverage or 0 not in args.subdivide:
        raise SystemExit("error: --coverage must include 1 and --subdivide must include 0 (the base setting)")
    load_before = os.getloadavg()
    started = time.perf_counter()
    results = []
    for spec in args.env:
        name, _, agents = spec.partition(":")
        for resolution in args.resolution:
            progress(f"profile {name} at {resolution} px, {args.worlds} worlds")
            results.append(profile(name, int(agents) if agents else None, args.worlds, resolution, args.subdivide,
                                   args.coverage, args.rounds, args.block_seconds, args.impostors))
            if args.groups:
                progress(f"profile {name} at {resolution} px, {args.worlds} worlds: draw groups")
                results[-1]["groups"] = group_costs(name, int(agents) if agents else None, args.worlds, resolution,
                                                    args.rounds, args.block_seconds, args.impostors)
    result = {"machine": {**machine(), "cpu_model": cpu_model(), "cpus": os.cpu_count()},
              "load_average_before": load_before[0], "load_average_after": os.getloadavg()[0],
              "seconds": time.perf_counter() - started, "impostors": args.impostors, "rounds": args.rounds,
              "worlds": args.worlds,
              "results": results}
    if args.out:
        write_report(args.out, "profile", result, markdown=markdown(result))
    return result


class _GroupVariants:
    """Switches of one env's renderer, each undone by `base()`: a draw group left out (its pairs are
    still packed and culled: what is left out is its GL work), static groups drawn after the moving
    ones (so that the depth test drops floor and wall pixels behind them before they are shaded), and
    impostor groups never frustum-tested (every candidate pair drawn). Reaches into the renderer's
    draw groups and packer on purpose: these are the choices being measured."""

    def __init__(self, renderer):
        self.renderer = renderer
        self.groups = renderer._groups
        self.orders = {name: [p[0].get_bin_draw_order() for p in draw.pass_nodes] for name, draw in self.groups.items()}
        self.names = ["base", *(f"hide {name}" for name in self.groups), "hide all", "static last"]
        if renderer.impostor_groups:
            self.names.append("impostors unculled")

    def base(self):
        for name, draw in self.groups.items():
            for (node, *_), order in zip(draw.pass_nodes, self.orders[name], strict=True):
                if node.is_stashed():
                    node.unstash()
                node.set_bin("fixed", order)
        for name in self.renderer.impostor_groups:
            self.renderer.packer.groups[name].frustum_pause = 0

    def set(self, variant: str):
        self.base()
        if variant.startswith("hide "):
            hidden = list(self.groups) if variant == "hide all" else [variant[len("hide "):]]
            for name in hidden:
                for node, *_ in self.groups[name].pass_nodes:
                    node.stash()  # not hide(): the renderer shows and hides nodes itself (draw_groups.set_draw)
        elif variant == "static last":
            count = len(self.groups)
            for name, draw in self.groups.items():
                for (node, *_), order in zip(draw.pass_nodes, self.orders[name], strict=True):
                    # Surfaces with patterns already sort after everything (order >= count): kept there.
                    node.set_bin("fixed", order + count if draw.static and order < count else order)
        elif variant == "impostors unculled":
            for name in self.renderer.impostor_groups:
                self.renderer.packer.groups[name].frustum_pause = 1 << 30
        # The next frame packs and culls again, as after a step.
        self.renderer.packer._cameras_dirty = True


def group_costs(name: str, agents: int | None, worlds: int, resolution: int, rounds: int, block_seconds: float,
                impostors: str = "auto") -> dict:
    """CPU ms of an env step (random actions) under each of _GroupVariants' switches, alternated in
    timed blocks (medians over rounds), and whether the frame of one state is the same byte for byte
    under "static last" and "impostors unculled" as under base."""
    from marl_render.envs import make_env

    kwargs = dict(num_worlds=worlds, seed=0, autoreset="next_step", impostors=impostors == "auto")
    if agents is not None:
        kwargs["num_agents"] = agents
    with make_env(name, resolution=resolution, **kwargs) as env:
        env.reset(seed=0)
        generator = torch.Generator().manual_seed(0)

        def step():
            env.step(env.random_actions(generator))
        for _ in range(3):
            step()
        variants = _GroupVariants(env.renderer)
        frames = {}
        for variant in ("base", "static last", "impostors unculled"):
            if variant in variants.names:
                variants.set(variant)
                frame = env.renderer.render()
                frames[variant] = bytes(frame.rgb.numpy().tobytes())
        variants.set("base")
        count = max(2, min(200, round(block_seconds / _block(step, 2)[1])))
        timings = {variant: [] for variant in variants.names}
        for _ in range(rounds):
            for variant in variants.names:
                variants.set(variant)
                timings[variant].append(_block(step, count)[1])
        variants.set("base")
    medians = {variant: 1e3 * statistics.median(values) for variant, values in timings.items()}
    return {"step_cpu_ms": medians, "delta_ms": {v: medians[v] - medians["base"] for v in medians},
            "same_frame": {v: frames[v] == frames["base"] for v in frames if v != "base"}}


def markdown(result: dict) -> list[str]:
    m = result["machine"]
    lines = [f"CPU: {m['cpu_model']}, {m['cpus']} CPUs, {m['gl_renderer']}; load average "
             f"{result['load_average_before']:.1f} before, {result['load_average_after']:.1f} after; "
             f"{result['worlds']} worlds, {result['rounds']} rounds, medians; impostors {result['impostors']}.", "",
             "| env | A | px | step CPU ms | render CPU ms | vertex ms (share) | fragment ms (share) | rest ms "
             "| triangles/frame | ns/triangle | ns/pixel |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result["results"]:
        split = r["vertex_ms"] is not None and r["fragment_ms"] is not None  # None: one setting, no fit
        vertex = f"{r['vertex_ms']:.2f} ({r['vertex_share']:.0%})" if split else ""
        fragment = f"{r['fragment_ms']:.2f} ({r['fragment_share']:.0%})" if split else ""
        rest = f"{r['rest_ms']:.2f}" if split else ""
        per_triangle = "" if r["ns_per_triangle"] is None else f"{r['ns_per_triangle']:.2f}"
        per_pixel = "" if r["ns_per_pixel"] is None else f"{r['ns_per_pixel']:.2f}"
        lines.append(f"| {r['env']} | {r['agents']} | {r['resolution']} | {r['step_cpu_ms']:.2f} "
                     f"| {r['render_cpu_ms']:.2f} | {vertex} | {fragment} | {rest} | {r['triangles']:,} "
                     f"| {per_triangle} | {per_pixel} |")
    grouped = [r for r in result["results"] if "groups" in r]
    if grouped:
        lines += ["", "Env step CPU ms under each switch (--groups) and its difference from base. "
                  "\"hide X\": X packed and culled but not drawn (its GL cost); \"static last\": static groups "
                  "drawn after moving ones; \"impostors unculled\": impostor groups never frustum-tested.", "",
                  "| env | px | variant | step CPU ms | difference | same frame as base |",
                  "|---|---:|---|---:|---:|---|"]
        for r in grouped:
            g = r["groups"]
            for variant, ms in g["step_cpu_ms"].items():
                same = g["same_frame"].get(variant)
                lines.append(f"| {r['env']} | {r['resolution']} | {variant} | {ms:.2f} | {g['delta_ms'][variant]:+.2f} "
                             f"| {'' if same is None else ('yes' if same else 'no')} |")
    return lines
