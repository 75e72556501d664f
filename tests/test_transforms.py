"""Rotation math in marl_render.transforms: quaternions, yaw/pitch/roll, look-at.

Pure torch, no GL: fast. Property-based where a property holds for every input.
"""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from marl_render import transforms as T

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
F64 = torch.float64

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
quat_components = st.tuples(finite, finite, finite, finite).filter(lambda c: sum(v * v for v in c) > 1e-4)
angles = st.floats(-math.pi, math.pi, allow_nan=False)
pitches = st.floats(-math.pi / 2, math.pi / 2, allow_nan=False)


def q64(components) -> torch.Tensor:
    return torch.tensor(components, dtype=F64)


def rot(q: torch.Tensor) -> torch.Tensor:
    return T.quat_to_matrix(T.normalize_quat(q))


def assert_rotation(m: torch.Tensor, atol: float = 1e-9) -> None:
    """Finite, orthonormal, det +1 (a proper rotation, no reflection, no scale)."""
    assert torch.isfinite(m).all()
    eye = torch.eye(3, dtype=m.dtype).expand_as(m)
    assert torch.allclose(m @ m.transpose(-1, -2), eye, atol=atol), m
    assert torch.allclose(torch.linalg.det(m), torch.ones((), dtype=m.dtype), atol=atol)


# ----------------------------------------------------------------------------- quaternions
@SETTINGS
@given(quat_components)
def test_normalize_quat_is_unit_with_nonnegative_w(components):
    q = T.normalize_quat(q64(components))
    assert abs(q.norm().item() - 1.0) < 1e-12
    assert q[0] >= 0


@SETTINGS
@given(quat_components, st.floats(1e-6, 1e6), st.sampled_from([1.0, -1.0]))
def test_unnormalised_quaternion_gives_the_same_rotation(components, scale, sign):
    """k * q is the same rotation for every k != 0, through normalize_quat and quat_to_matrix alike."""
    q = q64(components)
    reference = rot(q)
    scaled = sign * scale * q
    assert torch.allclose(rot(scaled), reference, atol=1e-12)
    # quat_to_matrix itself is homogeneous: no shear/scale from a slightly off-unit input.
    assert torch.allclose(T.quat_to_matrix(scaled), reference, atol=1e-9)
    assert_rotation(T.quat_to_matrix(scaled))


@SETTINGS
@given(quat_components)
def test_q_and_minus_q_give_identical_matrices(components):
    q = q64(components)
    # Every entry is quadratic in q: bit-identical, not just close.
    assert torch.equal(T.quat_to_matrix(q), T.quat_to_matrix(-q))
    assert torch.equal(rot(q), rot(-q))
    if q[0] != 0:
        assert torch.equal(T.normalize_quat(q), T.normalize_quat(-q))  # canonical sign w > 0


@pytest.mark.parametrize("bad", [
    [0.0, 0.0, 0.0, 0.0],
    [1e-13, 0.0, 0.0, 0.0],
    [0.0, -3e-14, 2e-14, 0.0],
])
def test_near_zero_quaternion_raises_clear_value_error(bad):
    batch = torch.tensor([[1.0, 0.0, 0.0, 0.0], bad, [0.0, 1.0, 0.0, 0.0]], dtype=F64)
    with pytest.raises(ValueError, match=r"rotation must be non-zero quaternions \(w, x, y, z\)"):
        T.normalize_quat(batch)
    with pytest.raises(ValueError, match="my_quat must be non-zero"):
        T.normalize_quat(batch, name="my_quat")
    with pytest.raises(ValueError, match="non-zero"):
        T.quat_to_matrix(batch)  # never NaN


def test_small_but_valid_quaternion_normalises_without_nan():
    for dtype in (torch.float32, F64):
        q = torch.tensor([1e-9, 2e-9, 0.0, -2e-9], dtype=dtype)
        unit = T.normalize_quat(q)
        assert torch.isfinite(unit).all()
        assert torch.allclose(unit, torch.tensor([1.0, 2.0, 0.0, -2.0], dtype=dtype) / 3, atol=1e-6)


@SETTINGS
@given(quat_components, quat_components)
def test_nearly_identical_quaternions_give_nearly_identical_matrices(components, direction):
    """Lipschitz: |dR| <= 4 |dq| / |q| entrywise (generous constant), no jumps anywhere,
    including across w = 0 where normalize_quat flips the sign."""
    q = T.normalize_quat(q64(components))
    d = q64(direction)
    d = d / d.norm() * 1e-7
    diff = (rot(q + d) - rot(q)).abs().max().item()
    assert diff <= 4e-7 + 1e-14


def test_no_jump_across_w_equals_zero():
    """q with w = +-eps straddles normalize_quat's sign flip; the matrices must agree."""
    a = torch.tensor([1e-9, 0.6, 0.0, 0.8], dtype=F64)
    b = torch.tensor([-1e-9, 0.6, 0.0, 0.8], dtype=F64)
    assert (rot(a) - rot(b)).abs().max() < 1e-8


