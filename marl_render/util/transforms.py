"""Batched rigid-transform math in torch.

Frame convention (Panda3D's): right-handed, Z up, Y forward, X right.
Quaternions are unit (w, x, y, z). Every function works on any leading batch shape.
"""
from __future__ import annotations

import torch

# Below this norm a quaternion carries no usable direction.
_MIN_QUAT_NORM = 1e-12


def normalize_quat(q: torch.Tensor, *, name: str = "rotation") -> torch.Tensor:
    """Unit quaternion with w >= 0 (q and -q are the same rotation).

    Raises ValueError for (near-)zero quaternions instead of producing NaN. The largest component
    is divided out before the norm is taken, so that huge quaternions (1e200) do not overflow it.
    """
    largest = q.abs().amax(dim=-1, keepdim=True)
    if bool((largest < _MIN_QUAT_NORM).any()):
        raise ValueError(f"{name} must be non-zero quaternions (w, x, y, z), got one with norm < {_MIN_QUAT_NORM}")
    q = q / largest
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v [..., 3] by unit quaternions q [..., 4]."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * torch.cross(u, v, dim=-1)
    return v + w * t + torch.cross(u, t, dim=-1)


# quat_to_matrix's nine entries, row by row: [1 -] s * (q[a] q[b] + sign q[c] q[d]), the products and
# sums of the textbook formula in its order (a - b and a + (-1 * b) are the same float), as one gather.
_M_A = torch.tensor([2, 1, 1, 1, 1, 2, 1, 2, 1])
_M_B = torch.tensor([2, 2, 3, 2, 1, 3, 3, 3, 1])
_M_C = torch.tensor([3, 0, 0, 0, 3, 0, 0, 0, 2])
_M_D = torch.tensor([3, 3, 2, 3, 3, 1, 2, 1, 2])
_M_SIGN = torch.tensor([1.0, -1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0])
_M_DIAGONAL = torch.tensor([True, False, False, False, True, False, False, False, True])


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] -> [..., 3, 3]; columns are the rotated x, y, z axes.

    Any non-zero scale of q gives the same rotation (the formula is divided by |q|^2),
    so slightly unnormalised quaternions never shear or scale; (near-)zero ones raise.
    The entries are those of the textbook formula (1 - s (y^2 + z^2), s (xy - wz), ...) bit for
    bit, computed as a few gathered products instead of 30 small ops (it runs every frame).
    """
    norm2 = (q * q).sum(-1)
    if bool((norm2 < _MIN_QUAT_NORM**2).any()):
        raise ValueError(f"q must be non-zero quaternions (w, x, y, z), got one with norm < {_MIN_QUAT_NORM}")
    s = (2.0 / norm2)[..., None]
    sign = _M_SIGN.to(device=q.device, dtype=q.dtype)
    scaled = s * (q[..., _M_A] * q[..., _M_B] + sign * (q[..., _M_C] * q[..., _M_D]))
    return torch.where(_M_DIAGONAL.to(q.device), 1 - scaled, scaled).unflatten(-1, (3, 3))


def matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] -> unit quaternions, numerically safe in all branches."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    w4, x4, y4, z4 = 1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22
    # Off-diagonal sums and differences shared by the candidates.
    xw, yw, zw = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    xy, xz, yz = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    # Four candidates: row k is q scaled by 4 q_k (for a unit q); pick the row with the
    # largest diagonal term, the best-conditioned one, and normalise it.
    candidates = torch.stack(
        (
            torch.stack((w4, xw, yw, zw), -1),
            torch.stack((xw, x4, xy, xz), -1),
            torch.stack((yw, xy, y4, yz), -1),
            torch.stack((zw, xz, yz, z4), -1),
        ),
        dim=-2,
    )
    diag = torch.stack((w4, x4, y4, z4), -1)
    best = diag.argmax(dim=-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    return normalize_quat(q)


def quat_from_yaw_pitch_roll(yaw, pitch=None, roll=None) -> torch.Tensor:
    """yaw about +Z (left turn), then pitch about the body's +X (nose up), then roll about +Y.

    q = q_z(yaw) * q_x(pitch) * q_y(roll). Arguments are tensors or floats of one shape.
    """
    yaw = torch.as_tensor(yaw, dtype=torch.get_default_dtype() if not torch.is_tensor(yaw) else None)
    pitch = torch.zeros_like(yaw) if pitch is None else torch.as_tensor(pitch, dtype=yaw.dtype)
    roll = torch.zeros_like(yaw) if roll is None else torch.as_tensor(roll, dtype=yaw.dtype)
    cy, sy = torch.cos(yaw / 2), torch.sin(yaw / 2)
    cp, sp = torch.cos(pitch / 2), torch.sin(pitch / 2)
    cr, sr = torch.cos(roll / 2), torch.sin(roll / 2)
    zero = torch.zeros_like(cy)
    qz = torch.stack((cy, zero, zero, sy), -1)
    qx = torch.stack((cp, sp, torch.zeros_like(cp), torch.zeros_like(cp)), -1)
    qy = torch.stack((cr, torch.zeros_like(cr), sr, torch.zeros_like(cr)), -1)
    return quat_multiply(quat_multiply(qz, qx), qy)


def yaw_pitch_roll_from_quat(q: torch.Tensor) -> torch.Tensor:
    """Inverse of quat_from_yaw_pitch_roll -> [..., 3] (yaw, pitch, roll).

    At pitch = +-90 degrees yaw and roll are coupled; roll is set to 0 there and the
    rotation is still reproduced exactly.
    """
    m = quat_to_matrix(normalize_quat(q))
    # R = Rz(yaw) Rx(pitch) Ry(roll): row 2 is (-cos(pitch) sin(roll), sin(pitch), cos(pitch) cos(roll)).
    # atan2 keeps pitch precise near +-90 degrees, where asin(m[2,1]) loses half the digits
    # (asin(1 - eps) is off by sqrt(2 eps): 3e-4 rad in float32).
    cos_pitch = torch.hypot(m[..., 2, 0], m[..., 2, 2])
    pitch = torch.atan2(m[..., 2, 1], cos_pitch)
    # Only rounding noise left in row 2: call it the lock and set roll to 0.
    gimbal = cos_pitch < 4 * torch.finfo(m.dtype).eps
    roll = torch.where(gimbal, torch.zeros_like(pitch), torch.atan2(-m[..., 2, 0], m[..., 2, 2]))
    # Yaw from R Ry(-roll) = Rz(yaw) Rx(pitch), whose first column is (cos yaw, sin yaw, 0).
    # Near the gimbal lock roll is ill-conditioned (its error grows like 1 / cos(pitch));
    # taking yaw from the roll actually used makes yaw absorb that error, so the
    # rotation is reproduced to rounding precision at every pitch.
    cr, sr = torch.cos(roll), torch.sin(roll)
    yaw = torch.atan2(m[..., 1, 0] * cr + m[..., 1, 2] * sr, m[..., 0, 0] * cr + m[..., 0, 2] * sr)
    return torch.stack((yaw, pitch, roll), -1)


def look_at_quat(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor | None = None) -> torch.Tensor:
    """Camera orientation looking from eye to target (+Y forward, +Z up in the camera frame).

    When forward is (anti)parallel to `up`, a fallback up (+Y world) is used so the
    result is a valid rotation that varies smoothly with nearby directions of the same yaw.
    """
    forward = target - eye
    norm = forward.norm(dim=-1, keepdim=True)
    if bool((norm < 1e-12).any()):
        raise ValueError("look_at target must differ from the camera position (got identical points)")
    forward = forward / norm
    if up is None:
        up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype, device=eye.device).expand_as(forward)
    else:
        up = up.expand_as(forward).to(eye.dtype)
    right = torch.cross(forward, up, dim=-1)
    right_norm = right.norm(dim=-1, keepdim=True)
    # Looking straight up/down: take "right" as world +X rotated so that it is
    # perpendicular to forward, which matches the limit of yaw = 0 from nearby directions.
    fallback_axis = torch.tensor([1.0, 0.0, 0.0], dtype=eye.dtype, device=eye.device).expand_as(forward)
    fallback = fallback_axis - (fallback_axis * forward).sum(-1, keepdim=True) * forward
    degenerate = right_norm < 1e-6
    right = torch.where(degenerate, fallback, right)
    right = right / right.norm(dim=-1, keepdim=True)
    cam_up = torch.cross(right, forward, dim=-1)
    m = torch.stack((right, forward, cam_up), dim=-1)
    return matrix_to_quat(m)


def perspective(fov_y: torch.Tensor, aspect: float, near: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """OpenGL projection [..., 4, 4] for a GL eye frame (x right, y up, looking down -z)."""
    f = 1.0 / torch.tan(fov_y / 2)
    zero = torch.zeros_like(f)
    proj = torch.stack(
        (
            torch.stack((f / aspect, zero, zero, zero), -1),
            torch.stack((zero, f, zero, zero), -1),
            torch.stack((zero, zero, (far + near) / (near - far), 2 * far * near / (near - far)), -1),
            torch.stack((zero, zero, -torch.ones_like(f), zero), -1),
        ),
        dim=-2,
    )
    return proj


# Camera frame (x right, y forward, z up) -> GL eye frame (x right, y up, -z forward).
_CAMERA_TO_GL = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def view_matrix(position: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """World -> GL eye transform [..., 4, 4] for cameras at `position` with `rotation`."""
    r_world_from_cam = quat_to_matrix(rotation)
    r = _CAMERA_TO_GL.to(position) @ r_world_from_cam.transpose(-1, -2)
    t = -(r @ position[..., None])[..., 0]
    bottom = torch.zeros(*position.shape[:-1], 1, 4, dtype=position.dtype, device=position.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat((torch.cat((r, t[..., None]), -1), bottom), -2)
