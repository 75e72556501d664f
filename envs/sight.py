"""What an arena agent sees, without rendering: line of sight and LIDAR over the planar geometry.

Everything is in the floor plane of envs/planar.py (metres; yaw 0 faces +y, yaw > 0 turns left)
and batched over worlds: rays are ``[W, R, 2]`` origins and unit directions, and every ray is
tested against every occluder at once. Three kinds of occluder:

* the arena's walls: the rectangle ``|x| <= hx, |y| <= hy``, which every ray from inside leaves;
* boxes: ``planar.Obstacles`` (centres, half extents, angle counter-clockwise), what a task's
  ``obstacles(state)`` gives the physics;
* circles: ``Circles`` (centres, radii, which are present), such as bodies.

    distance = first_hit(origin, direction, half_extent=(1.5, 1.5), boxes=boxes, circles=circles)   # [W, R]
    seen = line_of_sight(eye, yaw, targets, fov=math.pi / 2, reach=5.0, half_extent=(1.5, 1.5), boxes=boxes)
    scan = lidar(eye, yaw, rays=16, reach=5.0, half_extent=(1.5, 1.5), circles=bodies, skip=own_body)

ArenaScenario.sees and ArenaScenario.lidar (envs/arena.py) call these with a task's own geometry.
Sight is geometric: a target is a point, and it is seen when it lies within the field of view and
the reach and no occluder crosses the segment to it (an occluder that contains the target, such as
the box a target marks, does not hide it).
"""
from __future__ import annotations

import math
import numbers
from typing import NamedTuple

import torch
from torch import Tensor

from . import scenery

__all__ = ["Circles", "first_hit", "horizontal_fov", "lidar", "lidar_directions", "line_of_sight"]


class Circles(NamedTuple):
    """Round occluders: centres [W, K, 2] (m), radii [W, K] (m) and present [W, K] bool."""

    center: Tensor
    radius: Tensor
    present: Tensor


def horizontal_fov(fov_y: float, aspect: float = 1.0, pitch: float = 0.0) -> float:
    """The horizontal field of view (rad) of a camera with vertical field of view `fov_y`, a view
    `aspect` = width / height pixels wide, pitched by `pitch` (rad): exact for points at the
    camera's height (a pitched camera sees a little less far to the sides at its own height).
    ValueError for fov_y outside (0, pi), aspect not a finite number > 0 or pitch not finite."""
    checks = (("fov_y", fov_y, lambda v: 0 < v < math.pi, "a number in (0, pi) (radians)"),
              ("aspect", aspect, lambda v: 0 < v < math.inf, "a finite number > 0"),
              ("pitch", pitch, math.isfinite, "a finite number (radians)"))
    for name, value, good, want in checks:
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not good(value):
            raise ValueError(f"{name} must be {want}, got {value!r}")
    return 2 * math.atan(aspect * math.tan(fov_y / 2) * math.cos(pitch))


def first_hit(origin: Tensor, direction: Tensor, *, half_extent, boxes=None, circles: Circles | None = None,
              skip: Tensor | None = None) -> Tensor:
    """[W, R]: the distance (m) from each origin [W, R, 2] along its unit direction [W, R, 2] to the
    first wall, box or present circle it meets; 0 from inside a box or circle, or from outside the
    arena. skip [W, R, K] bool: circles a ray ignores (the body it starts from). ValueError for an
    origin that is not finite or a direction that is not a unit vector (one check, one sync)."""
    length = torch.linalg.vector_norm(direction, dim=-1)
    if not bool(torch.isfinite(origin).all() & ((length - 1).abs() <= 1e-3).all()):
        raise ValueError("origin must be finite and direction a unit vector on every ray (a zero or NaN direction "
                         "has no first hit)")
    return _first_hit(origin, direction, half_extent=half_extent, boxes=boxes, circles=circles, skip=skip)


def _first_hit(origin: Tensor, direction: Tensor, *, half_extent, boxes=None, circles: Circles | None = None,
               skip: Tensor | None = None) -> Tensor:
    """first_hit without its check on origin and direction (lidar's are checked, or unit by construction)."""
    _check_half_extent(half_extent)
    _check_circles(circles)
    distance = _wall_distance(origin, direction, half_extent)
    if boxes is not None and boxes.center.shape[1]:
        distance = torch.minimum(distance, _box_distances(origin, direction, boxes).amin(-1))
    if circles is not None and circles.center.shape[1]:
        hits = _circle_distances(origin, direction, circles)
        if skip is not None:
            hits = hits.masked_fill(skip, math.inf)
        distance = torch.minimum(distance, hits.amin(-1))
    return distance