@SETTINGS
@given(quat_components)
def test_quat_to_matrix_is_a_proper_rotation(components):
    m = T.quat_to_matrix(T.normalize_quat(q64(components)))
    assert_rotation(m, atol=1e-12)
    m32 = T.quat_to_matrix(T.normalize_quat(q64(components).float()))
    assert_rotation(m32, atol=1e-5)


@SETTINGS
@given(quat_components)
def test_quat_to_matrix_agrees_with_quat_rotate(components):
    q = T.normalize_quat(q64(components))
    v = torch.tensor([[0.3, -1.2, 2.0], [1.0, 0.0, 0.0]], dtype=F64)
    assert torch.allclose(T.quat_rotate(q.expand(2, 4), v), v @ T.quat_to_matrix(q).T, atol=1e-12)


# Rotations by ~180 degrees make the w-branch of matrix_to_quat useless (w ~ 0): mix them in.
near_half_turns = st.tuples(st.floats(-1e-6, 1e-6), finite, finite, finite).filter(
    lambda c: sum(v * v for v in c[1:]) > 1e-4)


@SETTINGS
@given(st.one_of(quat_components, near_half_turns))
def test_matrix_to_quat_round_trips(components):
    q = T.normalize_quat(q64(components))
    m = T.quat_to_matrix(q)
    back = T.matrix_to_quat(m)
    assert abs(back.norm().item() - 1.0) < 1e-12
    assert torch.allclose(T.quat_to_matrix(back), m, atol=1e-12)
    # Same quaternion up to sign.
    assert min((back - q).abs().max().item(), (back + q).abs().max().item()) < 1e-9


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_matrix_to_quat_half_turns_about_each_axis(axis):
    m = -torch.eye(3, dtype=F64)
    m[axis, axis] = 1.0  # 180 degrees about `axis`: trace -1
    q = T.matrix_to_quat(m)
    expected = torch.zeros(4, dtype=F64)
    expected[1 + axis] = 1.0
    assert torch.allclose(q.abs(), expected, atol=1e-15)
    assert torch.allclose(T.quat_to_matrix(q), m, atol=1e-15)


def test_matrix_to_quat_batched_mixed_branches():
    qs = T.normalize_quat(torch.tensor(
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0.1, 0.9, -0.3, 0.2], [0.2, -0.1, 0.1, 0.95]],
        dtype=F64))
    m = T.quat_to_matrix(qs)
    assert torch.allclose(T.quat_to_matrix(T.matrix_to_quat(m)), m, atol=1e-12)


# ----------------------------------------------------------------------------- yaw / pitch / roll
def ypr_matrix(yaw, pitch, roll, dtype=F64):
    t = lambda v: torch.as_tensor(v, dtype=dtype)  # noqa: E731
    return T.quat_to_matrix(T.quat_from_yaw_pitch_roll(t(yaw), t(pitch), t(roll)))


def round_trip_error(yaw, pitch, roll, dtype=F64) -> float:
    t = lambda v: torch.as_tensor(v, dtype=dtype)  # noqa: E731
    q = T.quat_from_yaw_pitch_roll(t(yaw), t(pitch), t(roll))
    angles_back = T.yaw_pitch_roll_from_quat(q)
    q_back = T.quat_from_yaw_pitch_roll(*angles_back.unbind(-1))
    return (T.quat_to_matrix(q_back) - T.quat_to_matrix(q)).abs().max().item()


def test_yaw_pitch_roll_conventions():
    """yaw turns left about +Z, pitch raises the nose (+Y forward towards +Z), roll is about +Y."""
    forward = lambda m: m[:, 1]  # noqa: E731  (column 1 = the rotated +Y axis)
    assert torch.allclose(forward(ypr_matrix(math.pi / 2, 0.0, 0.0)), torch.tensor([-1.0, 0, 0], dtype=F64), atol=1e-15)
    assert torch.allclose(forward(ypr_matrix(0.0, math.pi / 2, 0.0)), torch.tensor([0, 0, 1.0], dtype=F64), atol=1e-15)
    rolled = ypr_matrix(0.0, 0.0, math.pi / 2)
    assert torch.allclose(forward(rolled), torch.tensor([0, 1.0, 0], dtype=F64), atol=1e-15)
    assert torch.allclose(rolled[:, 0], torch.tensor([0, 0, -1.0], dtype=F64), atol=1e-15)  # right wing down


