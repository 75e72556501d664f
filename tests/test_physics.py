"""Tests for envs/planar.py (batched planar physics), envs/cartpole_dynamics.py and envs/dmc_rewards.py
(dm_control's cart-pole and its rewards)."""

import math
import sys
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

try:  # installed package layout
    from marl_render.envs import cartpole_dynamics as C
    from marl_render.envs import dmc_rewards as R
    from marl_render.envs import planar as P
except ImportError:  # repository checkout: envs/ at the root
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from envs import cartpole_dynamics as C
    from envs import dmc_rewards as R
    from envs import planar as P


DTYPES = [torch.float32, torch.float64]


pytestmark = pytest.mark.usefixtures("single_torch_thread")


def scene(W, B, radius=0.1, spread=0.8, dtype=torch.float64, seed=0, speed=0.0):
    """Random bodies inside [-spread, spread]^2, velocities of norm <= speed."""
    g = torch.Generator().manual_seed(seed)
    pos = (torch.rand(W, B, 2, generator=g, dtype=dtype) * 2 - 1) * spread
    vel = P.clamp_norm(torch.randn(W, B, 2, generator=g, dtype=dtype) * speed, speed)
    return P.BodyState.make(pos, radius, vel=vel)


def pair_distances(pos):
    B = pos.shape[1]
    d = (pos[:, :, None] - pos[:, None]).norm(dim=-1)
    return d + torch.eye(B, dtype=pos.dtype) * 1e9  # ignore self-pairs


def box_frame(p, center, angle):
    """World point(s) [..., 2] in the frame of a box (angle: float or tensor broadcasting to p[..., 0])."""
    angle = torch.as_tensor(angle, dtype=p.dtype)
    c, s = angle.cos(), angle.sin()
    rel = p - torch.as_tensor(center, dtype=p.dtype)
    return torch.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1]], -1)


def box_distance(p, center, half, angle):
    """Signed distance from point(s) to an oriented box (negative inside); independent of the module."""
    local = box_frame(p, center, angle)
    half = torch.as_tensor(half, dtype=p.dtype)
    q = local.abs() - half
    outside = q.clamp_min(0).norm(dim=-1)
    inside = q.max(dim=-1).values.clamp(max=0)
    return outside + inside


# --------------------------------------------------------------------------
# Shapes, dtypes, masks
# --------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("integrator", P.INTEGRATORS)
def test_shapes_and_dtype_preserved(dtype, integrator):
    cfg = P.PhysicsConfig(terms=P.TERM_NAMES, integrator=integrator, friction=0.1, drag=0.2)
    W, B, K = 3, 5, 2
    s = scene(W, B, dtype=dtype, speed=1.0)
    obs = P.Obstacles(torch.zeros(W, K, 2, dtype=dtype), torch.full((W, K, 2), 0.1, dtype=dtype),
                      torch.zeros(W, K, dtype=dtype))
    out = P.step(s, torch.ones(W, B, 2, dtype=dtype), obs, cfg)
    for name in ("pos", "vel", "radius", "mass", "active"):
        a, b = getattr(s, name), getattr(out, name)
        assert a.shape == b.shape and a.dtype == b.dtype, name
    assert out.pos.dtype == dtype and not torch.equal(out.pos, s.pos)
    ke = P.kinetic_energy(out)
    assert ke.shape == (W,) and ke.dtype == dtype


def test_inactive_bodies_unchanged_and_ignored():
    cfg = P.PhysicsConfig(terms=P.TERM_NAMES, friction=0.1, drag=0.1, restitution=1.0)
    # Body 0 flies through where body 1 (inactive) sits; body 2 is inactive and
    # outside the arena with a huge velocity.
    pos = torch.tensor([[[-0.5, 0.0], [0.0, 0.0], [5.0, 5.0]]], dtype=torch.float64)
    vel = torch.tensor([[[1.5, 0.0], [3.0, -1.0], [100.0, 0.0]]], dtype=torch.float64)
    active = torch.tensor([[True, False, False]])
    s = P.BodyState(pos, vel, torch.full((1, 3), 0.1, dtype=torch.float64),
                    torch.ones(1, 3, dtype=torch.float64), active)
    alone = P.BodyState(pos[:, :1], vel[:, :1], s.radius[:, :1], s.mass[:, :1], active[:, :1])
    force = torch.ones(1, 3, 2, dtype=torch.float64)
    for _ in range(30):
        s = P.step(s, force, None, cfg)
        alone = P.step(alone, force[:, :1], None, cfg)
    assert torch.equal(s.pos[:, 1:], pos[:, 1:]) and torch.equal(s.vel[:, 1:], vel[:, 1:])
    # The active body moved exactly as if the inactive ones did not exist.
    assert torch.equal(s.pos[:, :1], alone.pos) and torch.equal(s.vel[:, :1], alone.vel)
    assert s.pos[0, 0, 0] > 0.2  # it passed through body 1's place


def test_immovable_body_stays_and_reflects():
    cfg = P.PhysicsConfig(terms={"body_collisions"}, restitution=1.0, dt=0.02, substeps=2)
    pos = torch.tensor([[[-0.5, 0.0], [0.0, 0.0]]], dtype=torch.float64)
    vel = torch.tensor([[[1.0, 0.0], [0.3, 0.0]]], dtype=torch.float64)
    mass = torch.tensor([[1.0, math.inf]], dtype=torch.float64)
    s = P.BodyState(pos, vel, torch.full((1, 2), 0.1, dtype=torch.float64), mass, torch.ones(1, 2, dtype=torch.bool))
    for _ in range(60):
        s = P.step(s, torch.zeros_like(pos), None, cfg)
        assert torch.isfinite(s.pos).all() and torch.isfinite(s.vel).all()
    assert torch.equal(s.pos[0, 1], pos[0, 1]) and torch.equal(s.vel[0, 1], torch.zeros(2, dtype=torch.float64))
    assert torch.allclose(s.vel[0, 0], torch.tensor([-1.0, 0.0], dtype=torch.float64))  # bounced elastically
    assert torch.isfinite(P.kinetic_energy(s)).all()