def line_of_sight(eye: Tensor, yaw: Tensor, targets: Tensor, *, fov: float, reach: float, half_extent,
                  boxes=None, circles: Circles | None = None) -> Tensor:
    """[W, A, T] bool: whether an observer at eye [W, A, 2] facing yaw [W, A] sees each target point
    targets [W, T, 2]: its bearing within fov / 2 of the heading, at most `reach` metres away, and
    no wall, box or circle crossing the segment between them, except one that contains the target.
    A target at the eye itself is seen whatever the yaw (it has no bearing)."""
    _check_reach(reach, finite=False)
    if isinstance(fov, bool) or not isinstance(fov, numbers.Real) or not fov > 0:
        raise ValueError(f"fov must be a number > 0 (radians; 2 pi or more sees all round), got {fov!r}")
    _check_half_extent(half_extent)
    _check_circles(circles)
    if not bool(torch.isfinite(eye).all() & torch.isfinite(yaw).all() & torch.isfinite(targets).all()):
        raise ValueError("eye, yaw and targets must be finite: a NaN or inf position or heading sees nothing and is "
                         "seen by no one")
    W, A, T = eye.shape[0], eye.shape[1], targets.shape[1]
    delta = targets[:, None] - eye[:, :, None]  # [W, A, T, 2]
    distance = torch.linalg.vector_norm(delta, dim=-1)
    bearing = torch.atan2(-delta[..., 0], delta[..., 1])
    ahead = (scenery.wrap_angle(bearing - yaw[..., None]).abs() <= fov / 2) | (distance == 0)
    in_view = ahead & (distance <= reach)
    direction = delta / distance.clamp_min(1e-9)[..., None]
    origin, direction = eye[:, :, None].expand(W, A, T, 2).reshape(W, A * T, 2), direction.reshape(W, A * T, 2)
    point = targets[:, None].expand(W, A, T, 2).reshape(W, A * T, 2)
    blocked = _wall_distance(origin, direction, half_extent) < distance.reshape(W, A * T)
    if boxes is not None and boxes.center.shape[1]:
        crossing = _box_distances(origin, direction, boxes) < distance.reshape(W, A * T, 1)
        blocked |= (crossing & ~_inside_boxes(point, boxes)).any(-1)
    if circles is not None and circles.center.shape[1]:
        crossing = _circle_distances(origin, direction, circles) < distance.reshape(W, A * T, 1)
        blocked |= (crossing & ~_inside_circles(point, circles)).any(-1)
    return in_view & ~blocked.reshape(W, A, T)


def lidar_directions(yaw: Tensor, rays: int) -> Tensor:
    """[W, A, rays, 2] unit directions: ray 0 along each heading, the others evenly around the full
    circle counter-clockwise (ray k at yaw + 2 pi k / rays, to the left first)."""
    _check_rays(rays)
    offsets = torch.arange(rays, dtype=yaw.dtype, device=yaw.device) * (2 * math.pi / rays)
    return scenery.heading(yaw[..., None] + offsets)


def lidar(eye: Tensor, yaw: Tensor, *, rays: int, reach: float, half_extent, boxes=None,
          circles: Circles | None = None, skip: Tensor | None = None) -> Tensor:
    """[W, A, rays] in [0, 1]: the distance to the first hit along each ray of lidar_directions,
    divided by `reach` and capped at 1 (1: nothing within reach). skip [W, A, K] bool: circles each
    observer's rays ignore (its own body). An eye outside the arena reads 0 on every ray; a
    non-finite eye or yaw, `rays` < 1 and `reach` not a finite number > 0 are ValueErrors."""
    _check_rays(rays)
    _check_reach(reach, finite=True)
    finite = torch.isfinite(eye).all() & torch.isfinite(yaw).all()
    if circles is not None:
        finite = finite & (torch.isfinite(circles.center).all(-1) | ~circles.present).all()  # absent ones: unread
    if not bool(finite):  # one sync for all of them
        raise ValueError("eye and yaw must be finite: a NaN or inf position or heading has no readings"
                         if not bool(torch.isfinite(eye).all() & torch.isfinite(yaw).all()) else
                         "circles.center must be finite where present: a NaN or inf centre is missed by every ray")
    W, A = yaw.shape
    direction = lidar_directions(yaw, rays).reshape(W, A * rays, 2)
    origin = eye[:, :, None].expand(W, A, rays, 2).reshape(W, A * rays, 2)
    if skip is not None:
        skip = skip[:, :, None].expand(W, A, rays, skip.shape[-1]).reshape(W, A * rays, -1)
    distance = _first_hit(origin, direction, half_extent=half_extent, boxes=boxes, circles=circles, skip=skip)
    return (distance / reach).clamp_max(1.0).reshape(W, A, rays)


# ---------------------------------------------------------------------- arguments
def _check_rays(rays) -> None:
    if isinstance(rays, bool) or not isinstance(rays, numbers.Integral) or rays < 1:
        raise ValueError(f"rays must be an int >= 1, got {rays!r}")