@SETTINGS
@given(angles, pitches, angles)
def test_yaw_pitch_roll_round_trip_float64(yaw, pitch, roll):
    assert round_trip_error(yaw, pitch, roll) < 1e-12
    tensors = (torch.tensor(v, dtype=F64) for v in (yaw, pitch, roll))
    back = T.yaw_pitch_roll_from_quat(T.quat_from_yaw_pitch_roll(*tensors))
    assert -math.pi / 2 <= back[1].item() <= math.pi / 2


@SETTINGS
@given(angles, pitches, angles)
def test_yaw_pitch_roll_round_trip_float32(yaw, pitch, roll):
    assert round_trip_error(yaw, pitch, roll, torch.float32) < 2e-6


# Exactly at, just short of and just past the gimbal lock, down to below float32 resolution.
GIMBAL_PITCHES = [s * (math.pi / 2 - e) for s in (1.0, -1.0)
                  for e in (0.0, 1e-1, 1e-3, 1e-4, 1e-5, 1e-6, 3e-7, 1e-7, 1e-9, 1e-12, -1e-6, -1e-3)]


@pytest.mark.parametrize("dtype,tol", [(F64, 1e-12), (torch.float32, 2e-6)])
def test_round_trip_at_and_near_pitch_90_degrees(dtype, tol):
    yaws = torch.tensor([0.0, 0.7, -2.5, 3.1, -math.pi], dtype=dtype)
    rolls = torch.tensor([0.0, 0.3, -1.2, 2.9, 1.0], dtype=dtype)
    worst = max(round_trip_error(yaws, torch.full_like(yaws, p), rolls, dtype) for p in GIMBAL_PITCHES)
    assert worst < tol


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_exactly_pitch_90_gives_roll_zero_and_the_same_rotation(dtype):
    for sign in (1.0, -1.0):
        yaw = torch.tensor([0.3, 2.0, -1.0], dtype=dtype)
        roll = torch.tensor([0.5, -0.2, 1.0], dtype=dtype)
        q = T.quat_from_yaw_pitch_roll(yaw, torch.full_like(yaw, sign * math.pi / 2), roll)
        out = T.yaw_pitch_roll_from_quat(q)
        assert torch.isfinite(out).all()
        assert torch.allclose(out[:, 1], torch.full_like(yaw, sign * math.pi / 2), atol=1e-6)
        assert torch.equal(out[:, 2], torch.zeros_like(yaw))  # documented: roll is 0 at the lock
        assert round_trip_error(yaw, torch.full_like(yaw, sign * math.pi / 2), roll, dtype) < 2e-6


@pytest.mark.parametrize("dtype,tol", [(F64, 1e-12), (torch.float32, 2e-6)])
def test_rotation_is_continuous_through_pitch_90(dtype, tol):
    """Sweep pitch across +-90 degrees in tiny steps: the matrix moves by O(step) in both
    directions of the conversion (angles -> matrix, and matrix -> angles -> matrix)."""
    for centre in (math.pi / 2, -math.pi / 2):
        pitch = centre + torch.linspace(-1e-4, 1e-4, 401, dtype=F64)
        step = 2e-4 / 400
        yaw = torch.full_like(pitch, 0.8)
        roll = torch.full_like(pitch, -0.4)
        q = T.quat_from_yaw_pitch_roll(yaw.to(dtype), pitch.to(dtype), roll.to(dtype))
        m = T.quat_to_matrix(q)
        jumps = (m[1:] - m[:-1]).abs().amax(dim=(-1, -2))
        assert jumps.max() < 2 * step + tol
        back = T.quat_to_matrix(T.quat_from_yaw_pitch_roll(*T.yaw_pitch_roll_from_quat(q).unbind(-1)))
        jumps_back = (back[1:] - back[:-1]).abs().amax(dim=(-1, -2))
        assert jumps_back.max() < 2 * step + 2 * tol


def test_yaw_pitch_roll_from_quat_accepts_unnormalised_input():
    q = T.quat_from_yaw_pitch_roll(torch.tensor(0.4, dtype=F64), torch.tensor(-0.3, dtype=F64),
                                   torch.tensor(1.1, dtype=F64))
    assert torch.allclose(T.yaw_pitch_roll_from_quat(-7.5 * q), torch.tensor([0.4, -0.3, 1.1], dtype=F64), atol=1e-12)


# ----------------------------------------------------------------------------- look_at
def look(eye, target, dtype=F64):
    return T.quat_to_matrix(T.look_at_quat(torch.tensor(eye, dtype=dtype), torch.tensor(target, dtype=dtype)))


points = st.tuples(*(st.floats(-50, 50, allow_nan=False),) * 3)


@SETTINGS
@given(points, points)
def test_look_at_points_camera_y_at_the_target(eye, target):
    direction = torch.tensor(target, dtype=F64) - torch.tensor(eye, dtype=F64)
    if direction.norm() < 1e-3:
        return
    m = look(eye, target)
    assert_rotation(m, atol=1e-9)
    assert torch.allclose(m[:, 1], direction / direction.norm(), atol=1e-9)  # camera +Y -> target
    horizontal = direction[:2].norm() / direction.norm()
    if horizontal > 1e-3:
        assert abs(m[2, 0].item()) < 1e-9  # no roll: camera X stays horizontal
        assert m[2, 2] > 0  # camera up points up