@pytest.mark.parametrize("integrator", P.INTEGRATORS)
def test_constant_force_integration(integrator):
    cfg = P.PhysicsConfig(terms=set(), dt=0.1, substeps=4, integrator=integrator, max_speed=100.0,
                          min_body_radius=10.0)
    a, n, h = 3.0, 4 * 5, 0.1 / 4
    s = P.BodyState.make(torch.zeros(1, 1, 2, dtype=torch.float64), 10.0, mass=2.0)
    for _ in range(5):
        s = P.step(s, torch.tensor([[[2.0 * a, 0.0]]], dtype=torch.float64), None, cfg)
    # Velocity Verlet is exact for constant acceleration; semi-implicit Euler
    # moves with the end-of-substep velocity: x = a h^2 n (n + 1) / 2.
    expected = 0.5 * a * (n * h) ** 2 if integrator == "velocity_verlet" else a * h * h * n * (n + 1) / 2
    assert s.pos[0, 0, 0].item() == pytest.approx(expected, rel=1e-12)
    assert s.vel[0, 0, 0].item() == pytest.approx(a * n * h, rel=1e-12)


def test_speed_clamp_holds_after_impulses():
    # A heavy body at max speed hits a light one at rest: the light one would leave at ~2x max speed.
    cfg = P.PhysicsConfig(terms={"body_collisions"}, restitution=1.0, max_speed=1.0, dt=0.05, substeps=1,
                          min_body_radius=0.1)
    s = P.BodyState(torch.tensor([[[-0.3, 0.0], [0.0, 0.0]]], dtype=torch.float64),
                    torch.tensor([[[1.0, 0.0], [0.0, 0.0]]], dtype=torch.float64),
                    torch.full((1, 2), 0.1, dtype=torch.float64), torch.tensor([[100.0, 1.0]], dtype=torch.float64),
                    torch.ones(1, 2, dtype=torch.bool))
    for _ in range(10):
        s = P.step(s, torch.zeros(1, 2, 2, dtype=torch.float64), None, cfg)
        assert (s.vel.norm(dim=-1) <= 1.0 + 1e-12).all()
    assert s.vel[0, 1, 0].item() == pytest.approx(1.0)  # it was hit, and clamped


# --------------------------------------------------------------------------
# Walls and obstacles: nothing ends outside / inside / beyond
# --------------------------------------------------------------------------

@pytest.mark.parametrize("integrator", P.INTEGRATORS)
def test_walls_never_left_at_max_speed(integrator):
    r, ms, half = 0.1, 4.0, (1.0, 0.6)
    cfg = P.PhysicsConfig(dt=0.05, substeps=P.min_substeps(ms, 0.05, r), max_speed=ms, min_body_radius=r,
                          arena_half_extent=half, terms={"walls"}, restitution=0.9, integrator=integrator)
    dirs = torch.tensor([[1, 0], [-1, 0], [0, 1], [0, -1], [0.6, 0.8], [-0.8, -0.6]], dtype=torch.float32)
    W = dirs.shape[0]
    s = P.BodyState.make(torch.zeros(W, 1, 2), r, vel=(ms * dirs)[:, None])
    force = 50.0 * dirs[:, None]  # keeps pushing outwards, beyond what max_speed allows
    bound = torch.tensor(half) - r
    for i in range(400):
        s = P.step(s, force if i < 200 else -force, None, cfg)
        assert (s.pos.abs() <= bound + 1e-6).all(), i
        assert (s.vel.norm(dim=-1) <= ms * (1 + 1e-6)).all()
    assert (s.pos.abs() < bound - 0.05).any()  # in the second half it was pushed back inwards


def test_wall_bounce_reflects_with_restitution():
    cfg = P.PhysicsConfig(terms={"walls"}, restitution=0.5, arena_half_extent=(1.0, 1.0), dt=0.05, substeps=4)
    s = P.BodyState.make(torch.tensor([[[0.7, 0.0]]], dtype=torch.float64), 0.1,
                         vel=torch.tensor([[[1.0, 0.5]]], dtype=torch.float64))
    for _ in range(10):
        s = P.step(s, torch.zeros(1, 1, 2, dtype=torch.float64), None, cfg)
    assert torch.allclose(s.vel[0, 0], torch.tensor([-0.5, 0.5], dtype=torch.float64))


def test_wall_does_not_reflect_a_body_already_heading_back_in():
    cfg = P.PhysicsConfig(terms={"walls"}, restitution=0.5, arena_half_extent=(1.0, 1.0))
    s = P.BodyState.make(torch.tensor([[[1.5, 0.0]]], dtype=torch.float64), 0.1,
                         vel=torch.tensor([[[-0.5, 0.0]]], dtype=torch.float64))
    s = P.step(s, torch.zeros(1, 1, 2, dtype=torch.float64), None, cfg)
    # Clamped to 0.9 in the first of 4 substeps, then 3 more substeps inwards at the same velocity.
    assert s.pos[0, 0].tolist() == [pytest.approx(0.9 - 0.5 * 0.05 * 3 / 4), 0.0]
    assert s.vel[0, 0].tolist() == [-0.5, 0.0]


THIN_R = 0.06
THIN_MS = 2.0
THIN_ANGLES = [0.0, 0.3, math.pi / 4, 1.2, math.pi / 2, 2.5, -2.0]


def thin_box_setup(offset=0.0, force_on=False):
    """One world per angle: a box of half thickness == radius, a body aimed at it at max speed."""
    dt = 0.05
    cfg = P.PhysicsConfig(dt=dt, substeps=P.min_substeps(THIN_MS, dt, THIN_R), max_speed=THIN_MS,
                          min_body_radius=THIN_R, arena_half_extent=(3.0, 3.0),
                          restitution=0.0 if force_on else 1.0,
                          terms={"obstacles", "walls"})
    # The travel per substep is as close to the radius as validation allows.
    assert THIN_MS * cfg.substep_dt > 0.8 * THIN_R
    W = len(THIN_ANGLES)
    ang = torch.tensor(THIN_ANGLES, dtype=torch.float64)
    normal = torch.stack([ang.cos(), ang.sin()], -1)                 # box's local +x in world
    tangent = torch.stack([-ang.sin(), ang.cos()], -1)
    center = torch.tensor([0.2, -0.1], dtype=torch.float64)
    half = (THIN_R, 0.5)
    obs = P.Obstacles(center.expand(W, 1, 2).clone(), torch.tensor(half, dtype=torch.float64).expand(W, 1, 2).clone(),
                      ang[:, None].clone())
    start = center - 0.7 * normal + offset * tangent
    s = P.BodyState.make(start[:, None], THIN_R, vel=(THIN_MS * normal)[:, None])
    force = (20.0 * normal)[:, None] if force_on else torch.zeros(W, 1, 2, dtype=torch.float64)
    P.check_scene(s, obs, cfg)
    return cfg, s, obs, force, center, half


