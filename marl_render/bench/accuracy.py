"""Error against time: resolution, anti-aliasing, effects, physics substeps, float precision.

Every point of every sweep is measured twice in the same run: its cost (views/s or
world-steps/s) and its error against a reference.

Images (the `spread` environment's own scene): one world state is produced by the env
(reset with --seed, a few random steps), then the *same* state is rendered at every
setting by fresh renderers on copies of the env's scene (same groups, camera mounts and
instance data; only resolution, effects and anti-aliasing change). Error = mean
absolute error (0-255 scale) and PSNR against an 8x8 supersampled render of the same
resolution and effects.
  image      resolution 32..256 x anti-aliasing (none, 2x2 / 4x4 supersampling, MSAA 4,
             MSAA 8 if the GL allows it, and the 8x8 reference itself from a second
             renderer, which must come out identical).
  effects    no effect, lighting, texture (a checker on the arena), fog and all three,
             each with a few anti-aliasing modes.
  precision  the scene moved 1e5..1e7 m from the origin, positions passed as float64 vs
             first cast to float32; error against the same scene at the origin.
  shadows    lighting + shadows with shadow maps of 32..1024 texels per world, PCF off
             and on, and lighting alone; error against a 2048-texel map with PCF.
Physics (float64 state, one torch thread; cost = time of the rollout itself):
  spread_physics    spread's step (walls, collisions, drag) with 1..16 substeps and both
                    planar integrators; error = RMS position error after a fixed horizon
                    against velocity Verlet with 64 substeps (same start, same actions).
  cartpole_physics  cartpole_dynamics.cartpole_step (no slider limit), 1..16 substeps, semi-implicit
                    Euler / velocity Verlet / RK4; error against RK4 with 64 substeps.
  cartpole_energy   frictionless cart-pole (dampings 0, zero action): energy drift.
Pareto front: a point is on it when no other point of its sweep (and group) is at most as
slow and at most as wrong, and better in one. References are excluded (their error is zero
by construction).
Writes accuracy.md, accuracy.json and accuracy.png into --out (the recommendations, tables
and plot are written by marl_render.bench.accuracy_report from the result alone).
"""
from __future__ import annotations

import dataclasses
import math
import statistics
import sys
import time

import numpy as np
import torch
from tqdm import tqdm

from . import accuracy_report as report
from .accuracy_report import SHORT
from .common import machine

# Anti-aliasing modes: name -> (supersample, multisamples).
AA_MODES = {"none": (1, 0), "ss2x2": (2, 0), "ss4x4": (4, 0), "msaa4": (1, 4), "msaa8": (1, 8), "ss8x8": (8, 0)}
REFERENCE_AA = "ss8x8"
EFFECT_SETS = [(), ("lighting",), ("texture",), ("fog",), ("fog", "lighting", "texture")]
SPREAD_INTEGRATORS = ("semi_implicit_euler", "velocity_verlet")
CARTPOLE_INTEGRATORS = ("semi_implicit_euler", "velocity_verlet", "rk4")

FULL = dict(worlds=8, resolutions=[32, 48, 64, 96, 128, 256], image_aa=["none", "ss2x2", "ss4x4", "msaa4", "msaa8",
            "ss8x8"], effects_resolution=64, effects_aa=["none", "ss2x2", "msaa4"], precision_resolution=64,
            offsets=[1e5, 1e6, 1e7], substeps=[1, 2, 4, 8, 16], reference_substeps=64, physics_worlds=256,
            spread_horizon=20, cartpole_horizon=100, energy_horizon=1000, rounds=5, min_time=0.5, min_frames=3,
            max_frames=30, physics_rounds=5, energy_rounds=3, env_steps=5, shadow_maps=[64, 128, 256, 512, 1024],
            shadow_reference=2048)