@pytest.mark.parametrize("dtype,tol", [(F64, 1e-12), (torch.float32, 1e-6)])
@pytest.mark.parametrize("down", [True, False])
def test_look_at_straight_down_or_up_is_valid_and_matches_nearby_yaw_zero(dtype, tol, down):
    sign = -1.0 if down else 1.0
    m = look([1.0, 2.0, 3.0], [1.0, 2.0, 3.0 + sign * 4.0], dtype)
    assert_rotation(m.double(), atol=max(tol, 1e-12))
    assert torch.allclose(m[:, 1], torch.tensor([0.0, 0.0, sign], dtype=dtype), atol=tol)
    # Almost straight down/up while facing +Y (yaw 0): the matrices converge to the degenerate one.
    for eps in (1e-2, 1e-4, 1e-6, 1e-8, 1e-10):
        near = look([1.0, 2.0, 3.0], [1.0, 2.0 + 4.0 * eps, 3.0 + sign * 4.0], dtype)
        assert_rotation(near.double(), atol=max(tol, 1e-12))
        assert (near - m).abs().max().item() <= 2 * eps + tol, eps


def test_look_at_batched_mixes_degenerate_and_regular_rows():
    eye = torch.zeros(3, 3, dtype=F64)
    target = torch.tensor([[0.0, 0.0, -2.0], [3.0, 4.0, 0.0], [0.0, 0.0, 5.0]], dtype=F64)
    m = T.quat_to_matrix(T.look_at_quat(eye, target))
    assert_rotation(m)
    assert torch.allclose(m[..., 1], target / target.norm(dim=-1, keepdim=True), atol=1e-12)
    # Row 1 on its own gives the same answer: rows are independent.
    assert torch.allclose(m[1], look([0.0, 0.0, 0.0], [3.0, 4.0, 0.0]), atol=1e-15)


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_look_at_identical_points_raise(dtype):
    eye = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]], dtype=dtype)
    target = torch.tensor([[0.0, 1.0, 0.0], [1.0, 2.0, 3.0]], dtype=dtype)
    with pytest.raises(ValueError, match="look_at target must differ from the camera position"):
        T.look_at_quat(eye, target)


# ----------------------------------------------------------------------------- view / projection
def test_view_and_projection_put_the_look_at_target_on_the_axis():
    eye = torch.tensor([1e6, -1e6, 2.0], dtype=F64)
    target = eye + torch.tensor([3.0, 4.0, -1.0], dtype=F64)
    q = T.look_at_quat(eye, target)
    # Relative to the camera (as the renderer packs it), in float64.
    view = T.view_matrix(torch.zeros(3, dtype=F64), q)
    eye_space = view @ torch.cat((target - eye, torch.ones(1, dtype=F64)))
    assert torch.allclose(eye_space[:3], torch.tensor([0.0, 0.0, -(target - eye).norm().item()], dtype=F64), atol=1e-12)
    proj = T.perspective(torch.tensor(1.2, dtype=F64), 1.5, torch.tensor(0.05, dtype=F64),
                         torch.tensor(100.0, dtype=F64))
    clip = proj @ eye_space
    assert abs(clip[3].item() - (target - eye).norm().item()) < 1e-12  # w = distance along the view axis
    for depth, ndc in ((0.05, -1.0), (100.0, 1.0)):
        c = proj @ torch.tensor([0.0, 0.0, -depth, 1.0], dtype=F64)
        assert abs(c[2].item() / c[3].item() - ndc) < 1e-12


def _textbook_matrix(q: torch.Tensor) -> torch.Tensor:
    """quat_to_matrix as it was written before it became one gather: every entry's own ops."""
    s = 2.0 / (q * q).sum(-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack((
        torch.stack((1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)), -1),
        torch.stack((s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)), -1),
        torch.stack((s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)), -1)), -2)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_quat_to_matrix_is_the_textbook_formula_bit_for_bit(dtype):
    """Frames and digests depend on the camera matrices' last bits: the gathered form keeps them."""
    q = torch.randn(2000, 7, 4, dtype=dtype, generator=torch.Generator().manual_seed(0))
    q[::3] *= 1e3
    q[1::5, :, 2] = 0.0
    q[2::7, :, 1] = -0.0
    got = T.quat_to_matrix(q)
    assert got.shape == (2000, 7, 3, 3) and got.dtype == dtype
    assert got.numpy().tobytes() == _textbook_matrix(q).numpy().tobytes()
    assert T.quat_to_matrix(q[0, 0]).shape == (3, 3)