@pytest.mark.parametrize("force_on", [False, True])
def test_thin_obstacle_not_tunnelled(force_on):
    cfg, s, obs, force, center, half = thin_box_setup(force_on=force_on)
    angles = torch.tensor(THIN_ANGLES, dtype=torch.float64)
    # ~6 steps to reach the box; 20 steps is long enough to bounce off, short enough not to come back from a wall.
    for i in range(20):
        s = P.step(s, force, obs, cfg)
        p = s.pos[:, 0]
        assert (box_distance(p, center, half, angles) >= THIN_R - 1e-9).all(), i  # never inside
        assert (box_frame(p, center, angles)[:, 0] < 0).all(), i                   # never beyond
    local_v = box_frame(s.vel[:, 0] + center, center, angles)[:, 0]
    if force_on:  # inelastic: pressed against the near face, at rest along the normal
        assert torch.allclose(box_frame(s.pos[:, 0], center, angles)[:, 0],
                              torch.full_like(angles, -(half[0] + THIN_R)), atol=1e-9, rtol=0)
        assert local_v.abs().max() < 1e-9
    else:  # bounced back towards where it came from, at full speed (restitution 1)
        assert torch.allclose(local_v, torch.full_like(angles, -THIN_MS), atol=1e-9, rtol=0)


def test_obstacle_corner_hits_stay_outside():
    angles = torch.tensor(THIN_ANGLES, dtype=torch.float64)
    for offset in (0.5, 0.53, 0.58):  # at, near and grazing the box's end (half length 0.5)
        cfg, s, obs, force, center, half = thin_box_setup(offset=offset)
        for _ in range(20):
            s = P.step(s, force, obs, cfg)
            assert (box_distance(s.pos[:, 0], center, half, angles) >= THIN_R - 1e-9).all()


def test_body_spawned_inside_box_is_pushed_out_nearest_face():
    cfg = P.PhysicsConfig(terms={"obstacles"})
    obs = P.Obstacles(torch.zeros(2, 1, 2), torch.tensor([[0.3, 0.1]]).expand(2, 1, 2), torch.zeros(2, 1))
    # World 0 is nearest the +x face (0.05 away, vs 0.08 to +y); world 1 nearest the +y face.
    s = P.BodyState.make(torch.tensor([[[0.25, 0.02]], [[0.1, 0.05]]]), 0.05)
    s = P.step(s, torch.zeros(2, 1, 2), obs, cfg)
    assert s.pos[:, 0].tolist() == [pytest.approx([0.35, 0.02], abs=1e-6), pytest.approx([0.1, 0.15], abs=1e-6)]


def test_two_boxes_sharing_a_face_act_like_one_box():
    # A body hitting the seam between two boxes must be pushed and reflected
    # once, exactly as by a single box covering both.
    cfg = P.PhysicsConfig(terms={"obstacles"}, restitution=1.0, max_speed=2.0, dt=0.05, substeps=2,
                          min_body_radius=0.1, arena_half_extent=(3.0, 3.0))
    two = P.Obstacles(torch.tensor([[[0.0, -0.25], [0.0, 0.25]]], dtype=torch.float64),
                      torch.tensor([[[0.05, 0.25], [0.05, 0.25]]], dtype=torch.float64),
                      torch.zeros(1, 2, dtype=torch.float64))
    one = P.Obstacles(torch.tensor([[[0.0, 0.0]]], dtype=torch.float64),
                      torch.tensor([[[0.05, 0.5]]], dtype=torch.float64), torch.zeros(1, 1, dtype=torch.float64))
    start = P.BodyState.make(torch.tensor([[[-0.43, 0.0]]], dtype=torch.float64), 0.1,
                             vel=torch.tensor([[[2.0, 0.0]]], dtype=torch.float64))
    a = b = start
    for _ in range(12):
        a = P.step(a, torch.zeros(1, 1, 2, dtype=torch.float64), two, cfg)
        b = P.step(b, torch.zeros(1, 1, 2, dtype=torch.float64), one, cfg)
        assert torch.allclose(a.pos, b.pos, atol=1e-12, rtol=0) and torch.allclose(a.vel, b.vel, atol=1e-12, rtol=0)
    assert b.vel[0, 0, 0].item() == pytest.approx(-2.0)  # it did bounce


def test_overlap_correction_cannot_push_a_body_through_a_thin_box():
    # A heavy body spawned deep in a light one pushes it towards a thin box. The
    # correction alone (~0.2) would carry the light body past the box's middle
    # line (0.12 away); the per-substep travel cap keeps it on its side.
    r, t = 0.1, 0.02
    cfg = P.PhysicsConfig(terms={"body_collisions", "obstacles"}, dt=0.05, substeps=1, max_speed=1.0,
                          min_body_radius=r, position_correction=1.0, arena_half_extent=(3.0, 3.0))
    obs = P.Obstacles(torch.zeros(1, 1, 2, dtype=torch.float64), torch.tensor([[[t, 0.5]]], dtype=torch.float64),
                      torch.zeros(1, 1, dtype=torch.float64))
    s = P.BodyState(torch.tensor([[[-(t + r) - 0.2, 0.0], [-(t + r), 0.0]]], dtype=torch.float64),
                    torch.zeros(1, 2, 2, dtype=torch.float64), torch.tensor([[0.3, r]], dtype=torch.float64),
                    torch.tensor([[10.0, 0.1]], dtype=torch.float64), torch.ones(1, 2, dtype=torch.bool))
    for _ in range(30):
        s = P.step(s, torch.zeros(1, 2, 2, dtype=torch.float64), obs, cfg)
        assert s.pos[0, 1, 0] < 0
        assert box_distance(s.pos[0, 1], [0.0, 0.0], [t, 0.5], 0.0) >= r - 1e-9
    # The light body is pinned, so the heavy one takes its 1 % share and slowly backs off.
    assert pair_distances(s.pos).min() > 0.2 + 0.03


# --------------------------------------------------------------------------
# Body-body collisions
# --------------------------------------------------------------------------