def _check_reach(reach, *, finite: bool) -> None:
    if isinstance(reach, bool) or not isinstance(reach, numbers.Real) or not reach > 0 or (
            finite and not math.isfinite(reach)):
        raise ValueError(f"reach must be a {'finite ' if finite else ''}number > 0 (metres), got {reach!r}")


def _check_half_extent(half_extent) -> None:
    """The arena's half sizes (m): one number, or (x, y), each finite and > 0 (on the CPU: no sync)."""
    try:
        values = torch.as_tensor(half_extent, dtype=torch.float64, device="cpu").reshape(-1)
    except (TypeError, ValueError, RuntimeError):
        values = None
    if values is None or values.numel() not in (1, 2) or not bool((torch.isfinite(values) & (values > 0)).all()):
        raise ValueError(f"half_extent must be the arena's half size (m): a number or (x, y), finite and > 0, got "
                         f"{half_extent!r}")


def _check_circles(circles: Circles | None) -> None:
    if circles is not None and circles.radius.numel() and not bool((circles.radius >= 0).all()):
        raise ValueError(f"circles.radius must be >= 0 (metres), got a minimum of {float(circles.radius.min())}")


# ---------------------------------------------------------------------- ray against each shape
def _wall_distance(origin: Tensor, direction: Tensor, half_extent) -> Tensor:
    """[W, R]: where each ray leaves the arena's rectangle (0 for an origin already outside it)."""
    half = torch.tensor(half_extent, dtype=origin.dtype, device=origin.device)
    wall = torch.where(direction > 0, half, -half)  # the wall each axis runs towards
    moving = direction != 0
    t = torch.where(moving, (wall - origin) / torch.where(moving, direction, torch.ones_like(direction)), math.inf)
    outside = (origin.abs() > half).any(-1)
    return t.amin(-1).clamp_min(0.0).masked_fill(outside, 0.0)


def _box_distances(origin: Tensor, direction: Tensor, boxes) -> Tensor:
    """[W, R, K]: distance along each ray to each box (slab method in the box's frame), inf on a miss."""
    local = _box_frame(origin[:, :, None] - boxes.center[:, None], boxes)  # [W, R, K, 2]
    way = _box_frame(direction[:, :, None], boxes)
    half = boxes.half_extent[:, None]  # [W, 1, K, 2]
    moving = way != 0
    step = torch.where(moving, way, torch.ones_like(way))
    t1, t2 = (-half - local) / step, (half - local) / step
    # An axis the ray runs parallel to: its slab is everything (origin inside it) or nothing.
    inside = local.abs() <= half
    enter = torch.where(moving, torch.minimum(t1, t2), torch.where(inside, -math.inf, math.inf)).amax(-1)
    leave = torch.where(moving, torch.maximum(t1, t2), torch.where(inside, math.inf, -math.inf)).amin(-1)
    return torch.where((enter <= leave) & (leave >= 0), enter.clamp_min(0.0), math.inf)


def _box_frame(vector: Tensor, boxes) -> Tensor:
    """Vectors [W, R, K or 1, 2] of the world turned into each box's frame (by minus its angle)."""
    c, s = torch.cos(boxes.angle)[:, None], torch.sin(boxes.angle)[:, None]  # [W, 1, K]
    x, y = vector[..., 0], vector[..., 1]
    return torch.stack((c * x + s * y, -s * x + c * y), -1)


def _circle_distances(origin: Tensor, direction: Tensor, circles: Circles) -> Tensor:
    """[W, R, K]: distance along each ray to each present circle, inf on a miss."""
    rel = origin[:, :, None] - circles.center[:, None]  # [W, R, K, 2]
    b = (rel * direction[:, :, None]).sum(-1)
    c = (rel * rel).sum(-1) - circles.radius[:, None] ** 2
    discriminant = b * b - c
    root = discriminant.clamp_min(0.0).sqrt()
    hit = (discriminant >= 0) & (-b + root >= 0) & circles.present[:, None]
    return torch.where(hit, (-b - root).clamp_min(0.0), math.inf)


def _inside_boxes(point: Tensor, boxes) -> Tensor:
    """[W, R, K] bool: each point [W, R, 2] lies in each box."""
    local = _box_frame(point[:, :, None] - boxes.center[:, None], boxes)
    return (local.abs() <= boxes.half_extent[:, None]).all(-1)


def _inside_circles(point: Tensor, circles: Circles) -> Tensor:
    """[W, R, K] bool: each point [W, R, 2] lies in each circle."""
    return torch.linalg.vector_norm(point[:, :, None] - circles.center[:, None], dim=-1) <= circles.radius[:, None]