QUICK = dict(FULL, worlds=1, resolutions=[32, 48], effects_resolution=32, effects_aa=["none", "ss2x2"],
             precision_resolution=32, offsets=[1e5, 1e7], physics_worlds=16, spread_horizon=5, cartpole_horizon=20,
             energy_horizon=100, rounds=1, min_time=0.0, min_frames=1, max_frames=1, physics_rounds=1, energy_rounds=1,
             shadow_maps=[32, 64], shadow_reference=256)


def add_arguments(parser):
    parser.add_argument("--out", default="out/accuracy")
    parser.add_argument("--quick", action="store_true", help="small sizes and single timings (for tests)")
    parser.add_argument("--worlds", type=int, default=None, help="spread worlds rendered (3 views each)")
    parser.add_argument("--resolutions", type=int, nargs="+", default=None)
    parser.add_argument("--physics-worlds", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-framebuffer", type=int, default=4096,
                        help="framebuffer side limit of every renderer (bounds memory of the 8x8 references)")


# ============================================================================ helpers
def _median_time(function, min_time: float, min_frames: int, max_frames: int) -> float:
    """Median seconds per call after one warm-up call (the warm-up also compiles shaders)."""
    function()
    times = []
    start = time.perf_counter()
    while len(times) < min_frames or (time.perf_counter() - start < min_time and len(times) < max_frames):
        t = time.perf_counter()
        function()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def image_error(image: torch.Tensor, reference: torch.Tensor) -> dict:
    """MAE / max on the 0-255 scale, PSNR in dB (None: identical, i.e. infinite) and the
    fraction of pixels with any channel different."""
    diff = image.to(torch.float64) - reference.to(torch.float64)
    mse = float((diff * diff).mean())
    rows = diff.abs().sum(dim=(0, 1, 3, 4))  # [W, A, H, Wpx, 3] -> error per image row, all views
    total = float(rows.sum())
    return {"mae": float(diff.abs().mean()), "psnr_db": None if mse == 0 else 10 * math.log10(255.0 ** 2 / mse),
            "max_abs": float(diff.abs().max()), "pixels_changed": float((diff != 0).any(-1).to(torch.float64).mean()),
            "worst_row": int(rows.argmax()), "worst_row_share": float(rows.max()) / total if total else 0.0}


def pareto_flags(points: list, group_key=None) -> None:
    """Set point["pareto"]: not dominated in (cost_s, error) by another non-reference point
    of the same group. References are never on the front."""
    for p in points:
        p["pareto"] = False
        if p.get("reference"):
            continue
        rivals = [q for q in points if q is not p and not q.get("reference")
                  and (group_key is None or q[group_key] == p[group_key])]
        p["pareto"] = not any(q["cost_s"] <= p["cost_s"] and q["error"] <= p["error"]
                              and (q["cost_s"] < p["cost_s"] or q["error"] < p["error"]) for q in rivals)