def test_overlapping_spawn_separates_without_explosion():
    W, B, r = 3, 8, 0.1
    cfg = P.PhysicsConfig(dt=0.05, substeps=4, max_speed=2.0, min_body_radius=r, restitution=0.5,
                          arena_half_extent=(2.0, 2.0))
    g = torch.Generator().manual_seed(1)
    pos = torch.tensor([0.3, -0.2]).expand(W, B, 2).clone()
    pos[1] += 1e-3 * torch.randn(B, 2, generator=g)
    pos[2] += 1e-2 * torch.randn(B, 2, generator=g)
    vel = torch.zeros(W, B, 2)
    vel[2] = P.clamp_norm(0.05 * torch.randn(B, 2, generator=g), 0.05)  # world 2 also moves a little
    s = P.BodyState.make(pos, r, vel=vel)
    assert pair_distances(s.pos).min() < 0.05  # heavily overlapping (exactly coincident in world 0)
    for _ in range(40):
        s = P.step(s, torch.zeros(W, B, 2), None, cfg)
    assert pair_distances(s.pos).min() >= 2 * r - 1e-3, "bodies did not separate"
    speed = s.vel.norm(dim=-1)
    # The positional correction moved bodies apart without giving them velocity.
    assert speed[:2].max() == 0.0
    assert speed[2].max() <= 0.1


def test_two_body_elastic_collision_conserves_momentum_and_energy():
    cfg = P.PhysicsConfig(dt=0.01, substeps=2, terms={"body_collisions"}, restitution=1.0, max_speed=5.0,
                          min_body_radius=0.1, integrator="velocity_verlet")
    # Oblique hit, different masses and radii.
    pos = torch.tensor([[[-0.5, 0.05], [0.5, -0.03]]], dtype=torch.float64)
    vel = torch.tensor([[[1.0, 0.1], [-0.5, 0.0]]], dtype=torch.float64)
    s = P.BodyState(pos, vel, torch.tensor([[0.1, 0.15]], dtype=torch.float64),
                    torch.tensor([[1.0, 3.0]], dtype=torch.float64), torch.ones(1, 2, dtype=torch.bool))
    p0, e0 = P.momentum(s), P.kinetic_energy(s)
    for _ in range(150):
        s = P.step(s, torch.zeros_like(pos), None, cfg)
    assert not torch.allclose(s.vel, vel)  # they did collide
    assert torch.allclose(P.momentum(s), p0, atol=1e-12, rtol=0)
    assert torch.allclose(P.kinetic_energy(s), e0, atol=1e-12, rtol=0)


def test_head_on_collision_matches_1d_formula():
    cfg = P.PhysicsConfig(dt=0.01, substeps=2, terms={"body_collisions"}, restitution=0.7, max_speed=5.0)
    m1, m2, u1, u2, e = 2.0, 0.5, 1.0, -1.5, 0.7
    s = P.BodyState(torch.tensor([[[-0.4, 0.0], [0.4, 0.0]]], dtype=torch.float64),
                    torch.tensor([[[u1, 0.0], [u2, 0.0]]], dtype=torch.float64),
                    torch.full((1, 2), 0.1, dtype=torch.float64),
                    torch.tensor([[m1, m2]], dtype=torch.float64), torch.ones(1, 2, dtype=torch.bool))
    for _ in range(100):
        s = P.step(s, torch.zeros(1, 2, 2, dtype=torch.float64), None, cfg)
    v1 = (m1 * u1 + m2 * u2 - m2 * e * (u1 - u2)) / (m1 + m2)
    v2 = (m1 * u1 + m2 * u2 + m1 * e * (u1 - u2)) / (m1 + m2)
    assert s.vel[0, :, 0].tolist() == pytest.approx([v1, v2], abs=1e-12)
    assert s.vel[0, :, 1].abs().max() == 0


def test_many_body_momentum_conserved_without_walls():
    cfg = P.PhysicsConfig(terms={"body_collisions"}, restitution=0.6, max_speed=3.0, min_body_radius=0.1)
    W, B = 2, 8
    g = torch.Generator().manual_seed(3)
    s = scene(W, B, radius=0.12, spread=0.4, seed=3, speed=1.0)
    s = s._replace(mass=0.5 + torch.rand(W, B, generator=g, dtype=torch.float64))
    p0 = P.momentum(s)
    contacts = 0
    for _ in range(100):
        s = P.step(s, torch.zeros(W, B, 2, dtype=torch.float64), None, cfg)
        contacts += int((pair_distances(s.pos) < 0.24).sum())
    assert contacts > 0
    assert torch.allclose(P.momentum(s), p0, atol=1e-12, rtol=0)


# --------------------------------------------------------------------------
# Friction and drag
# --------------------------------------------------------------------------

def test_friction_stops_without_reversing_and_static_friction_holds():
    mu, g = 0.5, 9.81
    cfg = P.PhysicsConfig(terms={"friction"}, friction=mu, gravity=g, dt=0.02, substeps=4,
                          integrator="velocity_verlet", arena_half_extent=(5.0, 5.0), max_speed=3.0)
    # world 0: sliding at 1 m/s, no force; world 1: at rest, force just below mu m g; world 2: just above.
    s = P.BodyState.make(torch.zeros(3, 1, 2, dtype=torch.float64), 0.1, mass=2.0,
                         vel=torch.tensor([[[1.0, 0.0]], [[0.0, 0.0]], [[0.0, 0.0]]], dtype=torch.float64))
    fmax = mu * 2.0 * g
    force = torch.tensor([[[0.0, 0.0]], [[0.0, 0.99 * fmax]], [[0.0, 1.05 * fmax]]], dtype=torch.float64)
    for _ in range(30):
        s = P.step(s, force, None, cfg)
        assert s.vel[0, 0, 0] >= 0  # never reversed
    assert s.vel[0].abs().max() == 0
    assert s.pos[0, 0, 0].item() == pytest.approx(1.0 / (2 * mu * g), rel=1e-2)  # v^2 / (2 mu g)
    assert s.pos[1].abs().max() == 0 and s.vel[1].abs().max() == 0
    assert s.pos[2, 0, 1] > 0


def test_drag_is_exponential_decay():
    cfg = P.PhysicsConfig(terms={"drag"}, drag=0.7, dt=0.05, substeps=3, arena_half_extent=(50.0, 50.0))
    v0 = torch.tensor([[[1.2, -0.4]]], dtype=torch.float64)
    s = P.BodyState.make(torch.zeros(1, 1, 2, dtype=torch.float64), 0.1, vel=v0)
    for _ in range(20):
        s = P.step(s, torch.zeros(1, 1, 2, dtype=torch.float64), None, cfg)
    assert torch.allclose(s.vel, v0 * math.exp(-0.7 * 1.0), atol=1e-12, rtol=0)


