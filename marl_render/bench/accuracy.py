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
  cartpole_physics  physics.cartpole_step (no slider limit), 1..16 substeps, semi-implicit
                    Euler / velocity Verlet / RK4; error against RK4 with 64 substeps.
  cartpole_energy   frictionless cart-pole (dampings 0, zero action): energy drift.
Pareto front: a point is on it when no other point of its sweep (and group) is at most as
slow and at most as wrong, and better in one. References are excluded (their error is zero
by construction).
Writes accuracy.md, accuracy.json and accuracy.png into --out.
"""
from __future__ import annotations

import dataclasses
import math
import os
import statistics
import sys
import time

import numpy as np
import torch

from .common import machine, pyplot, write_report

# Anti-aliasing modes: name -> (supersample, multisamples).
AA_MODES = {"none": (1, 0), "ss2x2": (2, 0), "ss4x4": (4, 0), "msaa4": (1, 4), "msaa8": (1, 8), "ss8x8": (8, 0)}
REFERENCE_AA = "ss8x8"
EFFECT_SETS = [(), ("lighting",), ("texture",), ("fog",), ("fog", "lighting", "texture")]
SPREAD_INTEGRATORS = ("semi_implicit_euler", "velocity_verlet")
CARTPOLE_INTEGRATORS = ("semi_implicit_euler", "velocity_verlet", "rk4")
SHORT = {"semi_implicit_euler": "SIE", "velocity_verlet": "Verlet", "rk4": "RK4"}

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

# Thresholds the recommendations are phrased against (the answers come from the data).
SPREAD_TARGETS_M = (1e-2, 1e-3)
CARTPOLE_TARGETS = (1e-3, 1e-6)


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


def observed_order(points: list, floor: float = 1e-12):
    """Least-squares slope of -log(error) against log(substeps) (errors above `floor`)."""
    pairs = [(math.log(p["substeps"]), math.log(p["error"])) for p in points if p["error"] > floor]
    if len(pairs) < 2:
        return None
    xs, ys = zip(*pairs)
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    return -sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx if sxx else None


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
    """(image [W, A, H, W, 3] uint8, seconds per view or None, skip reason or None)."""
    import marl_render as mr
    from marl_render import backend

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
            got = renderer.buffer.get_fb_properties().get_multisamples()
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
        from tqdm import tqdm

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
            for p, f in zip(same, flags):
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
        from marl_render.envs import make_env

        c = self.cfg
        W, H = c["physics_worlds"], c["spread_horizon"]
        started = time.perf_counter()
        env = make_env("spread", num_worlds=W, resolution=8, seed=self.args.seed)
        base = env.physics
        try:
            env.reset(seed=self.args.seed)
            generator = torch.Generator().manual_seed(self.args.seed + 1)
            actions = torch.randint(env.num_actions, (H, W, env.num_agents), generator=generator)
            alive = torch.ones(W, env.num_agents, dtype=torch.bool)
            b = env.bodies
            start = b._replace(pos=b.pos.double(), vel=b.vel.double(), radius=b.radius.double(),
                               mass=b.mass.double())
            yaw0 = env.yaw.double()
            env.landmarks = env.landmarks.double()

            def rollout(substeps, integrator):
                env.physics = dataclasses.replace(base, substeps=substeps, integrator=integrator)
                env.bodies, env.yaw = start, yaw0
                for a in actions:
                    env._step_state(a, alive)  # the env's physics step, without rendering
                return env.bodies

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
                    settings, self._timed_rollouts("spread", settings, rollout, c["physics_rounds"])):
                seconds = min(rounds)
                pos_err = (bodies.pos - reference.pos).norm(dim=-1)
                vel_err = (bodies.vel - reference.vel).norm(dim=-1)
                own_err = (bodies.pos - own[integrator].pos).norm(dim=-1)
                points.append({
                    "label": f"{SHORT[integrator]} x{substeps}", "integrator": integrator, "substeps": substeps,
                    "default": substeps == base.substeps and integrator == base.integrator,
                    "world_steps_per_s": W * H / seconds, "cost_s": seconds / (W * H), "cost_rounds_s": rounds,
                    "error": float(pos_err.pow(2).mean().sqrt()), "pos_rms_m": float(pos_err.pow(2).mean().sqrt()),
                    "pos_max_m": float(pos_err.max()), "vel_rms_m_s": float(vel_err.pow(2).mean().sqrt()),
                    "pos_rms_vs_own_64_m": float(own_err.pow(2).mean().sqrt())})
            agents = env.num_agents
        finally:
            env.physics = base
            env.close()
        pareto_flags(points)
        self.result["spread_physics"] = {
            "what": f"spread physics (dt {base.dt} s, walls + collisions + drag), {W} worlds x {agents} agents, "
                    f"{H} steps of random actions, float64; error vs velocity_verlet x{c['reference_substeps']}",
            "cost": "seconds per world-step", "error": "RMS position error (m)", "env_default":
                {"substeps": base.substeps, "integrator": base.integrator}, "seconds": time.perf_counter() - started,
            "points": points, "skipped": skipped}

    def cartpole(self):
        from marl_render.envs import physics

        c = self.cfg
        W, H, E = c["physics_worlds"], c["cartpole_horizon"], c["energy_horizon"]
        started = time.perf_counter()
        g = torch.Generator().manual_seed(self.args.seed)
        f64 = dict(generator=g, dtype=torch.float64)
        start = torch.stack((torch.rand(W, **f64) - 0.5, (torch.rand(W, **f64) * 2 - 1) * math.pi,
                             torch.randn(W, **f64), torch.randn(W, **f64)), -1)
        actions = torch.rand(H, W, **f64) * 2 - 1
        zeros = torch.zeros(W, dtype=torch.float64)

        def rollout(substeps, integrator):
            q = start
            for a in actions:
                q = physics.cartpole_step(q, a, substeps=substeps, integrator=integrator)
            return q

        def energy_rollout(substeps, integrator):
            q, e0 = start, physics.cartpole_energy(start)
            drift = torch.zeros(W, dtype=torch.float64)
            for _ in range(E):
                q = physics.cartpole_step(q, zeros, substeps=substeps, integrator=integrator, slider_damping=0.0,
                                          hinge_damping=0.0)
                drift = torch.maximum(drift, (physics.cartpole_energy(q) - e0).abs())
            return drift, e0

        self.bar.set_description("cartpole reference")
        reference = rollout(c["reference_substeps"], "rk4")
        self.bar.update(1)
        settings = [(s, i) for i in CARTPOLE_INTEGRATORS for s in c["substeps"]]
        points, energy_points = [], []
        for (substeps, integrator), (q, rounds) in zip(
                settings, self._timed_rollouts("cartpole", settings, rollout, c["physics_rounds"])):
            seconds = min(rounds)
            q_err = (q[:, :2] - reference[:, :2]).norm(dim=-1)
            s_err = (q - reference).norm(dim=-1)
            points.append({"label": f"{SHORT[integrator]} x{substeps}", "integrator": integrator,
                           "substeps": substeps, "default": substeps == 1 and integrator == "rk4",
                           "world_steps_per_s": W * H / seconds, "cost_s": seconds / (W * H), "cost_rounds_s": rounds,
                           "error": float(q_err.pow(2).mean().sqrt()), "q_rms": float(q_err.pow(2).mean().sqrt()),
                           "q_max": float(q_err.max()), "state_rms": float(s_err.pow(2).mean().sqrt())})
        physics_seconds = time.perf_counter() - started
        for (substeps, integrator), ((drift, e0), rounds) in zip(
                settings, self._timed_rollouts("energy", settings, energy_rollout, c["energy_rounds"])):
            seconds = min(rounds)
            energy_points.append({"label": f"{SHORT[integrator]} x{substeps}", "integrator": integrator,
                                  "substeps": substeps, "world_steps_per_s": W * E / seconds,
                                  "cost_s": seconds / (W * E), "cost_rounds_s": rounds, "error": float(drift.mean()),
                                  "drift_mean_j": float(drift.mean()), "drift_max_j": float(drift.max()),
                                  "energy_spread_j": float(e0.max() - e0.min())})
        pareto_flags(points)
        pareto_flags(energy_points)
        dt = physics.CARTPOLE["timestep"]
        self.result["cartpole_physics"] = {
            "what": f"physics.cartpole_step (dt {dt} s, dm_control dampings, no slider limit), {W} worlds, {H} steps "
                    f"({H * dt:g} s) of random actions from random swinging states, float64; error vs rk4 x"
                    f"{c['reference_substeps']}",
            "cost": "seconds per world-step", "error": "RMS of |(dx, dtheta)| (m, rad)",
            "env_default": {"substeps": 1, "integrator": "rk4"}, "seconds": physics_seconds, "points": points,
            "skipped": []}
        self.result["cartpole_energy"] = {
            "what": f"frictionless cart-pole (dampings 0, action 0), {W} worlds, {E} steps ({E * dt:g} s); "
                    "error = max over time of |E(t) - E(0)|, mean over worlds",
            "cost": "seconds per world-step", "error": "energy drift (J)",
            "seconds": time.perf_counter() - started - physics_seconds, "points": energy_points, "skipped": []}


# ============================================================================ recommendations
def _fmt_cost(seconds: float) -> str:
    return f"{seconds * 1e6:,.1f} µs" if seconds < 1e-3 else f"{seconds * 1e3:,.2f} ms"


def recommendations(result: dict) -> list:
    sweeps = result["sweeps"]
    out = []
    image = [p for p in sweeps["image"]["points"] if not p["reference"]]
    if image:
        front = sorted((p for p in image if p["pareto"]), key=lambda p: p["cost_s"])
        out.append("Images, all resolutions and anti-aliasing modes (time per view vs MAE against the 8x8 reference "
                   "at the same resolution): the Pareto front, cheapest first, is "
                   + ", ".join(f"{p['resolution']}x{p['resolution']} {p['aa']}" for p in front) + ".")
        halving = {}
        for resolution in sorted({p["resolution"] for p in image}):
            same = [p for p in image if p["resolution"] == resolution]
            none = next((p for p in same if p["aa"] == "none"), None)
            if none is None:
                continue
            good = sorted((p for p in same if p["aa"] != "none" and p["error"] <= none["error"] / 2),
                          key=lambda p: p["cost_s"])
            if good:
                p = good[0]
                halving.setdefault(p["aa"], []).append(resolution)
                out.append(f"At {resolution}x{resolution} the cheapest mode that at least halves the no-AA error is "
                           f"{p['aa']}: MAE {none['error']:.2f} -> {p['error']:.2f} for "
                           f"{p['cost_s'] / none['cost_s']:.1f}x the time per view.")
            else:
                out.append(f"At {resolution}x{resolution} no anti-aliasing mode halves the no-AA error "
                           f"(MAE {none['error']:.2f}).")
        concentrated = [p for p in image if p["aa"] == "none" and p["worst_row_share"] >= 0.25]
        if concentrated:
            out.append("Without AA, one image row holds much of the error at "
                       + ", ".join(f"{p['resolution']} px (row {p['worst_row']}: {p['worst_row_share']:.0%})"
                                   for p in concentrated)
                       + ": a horizontal edge at the same height in every view, so the no-AA error depends on where "
                         "that edge falls inside a pixel row and is not monotonic in resolution.")
        if halving:
            best = max(halving, key=lambda k: len(halving[k]))
            out.append(f"Overall: {best} is the cheapest way to halve aliasing error at "
                       f"{len(halving[best])} of {len({p['resolution'] for p in image})} resolutions.")
    references = [p for p in sweeps["image"]["points"] if p["reference"]]
    differing = [p for p in references if p["max_abs"] > 0]
    if references and not differing:
        out.append("A second renderer reproduced the 8x8 reference bit for bit at every resolution.")
    for p in differing:
        out.append(f"A second renderer did not reproduce the 8x8 reference exactly at {p['resolution']} px: "
                   f"{p['pixels_changed']:.4%} of pixels differ, by up to {p['max_abs']:.0f} level(s) (renders of "
                   "one state by two renderers are not always bit-identical).")
    for aa in dict.fromkeys(k["aa"] for k in sweeps["image"]["skipped"]):
        skips = [k for k in sweeps["image"]["skipped"] if k["aa"] == aa]
        out.append(f"{aa} not measured at {', '.join(str(k['resolution']) for k in skips)} px: {skips[0]['reason']}.")
    effects = sweeps["effects"]["points"]
    none_aa = [p for p in effects if p["aa"] == "none"]
    if none_aa:
        base = next((p for p in none_aa if p["effects"] == "none"), None)
        parts = [f"{p['effects']} {p['cost_vs_no_effect']:+.0%} time, MAE {p['error']:.2f}" for p in none_aa
                 if p is not base and p["cost_vs_no_effect"] is not None]
        if base is not None:
            out.append(f"Effects at {base['resolution']}px without AA (no effect: MAE {base['error']:.2f}): "
                       + "; ".join(parts) + ".")
        worst = max(none_aa, key=lambda p: p["error"])
        fixes = sorted((p for p in effects if p["effects"] == worst["effects"] and p["aa"] != "none"),
                       key=lambda p: p["error"])
        if fixes:
            out.append(f"The effect set with the most aliasing is {worst['effects']} (MAE {worst['error']:.2f}); "
                       f"{fixes[0]['aa']} brings it to {fixes[0]['error']:.2f} at "
                       f"{fixes[0]['cost_s'] / worst['cost_s']:.1f}x the time.")
    precision = sweeps["precision"]["points"]
    if precision:
        f64 = [p for p in precision if p["positions"] == "float64"]
        f32 = sorted((p for p in precision if p["positions"] == "float32"), key=lambda p: p["offset_m"])
        worst64 = max(f64, key=lambda p: p["error"])
        first_bad = next((p for p in f32 if p["pixels_changed"] > 1e-3), None)
        far = f32[-1]
        text = (f"Precision: with float64 positions the worst error up to {max(p['offset_m'] for p in f64):.0e} m is "
                f"MAE {worst64['error']:.3f} ({worst64['pixels_changed']:.2%} of pixels changed); positions cast "
                f"to float32 first reach MAE {far['error']:.1f} at {far['offset_m']:.0e} m "
                f"({far['pixels_changed']:.0%} of pixels changed, float32 spacing {far['float32_spacing_m']:g} m)")
        text += (f"; float32 already changes {first_bad['pixels_changed']:.1%} of pixels at {first_bad['offset_m']:.0e} m "
                 f"(MAE {first_bad['error']:.2f}, worst pixel off by {first_bad['max_abs']:.0f})" if first_bad else "")
        out.append(text + ". Keep world positions in float64 up to BatchRenderer.update (it recentres and splits "
                          "them); never cast them to float32 before.")
    for key, targets, unit, what in (("spread_physics", SPREAD_TARGETS_M, "m", "position"),
                                     ("cartpole_physics", CARTPOLE_TARGETS, "(m, rad)", "(x, θ)"),
                                     ("cartpole_energy", None, "J", "energy drift")):
        sweep = sweeps[key]
        points = sweep["points"]
        if not points:
            continue
        name = key.replace("_", " ")
        orders = {i: observed_order([p for p in points if p["integrator"] == i])
                  for i in dict.fromkeys(p["integrator"] for p in points)}
        out.append(f"{name}: observed convergence order in substeps "
                   + ", ".join(f"{SHORT[i]} {o:.1f}" for i, o in orders.items() if o is not None) + ".")
        first = next(iter(orders))
        ratios = []
        for integrator in list(orders)[1:]:  # error ratio to the first integrator at equal substeps
            pairs = [(p["error"], q["error"]) for p in points for q in points if p["integrator"] == integrator
                     and q["integrator"] == first and p["substeps"] == q["substeps"] and q["error"] > 0]
            if pairs:
                ratios.append(f"{SHORT[integrator]} {min(a / b for a, b in pairs):.2g}-{max(a / b for a, b in pairs):.2g}x")
        if ratios:
            out.append(f"{name}: error relative to {SHORT[first]} at the same substeps: " + ", ".join(ratios) + ".")
        default = next((p for p in points if p.get("default")), None)
        if default is not None:
            dominated = [p for p in points if p is not default and p["cost_s"] <= default["cost_s"]
                         and p["error"] < default["error"]]
            text = (f"{name}: the env's setting ({SHORT[default['integrator']]} x{default['substeps']}) has "
                    f"{what} error {default['error']:.2e} {unit} at {_fmt_cost(default['cost_s'])} per world-step")
            text += ("; it is on the Pareto front" if default["pareto"] else
                     f"; it is dominated by {', '.join(p['label'] for p in dominated) or 'another point'}")
            out.append(text + ".")
        for target in targets or ():
            fit = sorted((p for p in points if p["error"] <= target), key=lambda p: p["cost_s"])
            if fit:
                out.append(f"{name}: cheapest setting with {what} error <= {target:g} {unit}: {fit[0]['label']} "
                           f"({fit[0]['error']:.2e}, {fit[0]['world_steps_per_s']:,.0f} world-steps/s).")
            else:
                out.append(f"{name}: no tested setting reaches {what} error <= {target:g} {unit}.")
        front = sorted((p for p in points if p["pareto"]), key=lambda p: p["cost_s"])
        out.append(f"{name}: Pareto front, cheapest first: " + ", ".join(p["label"] for p in front) + ".")
        if sweep["skipped"]:
            out.append(f"{name}: " + ", ".join(f"{SHORT[k['integrator']]} x{k['substeps']}" for k in sweep["skipped"])
                       + f" not run: {sweep['skipped'][0]['reason']}.")
    return out


def shadow_sweep(state: SpreadState, cfg: dict, max_framebuffer: int) -> dict:
    """Shadow-map resolution against error and time, on the spread scene with the shadows
    env's bounds (the arena). Every frame moves the bodies, so the atlas is redrawn each
    time; cost = the fastest of cfg["rounds"] passes over the settings."""
    import marl_render as mr
    from marl_render.envs import scenery
    from marl_render.envs.spread import Spread

    bounds = scenery.arena_shadow_bounds(Spread.arena_half_extent)
    resolution = cfg["effects_resolution"]
    settings = [(None, False)] + [(m, pcf) for m in cfg["shadow_maps"] for pcf in (False, True)]
    reference_setting = (cfg["shadow_reference"], True)

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

            return image, _median_time(frame, cfg["min_time"], cfg["min_frames"], cfg["max_frames"]) / scene.num_views

    started = time.perf_counter()
    reference, _ = render(reference_setting, timed=False)
    points = []
    for round_index in range(cfg["rounds"]):
        for index, setting in enumerate(settings):
            image, seconds = render(setting, timed=True)
            if round_index == 0:
                shadow_map, pcf = setting
                error = image_error(image, reference)
                points.append({"label": "no shadows" if shadow_map is None else f"{shadow_map} px{' PCF' if pcf else ''}",
                               "shadow_map": shadow_map, "pcf": pcf, "error": error["mae"], **error,
                               "cost_rounds_s": [seconds]})
            else:
                points[index]["cost_rounds_s"].append(seconds)
    for p in points:
        p["cost_s"] = min(p["cost_rounds_s"])
        p["views_per_s"] = 1 / p["cost_s"]
        p["cost_vs_no_shadows"] = p["cost_s"] / points[0]["cost_s"] - 1
    return {"what": f"spread scene at {resolution}px, lighting + shadows over the arena {bounds}; error vs a "
                    f"{cfg['shadow_reference']}-texel map with PCF (no anti-aliasing)",
            "cost": "seconds per view", "error": "mean absolute error (0-255)",
            "seconds": time.perf_counter() - started, "points": points, "skipped": []}


# ============================================================================ run / write
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
        sweeps.result["shadows"] = shadow_sweep(state, cfg, args.max_framebuffer)
        sweeps.spread_physics()
        sweeps.cartpole()
        sweeps.bar.close()
        result = {"benchmark": "accuracy", "quick": bool(args.quick), "seed": args.seed, "settings": cfg,
                  "machine": machine(), "sweeps": sweeps.result}
    finally:
        torch.set_num_threads(saved_threads)
    result["seconds"] = time.perf_counter() - started
    result["recommendations"] = recommendations(result)
    _write(args.out, result)
    return result


def _num(value, digits=2):
    if value is None:
        return "∞"
    return f"{value:.{digits}f}"


def _write(out: str, result: dict) -> None:
    s = result["sweeps"]
    m = result["machine"]
    mark = lambda p: "**yes**" if p.get("pareto") else ""  # noqa: E731
    lines = ["# Accuracy against cost", "",
             f"{m['gl_renderer']}, torch {m['torch']} ({m['cpu_threads']} thread), seed {result['seed']}, "
             f"{'quick' if result['quick'] else 'full'} run of {result['seconds']:.0f} s. Costs are measured in the "
             f"same run as the errors: renders as the fastest of {result['settings']['rounds']} round-robin passes "
             "over the settings (each the median frame time), physics as the fastest of "
             f"{result['settings']['physics_rounds']} round-robin passes of identical rollouts "
             f"({result['settings']['energy_rounds']} for energy drift). The machine is shared: compare within a "
             "table. PSNR ∞ = identical images.", "",
             "## Recommendations (derived from the numbers below)", ""]
    lines += [f"- {r}" for r in result["recommendations"]]
    lines += ["", "## Resolution x anti-aliasing", "", s["image"]["what"] + ".", "",
              "| resolution | AA | views/s | µs/view | MAE | PSNR dB | max abs | px changed | worst row (share) | Pareto "
              "| front at res |", "|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for p in s["image"]["points"]:
        lines.append(f"| {p['resolution']} | {p['aa']}{' (reference)' if p['reference'] else ''} | "
                     f"{p['views_per_s']:,.0f} | {p['cost_s'] * 1e6:,.1f} | {p['mae']:.3f} | {_num(p['psnr_db'])} | "
                     f"{p['max_abs']:.0f} | {p['pixels_changed']:.1%} | {p['worst_row']} ({p['worst_row_share']:.0%}) | "
                     f"{mark(p)} | "
                     f"{'yes' if p['pareto_at_resolution'] else ''} |")
    for aa in dict.fromkeys(k["aa"] for k in s["image"]["skipped"]):
        skips = [k for k in s["image"]["skipped"] if k["aa"] == aa]
        lines += ["", f"Not measured: {aa} at {', '.join(str(k['resolution']) for k in skips)} px ({skips[0]['reason']})."]
    lines += ["", "## Effects", "", s["effects"]["what"] + ". Pareto front within each effect set.", "",
              "| effects | AA | views/s | µs/view | time vs no effect | MAE | PSNR dB | px changed | Pareto |",
              "|---|---|---:|---:|---:|---:|---:|---:|---|"]
    for p in s["effects"]["points"]:
        vs = "" if p["cost_vs_no_effect"] is None else f"{p['cost_vs_no_effect']:+.0%}"
        lines.append(f"| {p['effects']} | {p['aa']} | {p['views_per_s']:,.0f} | {p['cost_s'] * 1e6:,.1f} | {vs} | "
                     f"{p['mae']:.3f} | {_num(p['psnr_db'])} | {p['pixels_changed']:.1%} | {mark(p)} |")
    lines += ["", "## Far from the origin: float64 vs float32 positions", "", s["precision"]["what"] + ".", "",
              "| offset (m) | positions | float32 spacing (m) | views/s | MAE | PSNR dB | max abs | px changed |",
              "|---:|---|---:|---:|---:|---:|---:|---:|"]
    for p in s["precision"]["points"]:
        lines.append(f"| {p['offset_m']:.0e} | {p['positions']} | {p['float32_spacing_m']:g} | "
                     f"{p['views_per_s']:,.0f} | {p['mae']:.3f} | {_num(p['psnr_db'])} | {p['max_abs']:.0f} | "
                     f"{p['pixels_changed']:.2%} |")
    if "shadows" in s:
        lines += ["", "## Shadows: shadow-map resolution", "", s["shadows"]["what"] + ".", "",
                  "| shadow map (per world) | PCF | views/s | µs/view | time vs no shadows | MAE | PSNR dB | px changed |",
                  "|---:|---|---:|---:|---:|---:|---:|---:|"]
        for p in s["shadows"]["points"]:
            size = "none" if p["shadow_map"] is None else f"{p['shadow_map']}x{p['shadow_map']}"
            pcf = "" if p["shadow_map"] is None else "on" if p["pcf"] else "off"
            lines.append(f"| {size} | {pcf} | {p['views_per_s']:,.0f} | {p['cost_s'] * 1e6:,.1f} | "
                         f"{p['cost_vs_no_shadows']:+.0%} | {p['mae']:.3f} | {_num(p['psnr_db'])} | "
                         f"{p['pixels_changed']:.1%} |")
    sp = s["spread_physics"]
    lines += ["", "## Spread physics: substeps x integrator", "", sp["what"] + ".", "",
              "| integrator | substeps | world-steps/s | µs/world-step | pos RMS (m) | pos max (m) | vel RMS (m/s) "
              "| pos RMS vs own x64 (m) | Pareto |", "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for p in sp["points"]:
        lines.append(f"| {p['integrator']}{' (env default)' if p['default'] else ''} | {p['substeps']} | "
                     f"{p['world_steps_per_s']:,.0f} | {p['cost_s'] * 1e6:,.2f} | {p['pos_rms_m']:.2e} | "
                     f"{p['pos_max_m']:.2e} | {p['vel_rms_m_s']:.2e} | {p['pos_rms_vs_own_64_m']:.2e} | {mark(p)} |")
    if sp["skipped"]:
        lines += ["", "Not run: " + "; ".join(f"{k['integrator']} x{k['substeps']}" for k in sp["skipped"])
                  + f" ({sp['skipped'][0]['reason']})."]
    cp = s["cartpole_physics"]
    lines += ["", "## Cart-pole physics: substeps x integrator", "", cp["what"] + ".", "",
              "| integrator | substeps | world-steps/s | µs/world-step | (x, θ) RMS | (x, θ) max | state RMS | Pareto |",
              "|---|---:|---:|---:|---:|---:|---:|---|"]
    for p in cp["points"]:
        lines.append(f"| {p['integrator']}{' (env default)' if p['default'] else ''} | {p['substeps']} | "
                     f"{p['world_steps_per_s']:,.0f} | {p['cost_s'] * 1e6:,.2f} | {p['q_rms']:.2e} | "
                     f"{p['q_max']:.2e} | {p['state_rms']:.2e} | {mark(p)} |")
    ce = s["cartpole_energy"]
    lines += ["", "## Cart-pole energy drift (frictionless)", "", ce["what"] + ".", "",
              "| integrator | substeps | world-steps/s | µs/world-step | drift mean (J) | drift max (J) | Pareto |",
              "|---|---:|---:|---:|---:|---:|---|"]
    for p in ce["points"]:
        lines.append(f"| {p['integrator']} | {p['substeps']} | {p['world_steps_per_s']:,.0f} | "
                     f"{p['cost_s'] * 1e6:,.2f} | {p['drift_mean_j']:.2e} | {p['drift_max_j']:.2e} | {mark(p)} |")
    lines += ["", "![error against time](accuracy.png)", ""]
    write_report(out, "accuracy", result, lines, allow_nan=False)
    _plot(os.path.join(out, "accuracy.png"), result)


def _plot(path: str, result: dict) -> None:
    plt = pyplot()

    s = result["sweeps"]
    fig, axes = plt.subplots(2, 3, figsize=(16, 9.5))
    panels = [("image", "aa", "resolution x anti-aliasing", "µs per view", 1e6, "MAE vs 8x8 reference (0-255)"),
              ("effects", "effects", "effects x anti-aliasing (front per effect set)", "µs per view", 1e6,
               "MAE vs 8x8 reference (0-255)"),
              ("spread_physics", "integrator", "spread physics: substeps", "µs per world-step", 1e6,
               "RMS position error (m)"),
              ("cartpole_physics", "integrator", "cart-pole physics: substeps", "µs per world-step", 1e6,
               "RMS (x, θ) error"),
              ("cartpole_energy", "integrator", "cart-pole energy drift (frictionless)", "µs per world-step", 1e6,
               "energy drift (J)")]
    for ax, (key, series, title, xlabel, scale, ylabel) in zip(axes.flat, panels):
        points = [p for p in s[key]["points"] if not p.get("reference") and p["error"] > 0]
        names = list(dict.fromkeys(p[series] for p in points))
        for index, name in enumerate(names):
            group = [p for p in points if p[series] == name]
            group.sort(key=lambda p: p["cost_s"] if series == "effects" else p.get("resolution", p.get("substeps", 0)))
            marker = "o" if series != "effects" else "os^vD"[index % 5]
            ax.plot([p["cost_s"] * scale for p in group], [p["error"] for p in group], marker=marker, ms=5,
                    lw=1, label=SHORT.get(name, name), color=f"C{index}")
            for p in group:
                tag = p.get("resolution", p.get("substeps"))
                if series == "effects":
                    tag = p["aa"]
                ax.annotate(str(tag), (p["cost_s"] * scale, p["error"]), fontsize=6, xytext=(3, 3),
                            textcoords="offset points")
        front = [p for p in points if p["pareto"]]
        ax.scatter([p["cost_s"] * scale for p in front], [p["error"] for p in front], s=120, facecolors="none",
                   edgecolors="k", linewidths=1.2, label="Pareto front", zorder=3)
        if s[key].get("group") is None and front:
            front.sort(key=lambda p: p["cost_s"])
            xs = [p["cost_s"] * scale for p in front]
            ys = [p["error"] for p in front]
            ax.step(xs, ys, where="post", color="k", lw=0.8, ls="--", zorder=2)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(fontsize=7)
    ax = axes.flat[5]
    for index, dtype in enumerate(("float64", "float32")):
        group = sorted((p for p in s["precision"]["points"] if p["positions"] == dtype), key=lambda p: p["offset_m"])
        # zero error cannot sit on a log axis: drawn at 1e-7, labelled so
        ax.plot([p["offset_m"] for p in group], [max(p["error"], 1e-7) for p in group], "o-", color=f"C{index}",
                label=f"{dtype} positions")
    ax.axhline(1e-7, color="grey", lw=0.5, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title("far from the origin (error 0 drawn at 1e-7)", fontsize=10)
    ax.set_xlabel("offset (m)")
    ax.set_ylabel("MAE vs the scene at the origin")
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7)
    fig.suptitle("error against time (log scales; circled: Pareto front)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