def _checker(size=64, cells=16) -> np.ndarray:
    pattern = (np.indices((size, size)) // (size // cells)).sum(0) % 2
    return np.where(pattern[..., None] == 1, 220, 70).astype(np.uint8).repeat(3, axis=2)


# ============================================================================ scenes
class SpreadState:
    """One world state of the spread env, re-renderable at any setting."""

    def __init__(self, worlds: int, seed: int, steps: int):
        from marl_render.envs import make_env

        env = make_env("spread", num_worlds=worlds, resolution=16, seed=seed)
        try:
            generator = torch.Generator().manual_seed(seed)
            env.reset(seed=seed)
            for _ in range(steps):
                env.step(torch.randint(env.num_actions, (env.num_worlds, env.num_agents), generator=generator))
            self.scene = env.renderer.scene
            self.instances = {name: env.renderer.instance_state(name) for name in self.scene.groups}
        finally:
            env.close()

    def scene_copy(self, resolution: int, effects, offset=None, float32=False):
        """The env's scene with another resolution / effects; static geometry moved by
        `offset` (metres, float64) and rounded to float32 when `float32`."""
        import marl_render as mr

        src = self.scene
        scene = mr.Scene(num_worlds=src.num_worlds, agents_per_world=src.agents_per_world, resolution=resolution,
                         effects=tuple(effects), background=src.background, lighting=src.lighting, fog=src.fog,
                         fov_y=src.fov_y, near=src.near, far=src.far)
        texture = _checker() if "texture" in effects else None
        for name, group in src.static.items():
            scene.add_static(name, group.mesh, position=self._move(group.position, offset, float32),
                             rotation=group.rotation, scale=group.scale, color=group.color,
                             texture=group.texture if group.texture is not None else texture)
        for name, group in src.groups.items():
            scene.add_group(name, group.mesh, group.capacity, texture=group.texture)
        mount = src.camera_mount
        if mount is not None:
            scene.mount_cameras(mount.group, mount.instance, mount.offset, mount.pitch, mount.hide_owner)
        return scene

    @staticmethod
    def _move(position, offset, float32):
        position = position.to(torch.float64)
        if offset is not None:
            position = position + torch.as_tensor(offset, dtype=torch.float64)
        return position.to(torch.float32) if float32 else position

    def updates(self, offset=None, float32=False, poses_only=False) -> dict:
        result = {}
        for name, state in self.instances.items():
            kwargs = dict(state)
            kwargs["position"] = self._move(state["position"], offset, float32)
            if poses_only:
                kwargs = {k: kwargs[k] for k in ("position", "rotation")}
            result[name] = kwargs
        return result


_REFUSED_SAMPLES = {}  # MSAA sample counts the GL refused once: not asked for again


def render_point(state: SpreadState, cfg: dict, *, resolution: int, effects, aa: str, max_framebuffer: int,
                 offset=None, float32=False, timed=True):
    """(image [W, A, H, Wpx, 3] uint8, seconds per view or None, skip reason or None)."""
    import marl_render as mr
    from marl_render.render import backend

    supersample, multisamples = AA_MODES[aa]
    if multisamples in _REFUSED_SAMPLES:
        return None, None, _REFUSED_SAMPLES[multisamples]
    scene = state.scene_copy(resolution, effects, offset, float32)
    try:
        renderer = mr.BatchRenderer(scene, supersample=supersample, multisamples=multisamples,
                                    max_framebuffer_size=min(max_framebuffer, backend.gl_info().max_framebuffer_size))
    except backend.GLUnavailableError:
        if not multisamples:
            raise
        # Panda3D logs what it got instead ("Could not get requested FrameBufferProperties").
        _REFUSED_SAMPLES[multisamples] = f"the GL ({backend.gl_info().renderer}) refused {multisamples} MSAA samples"
        return None, None, _REFUSED_SAMPLES[multisamples]
    with renderer:
        if multisamples:
            got = renderer.granted_multisamples
            if got != multisamples:
                _REFUSED_SAMPLES[multisamples] = f"the GL gave {got} samples instead of {multisamples}"
                return None, None, _REFUSED_SAMPLES[multisamples]
        full, poses = state.updates(offset, float32), state.updates(offset, float32, poses_only=True)
        for name, kwargs in full.items():
            renderer.update(name, **kwargs)
        image = renderer.render().rgb.clone()
        if not timed:
            return image, None, None

        def frame():
            for name, kwargs in poses.items():
                renderer.update(name, **kwargs)
            renderer.render()

        seconds = _median_time(frame, cfg["min_time"], cfg["min_frames"], cfg["max_frames"])
        return image, seconds / scene.num_views, None


# ============================================================================ sweeps
def shadow_settings(cfg: dict) -> list:
    """(shadow map texels or None for lighting alone, PCF) of the shadows sweep."""
    return [(None, False)] + [(m, pcf) for m in cfg["shadow_maps"] for pcf in (False, True)]


def _case(desc, ref, **render):
    """One render setting: `render` and `ref` are render_point keyword arguments."""
    render = {"effects": ("lighting",), "offset": None, "float32": False, **render}
    ref = {"effects": ("lighting",), "offset": None, "float32": False, **ref}
    return {"desc": desc, "render": render, "ref": ref}


class Sweeps:
    """Runs the sweeps in order; rendered settings are timed in `rounds` round-robin passes
    (cost = the fastest pass) so that a burst of load on the shared machine does not land
    on one setting only. Errors come from the first pass."""

    def __init__(self, args, cfg: dict, state: SpreadState):
        self.args, self.cfg, self.state = args, cfg, state
        self.result = {}
        c = cfg
        self.cases = {"image": [_case(f"image {r}px {aa}", dict(resolution=r, aa=REFERENCE_AA), resolution=r, aa=aa)
                                for r in c["resolutions"] for aa in c["image_aa"]],
                      "effects": [_case(f"effects {'+'.join(e) or 'none'} {aa}",
                                        dict(resolution=c["effects_resolution"], effects=e, aa=REFERENCE_AA),
                                        resolution=c["effects_resolution"], effects=e, aa=aa)
                                  for e in EFFECT_SETS for aa in c["effects_aa"]],
                      "precision": [_case(f"precision {d:.0e} m {dtype}",
                                          dict(resolution=c["precision_resolution"], aa="none"),
                                          resolution=c["precision_resolution"], aa="none", offset=(d, d, 0.0),
                                          float32=dtype == "float32")
                                    for d in c["offsets"] for dtype in ("float64", "float32")]}
        total = sum(len({repr(k["ref"]) for k in cases}) + c["rounds"] * len(cases) for cases in self.cases.values())
        total += 1 + c["rounds"] * len(shadow_settings(c))
        total += 1 + len(SPREAD_INTEGRATORS) * (1 + c["physics_rounds"] * len(c["substeps"]))
        total += 1 + (c["physics_rounds"] + c["energy_rounds"]) * len(CARTPOLE_INTEGRATORS) * len(c["substeps"])
        self.bar = tqdm(total=total, file=sys.stderr, unit="point", dynamic_ncols=True, mininterval=0.5)

    def _render_sweep(self, key: str) -> list:
        """[(case, error dict, [seconds per view per round]) or (case, None, skip reason)]."""
        c, cases = self.cfg, self.cases[key]
        out = [None] * len(cases)
        started = time.perf_counter()
        for round_index in range(c["rounds"]):
            ref_key = reference = None
            for index, case in enumerate(cases):
                self.bar.set_description(f"{case['desc']} ({round_index + 1}/{c['rounds']})")
                if out[index] is not None and out[index][1] is None:  # skipped in the first round
                    self.bar.update(1)
                    continue
                if round_index == 0 and repr(case["ref"]) != ref_key:
                    ref_key = repr(case["ref"])
                    reference, _, _ = render_point(self.state, c, max_framebuffer=self.args.max_framebuffer,
                                                   timed=False, **case["ref"])
                    self.bar.update(1)
                image, seconds, reason = render_point(self.state, c, max_framebuffer=self.args.max_framebuffer,
                                                      **case["render"])
                self.bar.update(1)
                if reason:
                    out[index] = (case, None, reason)
                elif round_index == 0:
                    out[index] = (case, image_error(image, reference), [seconds])
                else:
                    out[index][2].append(seconds)
        self._seconds = time.perf_counter() - started
        return out

    @staticmethod
    def _cost(point: dict, rounds: list) -> dict:
        seconds = min(rounds)
        point.update(views_per_s=1 / seconds, cost_s=seconds, cost_rounds_s=rounds)
        return point

    # -------------------------------------------------------------- images
    def images(self):
        points, skipped = [], []
        for case, error, rounds in self._render_sweep("image"):
            resolution, aa = case["render"]["resolution"], case["render"]["aa"]
            if error is None:
                skipped.append({"resolution": resolution, "aa": aa, "reason": rounds})
                continue
            points.append(self._cost({"label": f"{resolution}px {aa}", "resolution": resolution, "aa": aa,
                                      "reference": aa == REFERENCE_AA, "error": error["mae"], **error}, rounds))
        pareto_flags(points)
        for resolution in self.cfg["resolutions"]:  # the front among the AA modes of one resolution
            same = [p for p in points if p["resolution"] == resolution]
            flags = [dict(p) for p in same]
            pareto_flags(flags)
            for p, f in zip(same, flags, strict=True):
                p["pareto_at_resolution"] = f["pareto"]
        self.result["image"] = {
            "what": f"spread scene ({self.state.scene.num_views} views), lighting; error vs {REFERENCE_AA} at the "
                    "same resolution",
            "cost": "seconds per view", "error": "mean absolute error (0-255)", "views": self.state.scene.num_views,
            "seconds": self._seconds, "points": points, "skipped": skipped}

    def effects(self):
        points, skipped = [], []
        for case, error, rounds in self._render_sweep("effects"):
            name, aa = "+".join(case["render"]["effects"]) or "none", case["render"]["aa"]
            if error is None:
                skipped.append({"effects": name, "aa": aa, "reason": rounds})
                continue
            points.append(self._cost({"label": f"{name} {aa}", "effects": name, "aa": aa,
                                      "resolution": case["render"]["resolution"], "error": error["mae"], **error},
                                     rounds))
        for p in points:
            base = next((q for q in points if q["effects"] == "none" and q["aa"] == p["aa"]), None)
            p["cost_vs_no_effect"] = p["cost_s"] / base["cost_s"] - 1 if base else None
        pareto_flags(points, group_key="effects")
        self.result["effects"] = {
            "what": f"spread scene at {self.cfg['effects_resolution']}px; error vs {REFERENCE_AA} with the same "
                    "effects (texture: a checker on floor and walls)",
            "cost": "seconds per view", "error": "mean absolute error (0-255)", "group": "effects",
            "seconds": self._seconds, "points": points, "skipped": skipped}

    def precision(self):
        points = []
        for case, error, rounds in self._render_sweep("precision"):
            distance, dtype = case["render"]["offset"][0], "float32" if case["render"]["float32"] else "float64"
            points.append(self._cost({"label": f"{distance:.0e} m {dtype}", "offset_m": distance, "positions": dtype,
                                      "float32_spacing_m": float(np.spacing(np.float32(distance))),
                                      "error": error["mae"], **error}, rounds))
        self.result["precision"] = {
            "what": f"spread scene at {self.cfg['precision_resolution']}px moved by (d, d, 0) m; error vs the same "
                    "scene at the origin (same settings, no AA)",
            "cost": "seconds per view", "error": "mean absolute error (0-255)", "seconds": self._seconds,
            "points": points, "skipped": []}

    # -------------------------------------------------------------- shadows
    def shadows(self):
        """Shadow-map resolution against error and time, on the spread scene with the shadows
        env's bounds (the arena). Every frame moves the bodies, so the atlas is redrawn each
        time; cost = the fastest of cfg["rounds"] passes over the settings."""
        import marl_render as mr
        from marl_render.envs import scenery
        from marl_render.envs.spread import Spread
        from marl_render.render import backend

        c, state = self.cfg, self.state
        bounds = scenery.arena_shadow_bounds(Spread.arena_half_extent)
        resolution = c["effects_resolution"]
        max_framebuffer = min(self.args.max_framebuffer, backend.gl_info().max_framebuffer_size)

        def render(setting, timed):
            shadow_map, pcf = setting
            scene = state.scene_copy(resolution, ("lighting",) if shadow_map is None else ("lighting", "shadows"))
            if shadow_map is not None:
                scene.shadows = mr.Shadows(resolution=shadow_map, pcf=pcf, bounds=bounds)
            with mr.BatchRenderer(scene, max_framebuffer_size=max_framebuffer) as renderer:
                for name, kwargs in state.updates().items():
                    renderer.update(name, **kwargs)
                image = renderer.render().rgb.clone()
                if not timed:
                    return image, None
                poses = state.updates(poses_only=True)

                def frame():
                    for name, kwargs in poses.items():
                        renderer.update(name, **kwargs)
                    renderer.render()

                return image, _median_time(frame, c["min_time"], c["min_frames"], c["max_frames"]) / scene.num_views

        started = time.perf_counter()
        self.bar.set_description("shadows reference")
        reference, _ = render((c["shadow_reference"], True), timed=False)
        self.bar.update(1)
        settings = shadow_settings(c)
        points = []
        for round_index in range(c["rounds"]):
            for index, (shadow_map, pcf) in enumerate(settings):
                label = "no shadows" if shadow_map is None else f"{shadow_map} px{' PCF' if pcf else ''}"
                self.bar.set_description(f"shadows {label} ({round_index + 1}/{c['rounds']})")
                image, seconds = render((shadow_map, pcf), timed=True)
                self.bar.update(1)
                if round_index == 0:
                    error = image_error(image, reference)
                    points.append({"label": label, "shadow_map": shadow_map, "pcf": pcf, "error": error["mae"],
                                   **error, "rounds": [seconds]})
                else:
                    points[index]["rounds"].append(seconds)
        points = [self._cost(p, p.pop("rounds")) for p in points]
        for p in points:
            p["cost_vs_no_shadows"] = p["cost_s"] / points[0]["cost_s"] - 1
        self.result["shadows"] = {
            "what": f"spread scene at {resolution}px, lighting + shadows over the arena {bounds}; error vs a "
                    f"{c['shadow_reference']}-texel map with PCF (no anti-aliasing)",
            "cost": "seconds per view", "error": "mean absolute error (0-255)",
            "seconds": time.perf_counter() - started, "points": points, "skipped": []}

    # -------------------------------------------------------------- physics
    def _timed_rollouts(self, name: str, settings: list, rollout, rounds: int) -> list:
        """[(result of rollout(*setting) in the first round, [seconds per round])]: every round
        runs every setting once (round-robin, like the renders); all rounds are identical."""
        out = [None] * len(settings)
        for round_index in range(rounds):
            for index, setting in enumerate(settings):
                self.bar.set_description(f"{name} {SHORT[setting[1]]} x{setting[0]} ({round_index + 1}/{rounds})")
                start = time.perf_counter()
                result = rollout(*setting)
                seconds = time.perf_counter() - start
                self.bar.update(1)
                if round_index == 0:
                    out[index] = (result, [seconds])
                else:
                    out[index][1].append(seconds)
        return out

    def spread_physics(self):
        from marl_render.envs import BatchShape
        from marl_render.envs.spread import Spread

        c = self.cfg
        W, T = c["physics_worlds"], c["spread_horizon"]  # worlds, steps (the horizon)
        started = time.perf_counter()
        # The task's public scenario, stepped without an env or a renderer; float64 bodies (bench only).
        layout = BatchShape(num_worlds=W, num_agents=Spread.default_num_agents, continuous=False,
                            device=torch.device("cpu"))
        template = Spread(Spread.Params(), layout)
        base = template.physics
        s = template.spawn(torch.Generator().manual_seed(self.args.seed))
        generator = torch.Generator().manual_seed(self.args.seed + 1)
        actions = torch.randint(template.num_actions, (T, W, layout.num_agents), generator=generator)
        alive = torch.ones(W, layout.num_agents, dtype=torch.bool)
        start = dataclasses.replace(s, pos=s.pos.double(), vel=s.vel.double(), yaw=s.yaw.double(),
                                    landmarks=s.landmarks.double())

        def rollout(substeps, integrator):
            scenario = Spread(Spread.Params(), layout)
            scenario.physics = dataclasses.replace(base, substeps=substeps, integrator=integrator)
            scenario.radius, scenario.mass = scenario.radius.double(), scenario.mass.double()
            state, unused = start, torch.Generator()
            for a in actions:
                state = scenario.step(state, a, alive, unused).state
            return state

        settings, skipped = [], []
        for integrator in SPREAD_INTEGRATORS:
            for substeps in c["substeps"]:
                try:
                    dataclasses.replace(base, substeps=substeps, integrator=integrator)
                except ValueError as error:  # PhysicsConfig's no-tunnelling bound
                    skipped.append({"integrator": integrator, "substeps": substeps, "reason": str(error)})
                    self.bar.update(c["physics_rounds"])
                    continue
                settings.append((substeps, integrator))
        self.bar.set_description("spread references")
        reference = rollout(c["reference_substeps"], "velocity_verlet")
        own = {i: rollout(c["reference_substeps"], i) for i in SPREAD_INTEGRATORS}
        self.bar.update(1 + len(SPREAD_INTEGRATORS))
        points = []
        for (substeps, integrator), (bodies, rounds) in zip(
                settings, self._timed_rollouts("spread", settings, rollout, c["physics_rounds"]), strict=True):
            seconds = min(rounds)
            pos_err = (bodies.pos - reference.pos).norm(dim=-1)
            vel_err = (bodies.vel - reference.vel).norm(dim=-1)
            own_err = (bodies.pos - own[integrator].pos).norm(dim=-1)
            points.append({
                "label": f"{SHORT[integrator]} x{substeps}", "integrator": integrator, "substeps": substeps,
                "default": substeps == base.substeps and integrator == base.integrator,
                "world_steps_per_s": W * T / seconds, "cost_s": seconds / (W * T), "cost_rounds_s": rounds,
                "error": float(pos_err.pow(2).mean().sqrt()), "pos_rms_m": float(pos_err.pow(2).mean().sqrt()),
                "pos_max_m": float(pos_err.max()), "vel_rms_m_s": float(vel_err.pow(2).mean().sqrt()),
                "pos_rms_vs_own_64_m": float(own_err.pow(2).mean().sqrt())})
        agents = layout.num_agents
        pareto_flags(points)
        self.result["spread_physics"] = {
            "what": f"spread physics (dt {base.dt} s, walls + collisions + drag), {W} worlds x {agents} agents, "
                    f"{T} steps of random actions, float64; error vs velocity_verlet x{c['reference_substeps']}",
            "cost": "seconds per world-step", "error": "RMS position error (m)", "env_default":
                {"substeps": base.substeps, "integrator": base.integrator}, "seconds": time.perf_counter() - started,
            "points": points, "skipped": skipped}

    def cartpole(self):
        from marl_render.envs import cartpole_dynamics

        c = self.cfg
        W, T, TE = c["physics_worlds"], c["cartpole_horizon"], c["energy_horizon"]  # worlds, steps, energy steps
        started = time.perf_counter()
        g = torch.Generator().manual_seed(self.args.seed)
        f64 = dict(generator=g, dtype=torch.float64)
        start = torch.stack((torch.rand(W, **f64) - 0.5, (torch.rand(W, **f64) * 2 - 1) * math.pi,
                             torch.randn(W, **f64), torch.randn(W, **f64)), -1)
        actions = torch.rand(T, W, **f64) * 2 - 1
        zeros = torch.zeros(W, dtype=torch.float64)

        def rollout(substeps, integrator):
            q = start
            for a in actions:
                q = cartpole_dynamics.cartpole_step(q, a, substeps=substeps, integrator=integrator)
            return q

        def energy_rollout(substeps, integrator):
            q, e0 = start, cartpole_dynamics.cartpole_energy(start)
            drift = torch.zeros(W, dtype=torch.float64)
            for _ in range(TE):
                q = cartpole_dynamics.cartpole_step(q, zeros, substeps=substeps, integrator=integrator,
                                                    slider_damping=0.0, hinge_damping=0.0)
                drift = torch.maximum(drift, (cartpole_dynamics.cartpole_energy(q) - e0).abs())
            return drift, e0

        self.bar.set_description("cartpole reference")
        reference = rollout(c["reference_substeps"], "rk4")
        self.bar.update(1)
        settings = [(s, i) for i in CARTPOLE_INTEGRATORS for s in c["substeps"]]
        points, energy_points = [], []
        for (substeps, integrator), (q, rounds) in zip(
                settings, self._timed_rollouts("cartpole", settings, rollout, c["physics_rounds"]), strict=True):
            seconds = min(rounds)
            q_err = (q[:, :2] - reference[:, :2]).norm(dim=-1)
            s_err = (q - reference).norm(dim=-1)
            points.append({"label": f"{SHORT[integrator]} x{substeps}", "integrator": integrator,
                           "substeps": substeps, "default": substeps == 1 and integrator == "rk4",
                           "world_steps_per_s": W * T / seconds, "cost_s": seconds / (W * T), "cost_rounds_s": rounds,
                           "error": float(q_err.pow(2).mean().sqrt()), "q_rms": float(q_err.pow(2).mean().sqrt()),
                           "q_max": float(q_err.max()), "state_rms": float(s_err.pow(2).mean().sqrt())})
        physics_seconds = time.perf_counter() - started
        for (substeps, integrator), ((drift, e0), rounds) in zip(
                settings, self._timed_rollouts("energy", settings, energy_rollout, c["energy_rounds"]), strict=True):
            seconds = min(rounds)
            energy_points.append({"label": f"{SHORT[integrator]} x{substeps}", "integrator": integrator,
                                  "substeps": substeps, "world_steps_per_s": W * TE / seconds,
                                  "cost_s": seconds / (W * TE), "cost_rounds_s": rounds, "error": float(drift.mean()),
                                  "drift_mean_j": float(drift.mean()), "drift_max_j": float(drift.max()),
                                  "energy_spread_j": float(e0.max() - e0.min())})
        pareto_flags(points)
        pareto_flags(energy_points)
        dt = cartpole_dynamics.CARTPOLE["timestep"]
        self.result["cartpole_physics"] = {
            "what": f"cartpole_dynamics.cartpole_step (dt {dt} s, dm_control dampings, no slider limit), {W} worlds, "
                    f"{T} steps ({T * dt:g} s) of random actions from random swinging states, float64; error vs rk4 x"
                    f"{c['reference_substeps']}",
            "cost": "seconds per world-step", "error": "RMS of |(dx, dtheta)| (m, rad)",
            "env_default": {"substeps": 1, "integrator": "rk4"}, "seconds": physics_seconds, "points": points,
            "skipped": []}
        self.result["cartpole_energy"] = {
            "what": f"frictionless cart-pole (dampings 0, action 0), {W} worlds, {TE} steps ({TE * dt:g} s); "
                    "error = max over time of |E(t) - E(0)|, mean over worlds",
            "cost": "seconds per world-step", "error": "energy drift (J)",
            "seconds": time.perf_counter() - started - physics_seconds, "points": energy_points, "skipped": []}


# ============================================================================ run
def run(args) -> dict:
    cfg = dict(QUICK if args.quick else FULL)
    for key, value in (("worlds", args.worlds), ("resolutions", args.resolutions),
                       ("physics_worlds", args.physics_worlds)):
        if value is not None:
            cfg[key] = value
    saved_threads = torch.get_num_threads()
    torch.set_num_threads(1)  # like the envs: leave the cores to llvmpipe; small tensors lose nothing
    started = time.perf_counter()
    try:
        state = SpreadState(cfg["worlds"], args.seed, cfg["env_steps"])
        sweeps = Sweeps(args, cfg, state)
        sweeps.images()
        sweeps.effects()
        sweeps.precision()
        sweeps.shadows()
        sweeps.spread_physics()
        sweeps.cartpole()
        sweeps.bar.close()
        result = {"benchmark": "accuracy", "quick": bool(args.quick), "seed": args.seed, "settings": cfg,
                  "machine": machine(), "sweeps": sweeps.result}
    finally:
        torch.set_num_threads(saved_threads)
    result["seconds"] = time.perf_counter() - started
    result["recommendations"] = report.recommendations(result)
    report.write(args.out, result)
    return result