# --------------------------------------------------------------------------
# Long rollout and determinism
# --------------------------------------------------------------------------

OBSTACLE_LAYOUT = dict(center=[[0.5, 0.0], [-0.5, 0.3]], half=[[0.06, 0.3], [0.25, 0.06]], angle=[0.3, -0.7])


def rollout_setup(W, B, dtype=torch.float32, **cfg_kw):
    kw = dict(dt=0.05, substeps=2, terms=P.TERM_NAMES, max_speed=2.0, min_body_radius=0.06,
              arena_half_extent=(1.0, 1.0), friction=0.02, drag=0.05, restitution=0.9)
    kw.update(cfg_kw)
    cfg = P.PhysicsConfig(**kw)
    K = len(OBSTACLE_LAYOUT["angle"])
    obs = P.Obstacles(torch.tensor(OBSTACLE_LAYOUT["center"], dtype=dtype).expand(W, K, 2).clone(),
                      torch.tensor(OBSTACLE_LAYOUT["half"], dtype=dtype).expand(W, K, 2).clone(),
                      torch.tensor(OBSTACLE_LAYOUT["angle"], dtype=dtype).expand(W, K).clone())
    return cfg, obs


def test_long_rollout_random_forces_stays_finite_bounded_inside():
    # 1.6M world-steps with every term, as 160 worlds x 10k sequential steps (was 16 x 100k: the same
    # body-steps, 2.6x cheaper since a step's cost is mostly per-call overhead). The physics state is
    # only positions and velocities (nothing else accumulates), and at the speed clamp a body crosses
    # the arena in ~20 steps while drag, friction and restitution forget a start within a few hundred:
    # 10k steps are many such horizons per world, so a drift, leak or rare escape still shows, and ten
    # times more worlds see ten times more force sequences.
    W, B, steps = 160, 6, 10_000
    cfg, obs = rollout_setup(W, B, solver_iterations=1)
    g = torch.Generator().manual_seed(0)
    # Start in the arena's corners, away from the boxes.
    pos = torch.rand(W, B, 2, generator=g) * 0.25 + 0.65
    pos[:, ::2, 0] *= -1
    s = P.BodyState(pos, torch.zeros(W, B, 2), 0.06 + 0.04 * torch.rand(W, B, generator=g),
                    0.5 + torch.rand(W, B, generator=g), torch.ones(W, B, dtype=torch.bool))
    P.check_scene(s, obs, cfg)
    e_max = (0.5 * s.mass * cfg.max_speed ** 2).sum(-1)
    bound = torch.tensor(cfg.arena_half_extent) - s.radius[..., None] + 1e-5
    forces = torch.randn(1000, W, B, 2, generator=g) * 3.0
    with torch.inference_mode():
        for i in range(steps):
            s = P.step(s, forces[i % 1000], obs, cfg)
            if i % 500 == 499:
                assert torch.isfinite(s.pos).all() and torch.isfinite(s.vel).all(), i
                assert (s.pos.abs() <= bound).all(), i
                ke = P.kinetic_energy(s)
                assert torch.isfinite(ke).all() and (ke <= e_max * (1 + 1e-5)).all(), i
    assert P.kinetic_energy(s).sum() > 0
    for k in range(len(OBSTACLE_LAYOUT["angle"])):
        d = box_distance(s.pos, OBSTACLE_LAYOUT["center"][k], OBSTACLE_LAYOUT["half"][k], OBSTACLE_LAYOUT["angle"][k])
        assert (d >= s.radius - 1e-2).all()


def test_determinism_same_seed_identical():
    def run(seed):
        W, B = 4, 6
        cfg, obs = rollout_setup(W, B)
        g = torch.Generator().manual_seed(seed)
        s = P.BodyState.make(torch.rand(W, B, 2, generator=g) * 1.6 - 0.8, 0.07)
        for _ in range(100):
            s = P.step(s, torch.randn(W, B, 2, generator=g) * 3, obs, cfg)
        return s

    a, b, c = run(7), run(7), run(8)
    assert torch.equal(a.pos, b.pos) and torch.equal(a.vel, b.vel)
    assert not torch.equal(a.pos, c.pos)


# --------------------------------------------------------------------------
# Undeclared terms are never computed
# --------------------------------------------------------------------------

@pytest.mark.parametrize("declared", [set(), {"walls"}, {"drag", "obstacles"},
                                      {"body_collisions", "friction"}, set(P.TERM_NAMES)])
def test_undeclared_terms_are_not_computed(monkeypatch, declared):
    calls = {name: 0 for name in P.TERM_NAMES}

    def forbidden(name):
        def term(*args, **kwargs):
            raise AssertionError(f"undeclared term {name!r} was computed")
        return term

    def counted(name, fn):
        def term(*args, **kwargs):
            calls[name] += 1
            return fn(*args, **kwargs)
        return term

    for name in P.TERM_NAMES:
        original = P.TERMS[name]
        monkeypatch.setitem(P.TERMS, name, counted(name, original) if name in declared else forbidden(name))

    W, B, steps = 2, 4, 3
    cfg, obs = rollout_setup(W, B, terms=declared)
    s = scene(W, B, radius=0.07, dtype=torch.float32, speed=1.0)
    for _ in range(steps):
        s = P.step(s, torch.ones(W, B, 2), obs, cfg)
    assert all(calls[n] == steps for n in declared), calls
    assert all(calls[n] == 0 for n in P.TERM_NAMES - declared), calls


def test_term_hook_is_really_used(monkeypatch):
    # Control for the test above: a declared term goes through TERMS.
    def boom(*args, **kwargs):
        raise RuntimeError("walls hook")

    monkeypatch.setitem(P.TERMS, "walls", boom)
    s = scene(1, 2)
    with pytest.raises(RuntimeError, match="walls hook"):
        P.step(s, torch.zeros(1, 2, 2, dtype=torch.float64), None, P.PhysicsConfig(terms={"walls"}))


