"""Batched planar physics in pure torch: many worlds stepped side by side.

Every tensor is batch-first, ``[W, B, ...]`` for W worlds of B bodies (or
``[W, K, ...]`` for K obstacles). Functions are pure: they take state tensors
and return new ones (Brax / gymnax style), so a rollout is a plain loop over
``step``. There are no Python loops over worlds or bodies; the only loops are
over substeps and over a fixed, small number of solver iterations.

Model
-----
* Dynamic bodies are **circles** (agents, balls, items): ``BodyState``.
  A body with ``mass == inf`` is immovable (it collides but never moves, and
  its velocity is reported as zero). An inactive body (``active == False``)
  neither moves nor collides; ``step`` returns its tensors unchanged.
* Boxes are **static oriented obstacles** only: ``Obstacles`` (they may differ
  per world). Nothing moves them.
* The arena is the axis-aligned rectangle ``|x| <= hx, |y| <= hy``.

One substep of length ``h = dt / substeps`` does, in this order:

1. integrate the (constant over the step) applied force with
   ``cfg.integrator``; ``drag`` and ``friction`` act on the new velocity
   before positions move, so a body held by static friction does not creep;
   speeds are clamped to ``max_speed``;
2. ``body_collisions``: circle-circle impulses + positional correction that
   never touches velocities; speeds are clamped again, and no body travels
   more than ``max_speed * h`` in the substep, whatever the reason (motion or
   overlap correction) -- this is what makes the no-tunnelling bound hold;
3. ``obstacles``: circle vs oriented box, pushed out fully, normal velocity
   reflected with restitution;
4. ``walls``: positions clamped inside the arena (so never outside after a
   step), outward normal velocity reflected with restitution.
   Reflections with restitution <= 1 never raise a speed, so the clamp holds.

Only terms declared in ``cfg.terms`` are computed at all: ``step`` looks each
one up in the module-level ``TERMS`` dict, only if declared, once per step
(the entry precomputes what is fixed within the step and returns the
per-substep function). A test can monkeypatch an entry to raise and so prove
that an undeclared term never runs.

Why nothing tunnels: if every body moves less than its radius per substep
(``max_speed * dt / substeps < min_body_radius``), a centre that starts a
substep outside an obstacle by at least its radius is still outside the box
after moving, so the push-out always uses the true outside normal and never
sends a body through to the far side, however thin the box. Two approaching
circles close their gap by less than ``r_i + r_j`` per substep, so their
centres cannot pass each other either. ``PhysicsConfig`` enforces the bound;
``check_scene`` checks actual radii against ``cfg.min_body_radius``.
Limit: a gap narrower than a body between a box and a wall (or another box)
can squeeze a body into the box, because walls are resolved last; lay scenes
out with clearance.

dtype and device always follow the input tensors (float32 or float64).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from . import array_ops
from .array_ops import NumpyOps, TorchOps

__all__ = [
    "TERM_NAMES",
    "INTEGRATORS",
    "TERMS",
    "PhysicsConfig",
    "BodyState",
    "Obstacles",
    "min_substeps",
    "check_scene",
    "clamp_norm",
    "step",
    "kinetic_energy",
    "momentum",
]

TERM_NAMES = frozenset({"walls", "body_collisions", "obstacles", "friction", "drag"})
INTEGRATORS = ("semi_implicit_euler", "velocity_verlet")


# --------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------

def _is_real(x) -> bool:
    # bool is an int subclass; True as a time step is always a mistake.
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _bad(name: str, expected: str, got) -> ValueError:
    return ValueError(f"{name} must be {expected}, got {got!r}")


def min_substeps(max_speed: float, dt: float, min_body_radius: float) -> int:
    """Smallest ``substeps`` with ``max_speed * dt / substeps < min_body_radius``."""
    if not (_is_real(max_speed) and max_speed > 0):
        raise _bad("max_speed", "a finite number > 0", max_speed)
    if not (_is_real(dt) and dt > 0):
        raise _bad("dt", "a finite number > 0", dt)
    if not (_is_real(min_body_radius) and min_body_radius > 0):
        raise _bad("min_body_radius", "a finite number > 0", min_body_radius)
    return int(math.floor(max_speed * dt / min_body_radius)) + 1


@dataclass(frozen=True)
class PhysicsConfig:
    """Static settings of the simulation (hashable, shared by all worlds).

    dt: seconds per env step. substeps: int >= 1, each of ``dt / substeps``.
    integrator: "semi_implicit_euler" or "velocity_verlet".
    terms: declared terms, a subset of ``TERM_NAMES``; undeclared ones are
        never computed.
    restitution: in [0, 1], for body-body, body-obstacle and body-wall contacts.
    friction: Coulomb coefficient mu of ground friction: a moving body
        decelerates at ``mu * gravity`` (m/s^2) until it stops, and a resting
        body stays put unless ``|force| / mass > mu * gravity``.
    drag: linear damping rate (1/s): ``v <- v * exp(-drag * h)`` (exact for
        ``dv/dt = -drag v``, stable for any h).
    gravity: only used by friction (the plane is horizontal).
    arena_half_extent: (hx, hy) of the walls, centred on the origin.
    max_speed: speed clamp (m/s) applied to every body every substep.
    min_body_radius: the smallest radius this config must handle without
        tunnelling; ``max_speed * dt / substeps`` must be below it.
    solver_iterations: fixed number of collision-solver passes per substep.
    position_correction: fraction in (0, 1] of a body-body overlap removed
        per substep (before the per-substep displacement cap).
    """

    dt: float = 0.05
    substeps: int = 4
    integrator: str = "semi_implicit_euler"
    terms: frozenset = frozenset({"walls", "body_collisions", "obstacles"})
    restitution: float = 0.8
    friction: float = 0.0
    drag: float = 0.0
    gravity: float = 9.81
    arena_half_extent: tuple[float, float] = (1.0, 1.0)
    max_speed: float = 2.0
    min_body_radius: float = 0.05
    solver_iterations: int = 4
    position_correction: float = 0.5

    def __post_init__(self) -> None:
        if not (_is_real(self.dt) and self.dt > 0):
            raise _bad("dt", "a finite number > 0", self.dt)
        for name in ("substeps", "solver_iterations"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise _bad(name, "an int >= 1", v)
        if self.integrator not in INTEGRATORS:
            raise _bad("integrator", f"one of {INTEGRATORS}", self.integrator)

        # A bare string would iterate into characters; demand a collection.
        if isinstance(self.terms, str) or not hasattr(self.terms, "__iter__"):
            raise _bad("terms", f"a set of term names out of {sorted(TERM_NAMES)}", self.terms)
        terms = frozenset(self.terms)
        unknown = sorted(str(t) for t in terms - TERM_NAMES)
        if unknown:
            raise ValueError(
                f"terms must be a subset of {sorted(TERM_NAMES)}, got unknown term(s) {unknown}"
            )
        object.__setattr__(self, "terms", terms)  # frozen dataclass: normalise once

        if not (_is_real(self.restitution) and 0 <= self.restitution <= 1):
            raise _bad("restitution", "a number in [0, 1]", self.restitution)
        for name in ("friction", "drag"):
            v = getattr(self, name)
            if not (_is_real(v) and v >= 0):
                raise _bad(name, "a finite number >= 0", v)
        for name in ("gravity", "max_speed", "min_body_radius"):
            v = getattr(self, name)
            if not (_is_real(v) and v > 0):
                raise _bad(name, "a finite number > 0", v)
        if not (_is_real(self.position_correction) and 0 < self.position_correction <= 1):
            raise _bad("position_correction", "a number in (0, 1]", self.position_correction)

        ahe = self.arena_half_extent
        if (
            isinstance(ahe, (str, bytes))
            or not hasattr(ahe, "__len__")
            or len(ahe) != 2
            or not all(_is_real(a) and a > 0 for a in ahe)
        ):
            raise _bad("arena_half_extent", "a pair (hx, hy) of finite numbers > 0", ahe)
        object.__setattr__(self, "arena_half_extent", (float(ahe[0]), float(ahe[1])))

        # No tunnelling: see the module docstring for why the radius is the bound.
        travel = self.max_speed * self.dt / self.substeps
        if not travel < self.min_body_radius:
            need = min_substeps(self.max_speed, self.dt, self.min_body_radius)
            raise ValueError(
                f"substeps must be >= {need} so that max_speed * dt / substeps "
                f"< min_body_radius (no tunnelling), got substeps={self.substeps}: "
                f"{self.max_speed} * {self.dt} / {self.substeps} = {travel:.6g} "
                f">= {self.min_body_radius}"
            )

    @property
    def substep_dt(self) -> float:
        return self.dt / self.substeps


# --------------------------------------------------------------------------
# State
# --------------------------------------------------------------------------

class BodyState(NamedTuple):
    """Circles, batch-first. ``mass == inf`` marks an immovable body."""

    pos: Tensor      # [W, B, 2]
    vel: Tensor      # [W, B, 2]
    radius: Tensor   # [W, B]
    mass: Tensor     # [W, B]
    active: Tensor   # [W, B] bool

    @classmethod
    def make(
        cls,
        pos: Tensor,
        radius,
        vel: Tensor | None = None,
        mass=1.0,
        active=True,
    ) -> BodyState:
        """Convenience constructor: scalars broadcast to ``[W, B]``."""
        W, B = pos.shape[:2]
        like = dict(dtype=pos.dtype, device=pos.device)
        vel = torch.zeros_like(pos) if vel is None else vel
        radius = torch.as_tensor(radius, **like).expand(W, B).clone()
        mass = torch.as_tensor(mass, **like).expand(W, B).clone()
        active = torch.as_tensor(active, dtype=torch.bool, device=pos.device).expand(W, B).clone()
        return cls(pos, vel, radius, mass, active)


class Obstacles(NamedTuple):
    """Static oriented boxes (never moved by the simulation)."""

    center: Tensor       # [W, K, 2]
    half_extent: Tensor  # [W, K, 2], in the box's own frame
    angle: Tensor        # [W, K], radians, counter-clockwise


def _eps(t) -> float:
    return float(np.finfo(t.dtype).eps) if isinstance(t, np.ndarray) else float(torch.finfo(t.dtype).eps)


def _movable(state: BodyState, ops=TorchOps):
    return state.active & ops.isfinite(state.mass)


def _inv_mass(state: BodyState, ops=TorchOps):
    # 0 for immovable and inactive bodies, so they take no share of an impulse.
    return ops.where(_movable(state, ops), ops.reciprocal(state.mass), ops.zeros_like(state.mass))


def clamp_norm(v: Tensor, max_norm) -> Tensor:
    """Scale vectors (last dim) down to at most ``max_norm``; shorter ones are untouched.

    ``max_norm`` is a float > 0 or a tensor broadcasting against ``v[..., :1]``.
    """
    return _clamp_norm(TorchOps, v, max_norm)


def _clamp_norm(ops, v, max_norm):
    # A zero vector gives max_norm / 0 = inf -> scale 1 -> stays zero (no NaN). A float over a
    # tensor is torch's reciprocal times the float: written so, both namespaces give its bits.
    norm = ops.norm(v, keepdim=True)
    scale = ops.reciprocal(norm) * max_norm if isinstance(max_norm, (int, float)) else max_norm / norm
    return v * ops.clamp_max(scale, 1.0)


def check_scene(state: BodyState, obstacles: Obstacles | None, cfg: PhysicsConfig) -> None:
    """Setup-time sanity check (syncs with the device; call at reset, not per step).

    Raises ValueError if shapes disagree, if an active body is smaller than
    ``cfg.min_body_radius`` (the no-tunnelling bound would not hold), if a
    mass is not > 0, if a body cannot fit the arena or if a box is degenerate.
    """
    W, B = state.pos.shape[:2]
    expected = {"pos": (W, B, 2), "vel": (W, B, 2), "radius": (W, B), "mass": (W, B), "active": (W, B)}
    for name, shape in expected.items():
        got = tuple(getattr(state, name).shape)
        if got != shape:
            raise _bad(f"state.{name}", f"of shape {shape}", got)
    if state.active.dtype != torch.bool:
        raise _bad("state.active", "a bool tensor", state.active.dtype)
    act = state.active
    if bool((act & (state.radius < cfg.min_body_radius)).any()):
        rmin = float(state.radius[act].min())
        raise _bad("state.radius", f">= cfg.min_body_radius={cfg.min_body_radius} for active bodies", rmin)
    if bool((act & ~(state.mass > 0)).any()):
        raise _bad("state.mass", "> 0 (inf for immovable) for active bodies", float(state.mass[act].min()))
    if bool((act & (state.radius >= min(cfg.arena_half_extent))).any()):
        raise _bad("state.radius", f"< min(arena_half_extent)={min(cfg.arena_half_extent)}",
                   float(state.radius[act].max()))
    if obstacles is not None:
        K = obstacles.center.shape[1]
        for name, shape in {"center": (W, K, 2), "half_extent": (W, K, 2), "angle": (W, K)}.items():
            got = tuple(getattr(obstacles, name).shape)
            if got != shape:
                raise _bad(f"obstacles.{name}", f"of shape {shape}", got)
        if K and bool((obstacles.half_extent < 0).any()):
            raise _bad("obstacles.half_extent", ">= 0", float(obstacles.half_extent.min()))


# --------------------------------------------------------------------------
# Terms. Each entry of TERMS is called once per step, only if declared:
#     term(state, obstacles, cfg, h) -> apply(pos, vel) -> (pos, vel)
# The outer call precomputes what is constant within the step (masks, bounds,
# rotations); the returned ``apply`` runs once per substep on the current
# positions and velocities.
# --------------------------------------------------------------------------

def _drag(state, obstacles, cfg, h, ops=TorchOps):
    # Exact solution of dv/dt = -drag * v over h: never overshoots zero.
    factor = math.exp(-cfg.drag * h)

    def apply(pos, vel):
        return pos, vel * factor

    return apply


def _friction(state, obstacles, cfg, h, ops=TorchOps):
    # Kinetic Coulomb friction removes mu*g*h of speed, opposite to motion; it
    # may stop a body but never reverse it (what is left is static friction).
    dv = cfg.friction * cfg.gravity * h

    def apply(pos, vel):
        speed = ops.norm(vel, keepdim=True)
        new_speed = ops.clamp_min(speed - dv, 0.0)
        return pos, vel * (new_speed / ops.clamp_min(speed, _eps(vel)))

    return apply


@functools.lru_cache(maxsize=64)
def _pair_constants(B: int, dtype: torch.dtype, device: torch.device, numpy: bool) -> tuple:
    """(eye [B, B] bool, fallback normals [B, B, 2]): the same every step, built once (read only)."""
    like = torch.empty(0, dtype=dtype, device=device)
    eye, fallback = torch.eye(B, dtype=torch.bool, device=device), _fallback_normals(B, like)
    return (eye.numpy(), fallback.numpy()) if numpy else (eye, fallback)


def _fallback_normals(B: int, like: Tensor) -> Tensor:
    """[B, B, 2] unit normals for pairs whose centres coincide exactly.

    Antisymmetric (n_ij = -n_ji) so the pair is pushed apart, spread over the
    circle by the golden angle so a pile of coincident bodies fans out, and
    deterministic.
    """
    i = torch.arange(B, device=like.device)
    lo = torch.minimum(i[:, None], i[None, :])
    hi = torch.maximum(i[:, None], i[None, :])
    phi = (lo * B + hi).to(like.dtype) * 2.399963229728653  # golden angle
    sign = torch.where(i[:, None] < i[None, :], 1.0, -1.0).to(like.dtype)
    return torch.stack([torch.cos(phi), torch.sin(phi)], dim=-1) * sign[..., None]


def _body_collisions(state, obstacles, cfg, h, ops=TorchOps):
    """Circle-circle contacts for all pairs at once ([W, B, B]).

    Velocity: restitution impulses split by inverse mass, a few Jacobi passes
    that re-read the velocities so chains of contacts settle.
    Position: the overlap is split by inverse mass and only moved, never turned
    into velocity, so bodies spawned on top of each other separate without
    gaining speed. Each pair's share is divided by the larger contact count of
    its two bodies: symmetric (momentum stays exact) and under-relaxed, so a
    pile does not over-shoot; step() then caps every body's substep travel.
    """
    W, B = state.pos.shape[:2]
    eps = _eps(state.pos)
    inv_m = _inv_mass(state, ops)
    eye, fallback = _pair_constants(B, _torch_dtype(state.pos), _device(state.pos), ops is NumpyOps)
    inv_sum = inv_m[:, :, None] + inv_m[:, None, :]                          # [W,B,B]
    # Both active, distinct, and at least one of them can move.
    pair_ok = state.active[:, :, None] & state.active[:, None, :] & ~eye & (inv_sum > 0)
    share = ops.where(pair_ok, inv_m[:, :, None] / ops.clamp_min(inv_sum, eps), ops.zeros_like(inv_sum))
    rsum = state.radius[:, :, None] + state.radius[:, None, :]
    kick = -(1.0 + cfg.restitution)

    def apply(pos, vel):
        d = pos[:, :, None, :] - pos[:, None, :, :]                           # p_i - p_j
        dist = ops.norm(d)
        contact = pair_ok & (dist < rsum)
        if not contact.any():  # no pair touches (the usual case): every impulse and correction is 0
            return pos, vel
        n = ops.where((dist > eps)[..., None], d / ops.clamp_min(dist, eps)[..., None], fallback)
        count = ops.clamp_min(contact.sum(-1, dtype=pos.dtype), 1.0)             # [W,B]
        # Body i's part of pair (i, j), zero where there is no contact.
        weight = ops.where(contact, share, 0.0) / ops.maximum(count[:, :, None], count[:, None, :])
        kicked = kick * weight

        for _ in range(cfg.solver_iterations):
            vn = ops.sum_xy((vel[:, :, None, :] - vel[:, None, :, :]) * n)  # < 0: approaching
            dvn = kicked * ops.clamp_max(vn, 0.0)
            vel = vel + (dvn[..., None] * n).sum(2)

        # Positional correction: pure projection, velocity untouched.
        depth = ops.clamp_min(rsum - dist, 0.0)
        pos = pos + ((cfg.position_correction * weight * depth)[..., None] * n).sum(2)
        return pos, vel

    return apply


def _obstacles(state, obstacles, cfg, h, ops=TorchOps):
    """Circle vs static oriented box: push out along the closest-feature normal.

    Outside the box the normal runs from the closest surface point to the
    centre; a centre inside (which the substep bound prevents for moving
    bodies, but spawns can do) leaves through the nearest face. Each pass
    resolves only the deepest box per body, so a body touching two boxes that
    share a face is not reflected twice for one contact.
    """
    if obstacles is None or obstacles.center.shape[1] == 0:
        return lambda pos, vel: (pos, vel)
    kick = 1.0 + cfg.restitution
    eps = _eps(state.pos)
    fixed = ~_movable(state, ops)[:, :, None]                                # [W,B,1]
    r = state.radius[:, :, None]
    c, s = ops.cos(obstacles.angle), ops.sin(obstacles.angle)
    # Rows of R(-angle) (world -> box) and of R(+angle) (box -> world): [W,1,K,2,2].
    to_box = ops.stack([ops.stack([c, s], -1), ops.stack([-s, c], -1)], -2)[:, None]
    to_world = ops.swap_last(to_box)
    he = obstacles.half_extent[:, None]                                      # [W,1,K,2]
    center = obstacles.center[:, None]

    def apply(pos, vel):
        for _ in range(cfg.solver_iterations):
            rel = (pos[:, :, None, :] - center)[..., None, :]                # [W,B,K,1,2]
            local = ops.sum_xy(to_box * rel)                                 # [W,B,K,2]
            delta = local - ops.maximum(ops.minimum(local, he), -he)         # centre - closest point
            dist_out = ops.norm(delta)
            inside = dist_out <= 0
            gap = he - ops.abs(local)                                        # to the faces, per axis
            use_x = gap[..., 0] <= gap[..., 1]
            n_in = ops.copysign(ops.cast_like(ops.stack([use_x, ~use_x], -1), local), local)
            n_out = delta / ops.clamp_min(dist_out, eps)[..., None]
            n_loc = ops.where(inside[..., None], n_in, n_out)
            depth = ops.where(inside, r + ops.min_last(gap), r - dist_out)
            depth = ops.where(fixed, -1.0, depth)

            depth_k, k = ops.max_last(depth)                                 # deepest box per body
            n_all = ops.sum_xy(to_world * n_loc[..., None, :])               # world frame [W,B,K,2]
            n_w = ops.pick(n_all, k, 2)
            hit = depth_k > 0
            pos = pos + ops.clamp_min(depth_k, 0.0)[..., None] * n_w
            vn = ops.sum_xy(vel * n_w)
            vel = vel - (kick * ops.where(hit, ops.clamp_max(vn, 0.0), 0.0))[..., None] * n_w
        return pos, vel

    return apply


def _walls(state, obstacles, cfg, h, ops=TorchOps):
    hi = _arena_half(state.pos, cfg) - state.radius[..., None]               # [W,B,2]
    lo = -hi
    fixed = ~_movable(state, ops)[..., None]
    e = cfg.restitution

    def apply(pos, vel):
        # Clamp centres to [-(H - r), H - r]: bodies are never outside afterwards.
        out_lo = (pos < lo) & ~fixed
        out_hi = (pos > hi) & ~fixed
        if not (out_lo | out_hi).any():  # nobody at a wall (the usual case): nothing to clamp or reflect
            return pos, vel
        pos = ops.where(out_lo, lo, ops.where(out_hi, hi, pos))
        # Reflect only an outward normal velocity (a body sliding along a wall keeps it).
        bounce = (out_lo & (vel < 0)) | (out_hi & (vel > 0))
        vel = ops.where(bounce, -e * vel, vel)
        return pos, vel

    return apply


def _arena_half(like, cfg):
    """The arena's half extents as an array of `like`'s kind, dtype and device."""
    if isinstance(like, np.ndarray):
        return np.asarray(cfg.arena_half_extent, dtype=like.dtype)
    return torch.tensor(cfg.arena_half_extent, dtype=like.dtype, device=like.device)


def _torch_dtype(x) -> torch.dtype:
    return getattr(torch, x.dtype.name) if isinstance(x, np.ndarray) else x.dtype


def _device(x) -> torch.device:
    return torch.device("cpu") if isinstance(x, np.ndarray) else x.device


#: Term builders by name, looked up at call time and only for declared terms.
TERMS: dict[str, Callable] = {
    "drag": _drag,
    "friction": _friction,
    "body_collisions": _body_collisions,
    "obstacles": _obstacles,
    "walls": _walls,
}


# --------------------------------------------------------------------------
# Stepping
# --------------------------------------------------------------------------

def step(state: BodyState, force: Tensor, obstacles: Obstacles | None, cfg: PhysicsConfig) -> BodyState:
    """Advance all worlds by ``cfg.dt`` in ``cfg.substeps`` substeps.

    ``force`` [W, B, 2] (N) is held constant over the step. ``obstacles`` may be
    None: no boxes. Returns a new BodyState; inactive bodies are returned
    bit-for-bit unchanged, immovable ones keep their position with zero velocity.

    CPU float batches run on numpy arrays over the same memory (envs/array_ops.py: at
    small batches the cost is the number of calls); the results are torch's bits.
    """
    ops = array_ops.for_tensors(*state, force, *(obstacles or ()))
    if ops is TorchOps:
        return _step(ops, state, force, obstacles, cfg)
    arrays = BodyState(*(t.numpy() for t in state))
    boxes = None if obstacles is None else Obstacles(*(t.numpy() for t in obstacles))
    with ops.quiet():
        moved = _step(ops, arrays, force.numpy(), boxes, cfg)
    return state._replace(pos=torch.from_numpy(moved.pos), vel=torch.from_numpy(moved.vel))


def _step(ops, state: BodyState, force, obstacles: Obstacles | None, cfg: PhysicsConfig) -> BodyState:
    h = cfg.dt / cfg.substeps
    movable = _movable(state, ops)[..., None]
    # where() rather than a product: inf mass or an inactive zero mass must not make NaNs.
    accel = ops.where(movable, force / state.mass[..., None], ops.zeros_like(force))
    # Fixed order: velocity-only terms, then contacts; walls last so nothing ends outside.
    # Velocity Verlet splits drag around the force kick (Strang splitting): applied whole
    # after the kick it would make the scheme first order. Coulomb friction stays whole,
    # after the kick, so that static friction still holds a body exactly.
    split = cfg.integrator == "velocity_verlet" and "drag" in cfg.terms
    half_drag = TERMS["drag"](state, obstacles, cfg, h / 2, ops=ops) if split else None
    velocity_terms = [half_drag if split and t == "drag" else TERMS[t](state, obstacles, cfg, h, ops=ops)
                      for t in ("drag", "friction") if t in cfg.terms]
    contact_terms = [TERMS[t](state, obstacles, cfg, h, ops=ops) for t in ("body_collisions",) if t in cfg.terms]
    boundary_terms = [TERMS[t](state, obstacles, cfg, h, ops=ops) for t in ("obstacles", "walls") if t in cfg.terms]
    max_travel = cfg.max_speed * h
    dv = accel * h

    pos = state.pos
    vel = ops.where(movable, _clamp_norm(ops, state.vel, cfg.max_speed), ops.zeros_like(state.vel))
    for _ in range(cfg.substeps):
        pos0, v0 = pos, vel
        # Velocity first, so drag and friction act before anything moves.
        v1 = v0
        if split:
            _, v1 = half_drag(pos0, v1)
        v1 = v1 + dv
        for term in velocity_terms:
            _, v1 = term(pos0, v1)
        vel = _clamp_norm(ops, v1, cfg.max_speed)
        if cfg.integrator == "semi_implicit_euler":
            pos = pos0 + vel * h
        else:
            # Velocity Verlet with a force held constant over the substep (contacts
            # are impulses, not forces): x += v0 h + a h^2 / 2 == (v0 + v1) h / 2.
            pos = pos0 + (v0 + vel) * (0.5 * h)
        # Immovable and inactive bodies started at zero velocity with zero
        # acceleration, and no term gives them any, so they stay exactly put.

        if contact_terms:
            for term in contact_terms:
                pos, vel = term(pos, vel)
            # Impulses can speed a body up (a light one hit by a heavy one).
            vel = _clamp_norm(ops, vel, cfg.max_speed)
            # Travel cap (motion + overlap correction): the no-tunnelling
            # invariant. Integration alone already respects it.
            pos = pos0 + _clamp_norm(ops, pos - pos0, max_travel)
        # Reflections with restitution <= 1 never increase a speed: no clamp after.
        for term in boundary_terms:
            pos, vel = term(pos, vel)

    active = state.active[..., None]
    return state._replace(pos=ops.where(active, pos, state.pos), vel=ops.where(active, vel, state.vel))


def kinetic_energy(state: BodyState) -> Tensor:
    """Total kinetic energy per world, [W] (immovable and inactive bodies count 0)."""
    ke = 0.5 * state.mass * (state.vel * state.vel).sum(-1)
    return torch.where(_movable(state), ke, torch.zeros_like(ke)).sum(-1)


def momentum(state: BodyState) -> Tensor:
    """Total linear momentum per world, [W, 2] (movable, active bodies only)."""
    p = state.mass[..., None] * state.vel
    return torch.where(_movable(state)[..., None], p, torch.zeros_like(p)).sum(1)
