"""Cost of each effect (on against off, same run) and the batching ablation.

Effects: the arena scene rendered with no effect, then with each effect alone, then all
of them; views/s and the cost relative to no effect.

Observation formats (lighting on): RGB channels last (as shipped), RGB channels first (a
transposing copy after the read), and gray (luma drawn by the shader, one channel read
straight into the batch in either layout).

Shadows: lighting + shadows at each --shadow-resolutions map size (PCF on and off), the
atlas redrawn every frame (every box moves); wall and CPU time relative to lighting
alone, the two alternated.

Appearance: the same scene with walls around it, lit, against the same with the "appearance"
effect and everything it does on (each world's light, sky, floor and wall colours and patterns,
object colour jitter; the agents' cameras jittered in fov, height and pitch), timed in
alternating blocks; views/s, the median ratio of block pairs and the load average. Also the
seconds to sample and set every world's look (what an env does when worlds reset).

Skinning: the agents of the same scene as skinned characters (random joint poses every
frame, linear-blend skinning in the vertex shader) against the same mesh rigid, timed in
alternating blocks; views/s and the cost relative to rigid.

Ablation, cumulative, on the same scene and poses:
  1. one camera per view     one offscreen buffer and readback per view (plain Panda3D)
  2. tiled display regions    one buffer, a display region per view (plain Panda3D)
  3. one instanced pass       BatchRenderer, each framebuffer read into a buffer, then copied
  4. direct readback          BatchRenderer as shipped (GL reads into the batch)
  5. several processes        step 4 in --processes spawned processes, worlds split
Writes effects.md, effects.json and effects.png into --out.
"""
from __future__ import annotations

import functools
import multiprocessing
import os
import time

import numpy as np
import torch
from tabulate import tabulate

from .common import RandomMotion, apply, arena_scene, machine, progress, time_per_call, write_report
from .common import positive_int_argument as count_argument  # a count >= 1
from .figures import pyplot

SECTIONS = ("effects", "shadows", "appearance", "skinning", "outputs", "ablation")
OUTPUTS = [("rgb", {}), ("rgb, channels first", {"channels_first": True}), ("gray", {"color": "gray"})]
EFFECT_SETS = [(), ("lighting",), ("texture",), ("fog",), ("depth",), ("segmentation",), ("log_depth",),
               ("lighting", "texture", "fog", "depth", "segmentation")]


def add_arguments(parser):
    parser.add_argument("--worlds", type=count_argument, default=64)
    parser.add_argument("--agents", type=count_argument, default=4)
    parser.add_argument("--resolution", type=count_argument, default=64)
    parser.add_argument("--steps", type=count_argument, default=20)
    parser.add_argument("--processes", type=count_argument, default=2)
    parser.add_argument("--shadow-resolutions", type=count_argument, nargs="*", default=[128, 256, 512, 1024],
                        help="shadow-map texels per side (per world) to measure; none: skip shadows")
    parser.add_argument("--rounds", type=count_argument, default=8,
                        help="alternating blocks per variant (appearance)")
    parser.add_argument("--sections", nargs="*", default=list(SECTIONS), choices=SECTIONS,
                        help="parts to measure (default: all)")
    parser.add_argument("--out", default="out/effects")