# --------------------------------------------------------------------------
# Config validation
# --------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, words", [
    (dict(substeps=0), ["substeps", "int >= 1", "0"]),
    (dict(substeps=2.0), ["substeps", "2.0"]),
    (dict(dt=-0.1), ["dt", "> 0", "-0.1"]),
    (dict(dt=float("nan")), ["dt", "nan"]),
    (dict(integrator="rk5"), ["integrator", "velocity_verlet", "rk5"]),
    (dict(terms={"walls", "gravity", "magnets"}), ["terms", "gravity", "magnets"]),
    (dict(terms="walls"), ["terms", "walls"]),
    (dict(restitution=1.5), ["restitution", "[0, 1]", "1.5"]),
    (dict(friction=-0.1), ["friction", ">= 0", "-0.1"]),
    (dict(drag=-1), ["drag", "-1"]),
    (dict(arena_half_extent=(1.0,)), ["arena_half_extent", "(1.0,)"]),
    (dict(arena_half_extent=(1.0, -2.0)), ["arena_half_extent", "-2.0"]),
    (dict(max_speed=0.0), ["max_speed", "> 0"]),
    (dict(min_body_radius=0), ["min_body_radius"]),
    (dict(solver_iterations=0), ["solver_iterations", "0"]),
    (dict(position_correction=0.0), ["position_correction", "(0, 1]"]),
])
def test_config_validation_names_argument(kwargs, words):
    with pytest.raises(ValueError) as info:
        P.PhysicsConfig(**kwargs)
    for w in words:
        assert w in str(info.value), (w, str(info.value))


def test_tunnelling_check_says_how_many_substeps():
    ms, dt, r = 3.0, 0.05, 0.04
    need = P.min_substeps(ms, dt, r)
    assert ms * dt / need < r <= ms * dt / (need - 1)
    P.PhysicsConfig(max_speed=ms, dt=dt, min_body_radius=r, substeps=need)
    with pytest.raises(ValueError, match=rf"substeps must be >= {need}\b"):
        P.PhysicsConfig(max_speed=ms, dt=dt, min_body_radius=r, substeps=need - 1)


def test_config_normalises_terms_and_is_hashable():
    cfg = P.PhysicsConfig(terms=["walls", "drag", "walls"])
    assert cfg.terms == frozenset({"walls", "drag"})
    assert hash(cfg) == hash(P.PhysicsConfig(terms={"drag", "walls"}))


def test_check_scene_rejects_bodies_smaller_than_config_radius():
    cfg = P.PhysicsConfig(min_body_radius=0.05)
    s = P.BodyState.make(torch.zeros(1, 2, 2), torch.tensor([[0.1, 0.01]]))
    with pytest.raises(ValueError, match="radius"):
        P.check_scene(s, None, cfg)
    # An inactive small body is fine.
    P.check_scene(s._replace(active=torch.tensor([[True, False]])), None, cfg)


# --------------------------------------------------------------------------
# Property test
# --------------------------------------------------------------------------

@st.composite
def random_world(draw):
    W = draw(st.integers(1, 3))
    B = draw(st.integers(1, 5))
    dtype = draw(st.sampled_from(DTYPES))
    seed = draw(st.integers(0, 2**31 - 1))
    terms = draw(st.frozensets(st.sampled_from(sorted(P.TERM_NAMES))))
    integrator = draw(st.sampled_from(P.INTEGRATORS))
    restitution = draw(st.floats(0.0, 1.0))
    force_scale = draw(st.sampled_from([0.0, 1.0, 50.0, 1e4]))
    return W, B, dtype, seed, terms | {"walls"}, integrator, restitution, force_scale


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_world())
def test_property_random_states_finite_and_inside_arena(world):
    W, B, dtype, seed, terms, integrator, restitution, force_scale = world
    cfg = P.PhysicsConfig(dt=0.05, substeps=3, terms=terms, integrator=integrator, restitution=restitution,
                          friction=0.3, drag=0.5, max_speed=3.0, min_body_radius=0.06, arena_half_extent=(1.0, 0.8))
    g = torch.Generator().manual_seed(seed)
    pos = (torch.rand(W, B, 2, generator=g, dtype=dtype) * 2 - 1) * 2.0      # may start outside the arena
    vel = torch.randn(W, B, 2, generator=g, dtype=dtype) * 5.0               # may exceed max_speed
    radius = 0.06 + 0.2 * torch.rand(W, B, generator=g, dtype=dtype)
    mass = 0.1 + 5 * torch.rand(W, B, generator=g, dtype=dtype)
    mass = torch.where(torch.rand(W, B, generator=g) < 0.15, torch.full_like(mass, math.inf), mass)
    active = torch.rand(W, B, generator=g) < 0.8
    s = P.BodyState(pos, vel, radius, mass, active)
    K = 2
    obs = P.Obstacles((torch.rand(W, K, 2, generator=g, dtype=dtype) * 2 - 1) * 0.6,
                      0.02 + 0.3 * torch.rand(W, K, 2, generator=g, dtype=dtype),
                      torch.rand(W, K, generator=g, dtype=dtype) * 6.3)
    out = s
    for _ in range(3):
        out = P.step(out, torch.randn(W, B, 2, generator=g, dtype=dtype) * force_scale, obs, cfg)
    assert out.pos.dtype == dtype and out.vel.dtype == dtype
    assert torch.isfinite(out.pos).all() and torch.isfinite(out.vel).all()
    assert torch.isfinite(P.kinetic_energy(out)).all()
    movable = active & torch.isfinite(mass)
    bound = torch.tensor(cfg.arena_half_extent, dtype=dtype) - radius[..., None]
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert (out.pos.abs() <= bound + tol)[movable].all()
    assert (out.vel.norm(dim=-1) <= cfg.max_speed * (1 + 1e-5))[movable].all()
    # Inactive bodies untouched; immovable ones did not move.
    assert torch.equal(out.pos[~active], pos[~active]) and torch.equal(out.vel[~active], vel[~active])
    fixed = active & ~torch.isfinite(mass)
    assert torch.equal(out.pos[fixed], pos[fixed]) and (out.vel[fixed] == 0).all()


# --------------------------------------------------------------------------
# dm_control cart-pole
# --------------------------------------------------------------------------