def _checker(size=32, cells=4):
    pattern = (np.indices((size, size)) // (size // cells)).sum(0) % 2
    return np.where(pattern[..., None] == 1, 230, 60).astype(np.uint8).repeat(3, axis=2)


def _scene(args, effects):
    scene = arena_scene(args.worlds, args.agents, args.resolution, effects=effects)
    if "texture" in effects:
        scene.groups["boxes"].texture = _checker()
    return scene


def _views_per_s(renderer, scene, steps):
    motion = RandomMotion(scene, seed=0)

    def frame():
        apply(renderer, motion.next())
        renderer.render()

    return scene.num_views / time_per_call(frame, steps)


def _shadow_costs(args, rounds: int = 3) -> list:
    """Per map resolution and PCF setting: lighting + shadows against lighting alone, timed
    in alternation (`rounds` times each, the fastest kept) so that load from elsewhere on a
    shared machine falls on both. CPU time (all threads of the process, llvmpipe's
    included) is reported too: it varies far less with such load than wall time."""
    import marl_render as mr

    rows = []
    for resolution in args.shadow_resolutions:
        for pcf in (False, True):
            progress(f"shadows: {resolution}px pcf={pcf}")
            plain = _scene(args, ("lighting",))
            scene = _scene(args, ("lighting", "shadows"))
            scene.shadows = mr.Shadows(resolution=resolution, pcf=pcf)
            with mr.BatchRenderer(plain) as base, mr.BatchRenderer(scene) as shaded:
                timings = {"base": [], "shadows": []}
                for _ in range(rounds):
                    timings["base"].append(_seconds_per_frame(base, plain, args.steps))
                    timings["shadows"].append(_seconds_per_frame(shaded, scene, args.steps))
            (base_wall, base_cpu), (wall, cpu) = (min(timings[k]) for k in ("base", "shadows"))
            rows.append({"resolution": resolution, "pcf": pcf, "atlas_texels": scene.num_worlds * resolution ** 2,
                         "views_per_s": scene.num_views / wall, "ms_per_frame": wall * 1e3,
                         "lighting_views_per_s": scene.num_views / base_wall, "cost_vs_lighting": wall / base_wall - 1,
                         "cpu_ms_per_frame": cpu * 1e3, "lighting_cpu_ms_per_frame": base_cpu * 1e3,
                         "cpu_cost_vs_lighting": cpu / base_cpu - 1})
    return rows


def _seconds_per_frame(renderer, scene, steps) -> tuple:
    """(wall, process CPU) seconds per frame of random motion, after 3 warm-up frames."""
    motion = RandomMotion(scene, seed=0)
    for _ in range(3):
        apply(renderer, motion.next())
        renderer.render()
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(steps):
        apply(renderer, motion.next())
        renderer.render()
    return (time.perf_counter() - wall) / steps, (time.process_time() - cpu) / steps


def _alternating_blocks(frame, renderers: dict, steps: int, rounds: int = 8) -> tuple[dict, dict]:
    """({label: [wall seconds per frame of each block]}, the same in process CPU seconds): frame(label)
    timed in blocks that alternate between the renderers (so that both see the same load on a shared
    machine; CPU time, llvmpipe's threads included, varies far less with that load); the renderers
    are closed."""
    seconds, cpu_seconds = {label: [] for label in renderers}, {label: [] for label in renderers}
    block = max(steps // 4, 2)
    try:
        for label in renderers:
            time_per_call(functools.partial(frame, label), 1, warmup=2)
        for _ in range(rounds):
            for label in renderers:
                cpu = time.process_time()
                seconds[label].append(time_per_call(functools.partial(frame, label), block, warmup=0))
                cpu_seconds[label].append((time.process_time() - cpu) / block)
    finally:
        for renderer in renderers.values():
            renderer.close()
    return seconds, cpu_seconds


def _appearance_scene(args, look):
    """arena_scene with its floor and four walls given roles, lit, with the appearance effect when
    look (a marl_render.Appearance) is given (its patterns compiled when it draws them)."""
    effects = ("lighting",) if look is None else ("lighting", "appearance")
    scene = arena_scene(args.worlds, args.agents, args.resolution, effects=effects, floor_role="floor")
    scene.surface_patterns = look is not None and look.textures
    half, height = 6.0, 1.0
    scene.add_static("walls", "box", position=[[half, 0, height / 2], [-half, 0, height / 2], [0, half, height / 2],
                                               [0, -half, height / 2]],
                     scale=[[0.2, 2 * half, height]] * 2 + [[2 * half, 0.2, height]] * 2, color=[0.55, 0.5, 0.45],
                     role="wall")
    return scene


def _set_look(renderer, look, ids: torch.Tensor) -> None:
    """What an env does at a reset: every world's look from its id, and its cameras' jitter."""
    params = look.sample(ids)
    renderer.set_appearance(**params.renderer_kwargs())
    scene, mount = renderer.scene, renderer.scene.camera_mount
    W, A = scene.num_worlds, scene.agents_per_world
    renderer.set_cameras(fov_y=(scene.fov_y * params.fov_scale[:, None]).expand(W, A),
                         mount_offset=torch.tensor(mount.offset, dtype=torch.float64)
                         + params.camera_height[:, None, None] * torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                         mount_pitch=(mount.pitch + params.camera_pitch[:, None]).expand(W, A))


def _appearance(args) -> dict:
    """The appearance effect against lighting alone, everything on ("on") and without the floor and
    wall patterns ("no_patterns"), in alternating blocks of frames: per variant views/s, wall and CPU
    ms per frame, and the median of its blocks' ratios to "off"."""
    import marl_render as mr
    from marl_render.util.threads import single_threaded

    variants = {"off": None, "on": mr.Appearance(), "no_patterns": mr.Appearance(textures=False)}
    ids = torch.arange(args.worlds, dtype=torch.int64)
    renderers, motions = {}, {}
    for label, look in variants.items():
        scene = _appearance_scene(args, look)
        renderers[label], motions[label] = mr.BatchRenderer(scene), RandomMotion(scene, seed=0)
        if look is not None:
            _set_look(renderers[label], look, ids)
    set_seconds = time_per_call(functools.partial(_set_look, renderers["on"], variants["on"], ids), 5, warmup=1)
    patterns = variants["on"].sample(ids)

    @single_threaded()
    def frame(label):
        apply(renderers[label], motions[label].next())
        renderers[label].render()

    load_before = os.getloadavg()
    seconds, cpu_seconds = _alternating_blocks(frame, renderers, args.steps, rounds=args.rounds)
    views = args.worlds * args.agents
    result = {"views": views, "patterned_floors": float((patterns.floor_pattern > 0).double().mean()),
              "patterned_walls": float((patterns.wall_pattern > 0).double().mean()),
              "set_appearance_ms": set_seconds * 1e3, "load_average_before": load_before}
    for label in variants:
        result[f"{label}_views_per_s"] = views / float(np.median(seconds[label]))
        result[f"{label}_ms_per_frame"] = float(np.median(seconds[label])) * 1e3
        result[f"{label}_cpu_ms_per_frame"] = float(np.median(cpu_seconds[label])) * 1e3
        if label == "off":
            continue
        for kind, timings in (("time", seconds), ("cpu", cpu_seconds)):
            ratios = [t / off for t, off in zip(timings[label], timings["off"], strict=True)]
            result[f"{kind}_ratios_{label}_off"] = ratios
            result[f"{kind}_ratio_{label}_off"] = float(np.median(ratios))
    result["cost_vs_off"] = result["time_ratio_on_off"] - 1
    result["cpu_cost_vs_off"] = result["cpu_ratio_on_off"] - 1
    result["load_average"] = os.getloadavg()
    return result


def _skinning(args) -> dict:
    """Skinned against rigid agents (the same character mesh), alternating blocks of frames."""
    import marl_render as mr
    from marl_render.util.threads import single_threaded
    from marl_render.util.transforms import normalize_quat

    character = mr.skinned_character()
    renderers, motions = {}, {}
    for label, mesh in (("skinned", character), ("rigid", character.rigid())):
        scene = _scene(args, ("lighting",))
        scene.groups["agents"].mesh = mesh
        renderers[label], motions[label] = mr.BatchRenderer(scene), RandomMotion(scene, seed=0)
    generator = torch.Generator().manual_seed(0)
    shape = (args.worlds, args.agents, character.num_joints, 4)

    @single_threaded()  # tiny tensors, as in the envs: the cores stay llvmpipe's, the timing steadier
    def frame(label):
        apply(renderers[label], motions[label].next())
        if label == "skinned":  # a random pose per agent: the joints are packed every frame
            joints = normalize_quat(torch.randn(shape, generator=generator) * torch.tensor([4.0, 1, 1, 1]))
            renderers[label].update("agents", joints=joints)
        renderers[label].render()

    seconds, _ = _alternating_blocks(frame, renderers, args.steps)
    views = args.worlds * args.agents
    # Medians over the blocks: the cost is the median of each block pair's ratio.
    cost = float(np.median([s / r - 1.0 for s, r in zip(seconds["skinned"], seconds["rigid"], strict=True)]))
    return {"mesh": character.name, "vertices": len(character.positions), "joints": character.num_joints,
            "influences": character.influences, "rigid_views_per_s": views / float(np.median(seconds["rigid"])),
            "skinned_views_per_s": views / float(np.median(seconds["skinned"])), "cost_vs_rigid": cost}


def _worker(arguments):
    """One process of the last ablation step: its share of the worlds, timed alone."""
    worlds, agents, resolution, steps, start_event = arguments
    import marl_render as mr

    class Args:
        pass

    args = Args()
    args.worlds, args.agents, args.resolution = worlds, agents, resolution
    scene = _scene(args, ("lighting",))
    with mr.BatchRenderer(scene) as renderer:
        motion = RandomMotion(scene, seed=0)
        for _ in range(3):
            apply(renderer, motion.next())
            renderer.render()
        start_event.wait()
        start = time.perf_counter()
        for _ in range(steps):
            apply(renderer, motion.next())
            renderer.render()
        return time.perf_counter() - start


def _several_processes(args) -> float:
    share = args.worlds // args.processes
    context = multiprocessing.get_context("spawn")
    with context.Manager() as manager:
        start_event = manager.Event()
        with context.Pool(args.processes) as pool:
            work = (share, args.agents, args.resolution, args.steps, start_event)
            pending = pool.map_async(_worker, [work] * args.processes)
            time.sleep(1.0)
            start_event.set()
            seconds = pending.get(timeout=600)
    return args.processes * share * args.agents * args.steps / max(seconds)


def run(args) -> dict:
    import marl_render as mr
    from marl_render.bench.naive import NaiveRenderer

    result = {"benchmark": "effects", "worlds": args.worlds, "agents": args.agents, "resolution": args.resolution,
              "views": args.worlds * args.agents, "machine": machine(), "effects": [], "outputs": [], "ablation": []}
    sections = set(args.sections)
    base = None
    for effects in EFFECT_SETS if "effects" in sections else ():
        label = "+".join(effects) or "none"
        progress(f"effects: {label}")
        scene = _scene(args, effects)
        with mr.BatchRenderer(scene) as renderer:
            rate = _views_per_s(renderer, scene, args.steps)
        base = base or rate
        result["effects"].append({"effects": label, "views_per_s": rate, "ms_per_frame": scene.num_views / rate * 1e3,
                                  "cost_vs_none": base / rate - 1.0})

    if "shadows" in sections:
        result["shadows"] = _shadow_costs(args)
    if "appearance" in sections:
        progress("effects: appearance against lighting alone")
        result["appearance"] = _appearance(args)
    if "skinning" in sections:
        progress("effects: skinned agents against rigid ones")
        result["skinning"] = _skinning(args)

    scene = _scene(args, ("lighting",))
    for label, options in OUTPUTS if "outputs" in sections else ():
        progress(f"output: {label}")
        with mr.BatchRenderer(scene, **options) as renderer:
            rate = _views_per_s(renderer, scene, args.steps)
            channels = renderer.channels
        result["outputs"].append({"output": label, "views_per_s": rate, "ms_per_frame": scene.num_views / rate * 1e3,
                                  "bytes_per_view": args.resolution ** 2 * channels})
    for row in result["outputs"]:
        row["speedup_vs_rgb"] = row["views_per_s"] / result["outputs"][0]["views_per_s"]
    steps = [
        ("one camera per view", lambda: NaiveRenderer(scene, tiled=False), max(3, args.steps // 4)),
        ("tiled display regions", lambda: NaiveRenderer(scene), max(3, args.steps // 4)),
        ("one instanced pass", lambda: mr.BatchRenderer(scene, readback="copy"), args.steps),
        ("direct readback", lambda: mr.BatchRenderer(scene), args.steps),
    ]
    for label, make, count in steps if "ablation" in sections else ():
        progress(f"ablation: {label}")
        renderer = make()
        rate = _views_per_s(renderer, scene, count)
        renderer.close()
        result["ablation"].append({"step": label, "views_per_s": rate})
    if args.processes > 1 and "ablation" in sections:
        progress(f"ablation: {args.processes} processes")
        result["ablation"].append({"step": f"{args.processes} processes", "views_per_s": _several_processes(args)})
    for row in result["ablation"]:
        row["speedup_vs_first"] = row["views_per_s"] / result["ablation"][0]["views_per_s"]
    _write(args.out, result)
    return result


def _write(out: str, result: dict) -> None:
    effects = tabulate([[r["effects"], r["views_per_s"], r["ms_per_frame"], r["cost_vs_none"]]
                        for r in result["effects"]],
                       ["effects", "views/s", "ms/frame", "cost vs none"], tablefmt="pipe",
                       floatfmt=["", ",.0f", ".1f", "+.0%"])
    outputs = tabulate([[r["output"], f"{r['bytes_per_view']:,}", r["views_per_s"], r["ms_per_frame"],
                         f"{r['speedup_vs_rgb']:.2f}x"] for r in result["outputs"]],
                       ["observation", "bytes per view", "views/s", "ms/frame", "vs rgb"], tablefmt="pipe",
                       floatfmt=["", "", ",.0f", ".1f", ""], colalign=["left", "right", "right", "right", "right"])
    ablation = tabulate([[r["step"], r["views_per_s"], f"{r['speedup_vs_first']:.1f}x"] for r in result["ablation"]],
                        ["ablation step (cumulative)", "views/s", "speed-up"], tablefmt="pipe",
                        floatfmt=["", ",.0f", ""], colalign=["left", "right", "right"])
    lines = [f"Views of {result['resolution']}x{result['resolution']}, {result['views']} per frame "
             f"({result['machine']['gl_renderer']}).", "", effects, "", outputs]
    if result.get("shadows"):
        shadows = tabulate([[f"{r['resolution']}x{r['resolution']}", "on" if r["pcf"] else "off", r["views_per_s"],
                             r["ms_per_frame"], r["cost_vs_lighting"], r["cpu_ms_per_frame"],
                             r["cpu_cost_vs_lighting"]] for r in result["shadows"]],
                           ["shadow map (per world)", "PCF", "views/s", "ms/frame", "vs lighting alone",
                            "CPU ms/frame", "CPU vs lighting alone"], tablefmt="pipe",
                           floatfmt=["", "", ",.0f", ".1f", "+.0%", ".1f", "+.0%"],
                           colalign=["right", "left", "right", "right", "right", "right", "right"])
        lines += ["", f"Shadows: one {result['worlds']}-world atlas pass per frame, the fragment shader reads it.",
                  "", shadows]
    look = result.get("appearance")
    if look:
        rows = [["lighting", look["off_views_per_s"], look["off_ms_per_frame"], "", look["off_cpu_ms_per_frame"], ""]]
        for label, name in (("on", "lighting + appearance"), ("no_patterns", "the same without patterns")):
            rows.append([name, look[f"{label}_views_per_s"], look[f"{label}_ms_per_frame"],
                         f"{look[f'time_ratio_{label}_off'] - 1:+.1%}", look[f"{label}_cpu_ms_per_frame"],
                         f"{look[f'cpu_ratio_{label}_off'] - 1:+.1%}"])
        appearance = tabulate(rows, ["effects", "views/s", "ms/frame", "cost", "CPU ms/frame", "CPU cost"],
                              tablefmt="pipe", floatfmt=["", ",.0f", ".1f", "", ".1f", ""],
                              colalign=["left", "right", "right", "right", "right", "right"])
        lines += ["", "Appearance: each world's light, sky, floor and wall colours and patterns, object colour "
                  "jitter and camera jitter, against lighting alone; costs are medians of the ratios of "
                  f"alternating blocks (load average {look['load_average'][0]:.2f}; sampling and setting every "
                  f"world's look: {look['set_appearance_ms']:.2f} ms):", "", appearance]
    skin = result.get("skinning")
    if skin:
        skinning = tabulate([["rigid", skin["rigid_views_per_s"], ""],
                             ["skinned", skin["skinned_views_per_s"], f"{skin['cost_vs_rigid']:+.0%}"]],
                            ["agents", "views/s", "cost vs rigid"], tablefmt="pipe", floatfmt=["", ",.0f", ""],
                            colalign=["left", "right", "right"])
        lines += ["", f"Agents as a skinned character ({skin['vertices']} vertices, {skin['joints']} joints, "
                  f"{skin['influences']} per vertex; lighting), a random pose each frame, against the same mesh "
                  "rigid:", "", skinning]
    write_report(out, "effects", result, lines + ["", ablation])
    if not (result["effects"] and result["ablation"]):  # sections left out: no figure
        return
    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.2))
    names = [r["effects"].replace("+", "+\n") if len(r["effects"]) > 12 else r["effects"] for r in result["effects"]]
    left.bar(names, [r["views_per_s"] for r in result["effects"]], color="#4c72b0")
    left.set_ylabel("views / s")
    left.set_title("cost of each effect")
    left.tick_params(axis="x", labelsize=7, rotation=30)
    right.bar([r["step"].replace(" ", "\n", 1) for r in result["ablation"]],
              [r["views_per_s"] for r in result["ablation"]], color="#dd8452")
    right.set_yscale("log")
    right.set_title("cumulative ablation")
    right.tick_params(axis="x", labelsize=7)
    for i, r in enumerate(result["ablation"]):
        right.text(i, r["views_per_s"], f"{r['speedup_vs_first']:.1f}x", ha="center", va="bottom", fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "effects.png"), dpi=110)
    plt.close(fig)