def test_cartpole_matches_mujoco_rk4_trajectory():
    # Reference: MuJoCo 4.0.0 with dm_control's cartpole.xml (timestep 0.01, RK4),
    # from (x, theta, xdot, thetadot) = (.05, .03, .01, -.02) with ctrl_t = 0.3 sin(0.05 t).
    # The pole falls and swings over; the cart stays within the slider range.
    ref = {
        50: [0.2718183450384065, -0.29981457601702305, 1.0663971801399363, -1.918866691158302],
        150: [0.7577038547448353, -5.803857192878724, 0.5316252078932918, -4.446588151435409],
        300: [1.601069234344276, -16.64994811782776, 0.7403000734078956, -8.185646840777553],
    }
    s = torch.tensor([[0.05, 0.03, 0.01, -0.02]], dtype=torch.float64)
    for t in range(300):
        s = C.cartpole_step(s, torch.tensor([0.3 * math.sin(0.05 * t)], dtype=torch.float64))
        if t + 1 in ref:
            assert s[0].tolist() == pytest.approx(ref[t + 1], abs=1e-9), t + 1


# One-step transitions and rewards recorded from dm_control 1.0.50 (MuJoCo 3.17)
# cartpole/balance with actions outside [-1, 1] (clipped by the actuator, not by the reward).
DMC_STEPS = [
    ([0.010183700136135341, 0.01395672588277802, 0.0038591754767485407, -0.02083529992103551], 1.171205610447432,
     [0.010708483276110098, 0.013052082068183151, 0.10109847269163995, -0.16011669828603764], 0.7989961974277447),
    ([0.04641444766644547, -0.035025182331680664, 0.321332520144065, -0.469081682139632], 0.9789964506831093,
     [0.050105420318797465, -0.04043543503907198, 0.41686710047582726, -0.6130999132222503], 0.7936621376237291),
    ([0.634955014705543, -5.788995167890525, 0.4716462769506151, -1.361158613767902], 1.2034479039523924,
     [0.6401386231483303, -5.802870500367115, 0.5651002929899079, -1.414378003762397], 0.6186140450408776),
    ([-0.3182835781588459, -0.13087911602470906, -1.3124870632256753, 1.0823467668360407], 1.1567293664396272,
     [-0.3309182598074836, -0.12085237435071161, -1.2144536148455816, 0.9232142301179109], 0.7435643550265717),
]


def test_cartpole_step_and_reward_match_dm_control():
    before = torch.tensor([r[0] for r in DMC_STEPS], dtype=torch.float64)
    action = torch.tensor([r[1] for r in DMC_STEPS], dtype=torch.float64)
    after = torch.tensor([r[2] for r in DMC_STEPS], dtype=torch.float64)
    reward = torch.tensor([r[3] for r in DMC_STEPS], dtype=torch.float64)
    assert torch.allclose(C.cartpole_step(before, action), after, atol=1e-12, rtol=0)
    assert torch.allclose(R.dmc_balance_reward(after, action), reward, atol=1e-12, rtol=0)


def test_tolerance_like_dm_control():
    x = torch.tensor([-3.0, -1.0, 0.0, 0.5, 1.0, 2.0, 3.0], dtype=torch.float64)
    t = R.tolerance(x, bounds=(0.0, 1.0), margin=2.0)
    assert t[1:5].tolist() == pytest.approx([math.exp(-0.5 * 0.5 ** 2 * -2 * math.log(0.1)), 1, 1, 1])
    assert t[-2].item() == pytest.approx(math.exp(-0.5 * 0.5 ** 2 * -2 * math.log(0.1)))
    assert t[-1].item() == pytest.approx(0.1)  # value_at_margin at distance == margin
    assert R.tolerance(x, bounds=(0.0, 1.0)).tolist() == [0, 0, 1, 1, 1, 0, 0]
    q = R.tolerance(x, margin=1.0, value_at_margin=0.0, sigmoid="quadratic")
    assert q.tolist() == pytest.approx([0, 0, 1, 0.75, 0, 0, 0])
    with pytest.raises(ValueError, match="bounds"):
        R.tolerance(x, bounds=(1.0, 0.0))


def test_balance_reward_is_one_when_perfect_and_sparse_reward():
    s = torch.zeros(2, 4, dtype=torch.float64)
    s[1, 1] = math.pi  # hanging down
    r = R.dmc_balance_reward(s, torch.zeros(2, dtype=torch.float64))
    assert r[0].item() == 1.0 and r[1].item() == pytest.approx(0.0, abs=1e-12)
    assert R.dmc_balance_sparse_reward(s).tolist() == [1.0, 0.0]


def _energy_drift(integrator, substeps, steps=1000):
    s = torch.tensor([[0.0, 0.1, 0.0, 0.0], [0.3, -0.5, 0.2, 1.0], [0.0, 3.0, 0.0, 0.0]], dtype=torch.float64)
    e0 = C.cartpole_energy(s)
    a = torch.zeros(3, dtype=torch.float64)
    worst = torch.zeros(3, dtype=torch.float64)
    for _ in range(steps):
        s = C.cartpole_step(s, a, dt=0.01, substeps=substeps, integrator=integrator,
                            slider_damping=0.0, hinge_damping=0.0)
        worst = torch.maximum(worst, ((C.cartpole_energy(s) - e0) / e0.abs()).abs())
    return worst.max().item()


def test_cartpole_energy_conserved_without_damping():
    # The pole starts near upright and swings all the way round; 10 s of motion.
    verlet = _energy_drift("velocity_verlet", substeps=2)
    assert verlet < 1e-3
    assert _energy_drift("rk4", substeps=1) < 1e-6
    # The first-order scheme is clearly worse: the check can tell them apart.
    assert _energy_drift("semi_implicit_euler", substeps=2) > 10 * verlet


@pytest.mark.parametrize("integrator, order", [("semi_implicit_euler", 1), ("velocity_verlet", 2), ("rk4", 4)])
def test_cartpole_substeps_converge_to_reference(integrator, order):
    s0 = torch.tensor([[0.0, 0.1, 0.0, 0.0], [0.3, -0.5, 0.2, 1.0], [0.0, 3.0, 0.0, 0.0]], dtype=torch.float64)
    action = torch.tensor([0.5, -0.3, 0.1], dtype=torch.float64)

    def roll(substeps):
        s = s0
        for _ in range(50):
            s = C.cartpole_step(s, action, substeps=substeps, integrator=integrator)
        return s

    ref = roll(64)
    err = {k: (roll(k) - ref).abs().max().item() for k in (1, 2, 4, 16)}
    assert err[16] < err[4] < err[2] < err[1]
    # Halving the substep divides the error by about 2**order.
    assert 2 ** order * 0.7 < err[1] / err[2] < 2 ** order * 1.4


def test_cartpole_action_is_clipped_and_validated():
    s = torch.tensor([[0.0, 0.05, 0.0, 0.0]], dtype=torch.float64)
    a = C.cartpole_step(s, torch.tensor([1.0], dtype=torch.float64))
    b = C.cartpole_step(s, torch.tensor([7.0], dtype=torch.float64))
    assert torch.equal(a, b)
    assert C.cartpole_step(s.float(), torch.tensor([0.2])).dtype == torch.float32
    with pytest.raises(ValueError, match="integrator"):
        C.cartpole_step(s, torch.zeros(1), integrator="euler")
    with pytest.raises(ValueError, match="substeps"):
        C.cartpole_step(s, torch.zeros(1), substeps=0)


# The numpy path (envs/array_ops.py) that CPU batches take must give the torch path's bits.
@pytest.mark.parametrize("integrator", C.CARTPOLE_INTEGRATORS)
@pytest.mark.parametrize("worlds", [1, 16, 1000])
def test_cartpole_numpy_path_gives_the_torch_paths_bits(integrator, worlds):
    from marl_render.envs.array_ops import NumpyOps, TorchOps

    g = torch.Generator().manual_seed(worlds)
    s = (torch.rand(worlds, 4, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([3.0, 7.0, 4.0, 9.0],
                                                                                        dtype=torch.float64)
    outs = {}
    for ops in (NumpyOps, TorchOps):
        q = s.clone() if ops is TorchOps else s.clone().numpy()
        for t in range(300):  # 3 s: the pole falls and swings over; the cart hits the stops
            force = 10.0 * torch.sin(torch.full((worlds,), 0.07 * t, dtype=torch.float64))
            q = C.integrate(ops, q, force if ops is TorchOps else force.numpy(), 0.01, 2, integrator, 5e-4, 2e-6)
            q = C.stop_at_limit(ops, q)
            reward = R.balance_reward(ops, q, force / 10.0 if ops is TorchOps else force.numpy() / 10.0)
        outs[ops] = (torch.as_tensor(q), torch.as_tensor(reward))
    assert torch.equal(outs[NumpyOps][0], outs[TorchOps][0]) and torch.equal(outs[NumpyOps][1], outs[TorchOps][1])
    assert outs[NumpyOps][0].dtype == torch.float64


@pytest.mark.parametrize("sigmoid", ["gaussian", "hyperbolic", "long_tail", "reciprocal", "cosine", "linear",
                                     "quadratic", "tanh_squared"])
def test_tolerance_numpy_path_gives_the_torch_paths_bits(sigmoid):
    from marl_render.envs.array_ops import NumpyOps

    x = torch.linspace(-4, 4, 1001, dtype=torch.float64)
    value = 0.0 if sigmoid in ("linear", "quadratic", "cosine") else 0.1
    expected = R.tolerance(x, bounds=(-0.5, 1.0), margin=2.0, sigmoid=sigmoid, value_at_margin=value)
    got = R.tolerance(x.numpy(), bounds=(-0.5, 1.0), margin=2.0, sigmoid=sigmoid, value_at_margin=value, ops=NumpyOps)
    assert torch.equal(torch.from_numpy(got), expected)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("integrator", P.INTEGRATORS)
def test_planar_numpy_path_gives_the_torch_paths_bits(dtype, integrator):
    # A crowded box with obstacles, an immovable and an inactive body, friction and drag: every
    # term and branch (contacts, walls, inside and outside boxes) runs on both namespaces.
    from marl_render.envs.array_ops import TorchOps

    cfg = P.PhysicsConfig(terms=P.TERM_NAMES, integrator=integrator, friction=0.1, drag=0.2)
    W, B, K = 6, 9, 3
    s = scene(W, B, radius=0.12, spread=0.9, dtype=dtype, seed=3, speed=2.0)
    mass = s.mass.clone()
    mass[:, 0] = math.inf
    active = s.active.clone()
    active[:, 1] = False
    s = s._replace(mass=mass, active=active)
    g = torch.Generator().manual_seed(1)
    boxes = P.Obstacles((torch.rand(W, K, 2, generator=g, dtype=dtype) - 0.5),
                        torch.full((W, K, 2), 0.15, dtype=dtype), torch.rand(W, K, generator=g, dtype=dtype) * 3)
    numpy_state, torch_state = s, s
    for t in range(60):
        force = torch.randn(W, B, 2, generator=g, dtype=dtype) * 3
        numpy_state = P.step(numpy_state, force, boxes, cfg)
        torch_state = P._step(TorchOps, torch_state, force, boxes, cfg)
        assert torch.equal(numpy_state.pos, torch_state.pos) and torch.equal(numpy_state.vel, torch_state.vel), t
    assert numpy_state.pos.dtype == dtype and not torch.equal(numpy_state.pos, s.pos)


def test_tensors_outside_the_numpy_path_keep_the_torch_path():
    # Autograd and unusual dtypes take the torch namespace: gradients flow, bits are the same.
    from marl_render.envs.array_ops import NumpyOps, TorchOps, for_tensors

    s = torch.tensor([[0.05, 0.03, 0.01, -0.02], [0.3, -0.5, 0.2, 1.0]], dtype=torch.float64)
    u = torch.tensor([0.4, -0.7], dtype=torch.float64)
    assert for_tensors(s, u, torch.ones(2, dtype=torch.bool)) is NumpyOps
    assert for_tensors(s, u.half()) is TorchOps and for_tensors(s.requires_grad_(False), u.requires_grad_()) is TorchOps
    stepped = C.cartpole_step(s, u)
    assert stepped.grad_fn is not None
    stepped.sum().backward()
    assert u.grad is not None and torch.isfinite(u.grad).all()
    assert torch.equal(stepped.detach(), C.cartpole_step(s, u.detach()))

    cfg = P.PhysicsConfig(terms=P.TERM_NAMES, friction=0.1, drag=0.2)
    bodies = scene(2, 4, speed=1.0)
    force = torch.ones(2, 4, 2, dtype=torch.float64, requires_grad=True)
    moved = P.step(bodies, force, None, cfg)
    assert moved.vel.grad_fn is not None
    assert torch.equal(moved.pos.detach(), P.step(bodies, force.detach(), None, cfg).pos)
