"""Scene pieces shared by the environments: arena, colours, planar poses, overview camera.

Everything here is plain data or batched torch, so an environment file stays short:

    scene = mr.Scene(...)
    add_arena(scene, half_extent=(1.5, 1.5))            # static floor + 4 walls
    scene.add_group("agents", agent_mesh(), capacity=n)
    ...
    renderer.update("agents", position=planar_to_3d(pos, z), rotation=yaw_quat(yaw))

Frame: Z up, planar physics in the XY plane. A body's heading is its yaw about +Z;
yaw 0 faces +Y (the direction a mounted camera looks), yaw > 0 turns left (towards -X).
"""
from __future__ import annotations

import math

import torch

import marl_render as mr

# Muted, distinguishable colours (RGB in [0, 1]); a per-index palette for agents/landmarks.
PALETTE = (
    (0.90, 0.30, 0.25),  # red
    (0.25, 0.55, 0.90),  # blue
    (0.30, 0.75, 0.35),  # green
    (0.95, 0.75, 0.20),  # yellow
    (0.65, 0.35, 0.85),  # purple
    (0.20, 0.80, 0.80),  # cyan
    (0.95, 0.55, 0.15),  # orange
    (0.90, 0.45, 0.70),  # pink
    (0.55, 0.40, 0.25),  # brown
    (0.60, 0.85, 0.30),  # lime
    (0.25, 0.30, 0.65),  # navy
    (0.75, 0.75, 0.75),  # light grey
)

# One colour per team name; envs with teams colour each agent by its team.
TEAM_COLORS = {
    "agents": (0.25, 0.55, 0.90),
    "predator": (0.85, 0.25, 0.20),
    "prey": (0.30, 0.75, 0.35),
    "red": (0.85, 0.25, 0.20),
    "blue": (0.25, 0.45, 0.90),
}

FLOOR_COLOR = (0.42, 0.42, 0.40)
WALL_COLOR = (0.55, 0.50, 0.45)
SKY_COLOR = (0.55, 0.65, 0.75)


def palette(n: int, offset: int = 0) -> torch.Tensor:
    """[n, 3] float32 colours, cycling through PALETTE (darkened on each further cycle)."""
    index = torch.arange(n) + offset
    base = torch.tensor(PALETTE, dtype=torch.float32)[index % len(PALETTE)]
    shade = 0.75 ** (index // len(PALETTE)).to(torch.float32)
    return base * shade[:, None]


# ---------------------------------------------------------------------- static scenery
def add_arena(scene: mr.Scene, half_extent=(1.5, 1.5), *, wall_height: float = 0.4, wall_thickness: float = 0.1,
              floor_margin: float = 4.0, floor_color=FLOOR_COLOR, wall_color=WALL_COLOR,
              name: str = "arena") -> None:
    """One static group `name` of 5 boxes: instance 0 is the floor slab (top face at z=0),
    1-4 are the walls just outside |x| <= hx, |y| <= hy (+x, -x, +y, -y).

    One group rather than two because the renderer culls and draws once per group. The
    floor extends `floor_margin` metres past the walls so egocentric views see ground,
    not sky, below the horizon. Stored once for all worlds. Under the "appearance" effect the
    slab takes each world's floor look and the walls its wall look (their roles).
    """
    hx, hy = (float(v) for v in half_extent)
    t, h = float(wall_thickness), float(wall_height)
    position = [[0.0, 0.0, -0.05],
                [hx + t / 2, 0.0, h / 2], [-hx - t / 2, 0.0, h / 2],
                [0.0, hy + t / 2, h / 2], [0.0, -hy - t / 2, h / 2]]
    scale = [[2 * (hx + floor_margin), 2 * (hy + floor_margin), 0.1],
             [t, 2 * hy + 2 * t, h], [t, 2 * hy + 2 * t, h], [2 * hx, t, h], [2 * hx, t, h]]
    scene.add_static(name, "box", position=position, scale=scale, color=[list(floor_color)] + [list(wall_color)] * 4,
                     role=["floor"] + ["wall"] * 4)


def arena_shadow_bounds(half_extent=(1.5, 1.5), *, margin: float = 0.6, height: float = 1.0) -> tuple:
    """((x0, y0, z0), (x1, y1, z1)) for mr.Shadows(bounds=...): the arena, its walls and
    `margin` metres around them (where the walls' shadows fall under a light from above)."""
    hx, hy = (float(v) for v in half_extent)
    return (-hx - margin, -hy - margin, -0.1), (hx + margin, hy + margin, height)


def agent_mesh(radius: float = 0.15, height: float = 0.5) -> mr.MeshData:
    """Low-poly upright capsule (8 segments): agents are drawn in every other agent's view."""
    return mr.capsule(radius, height, segments=8, rings=2)


def disc_mesh(segments: int = 8) -> mr.MeshData:
    """Low-poly cylinder for flat markers (landmarks, goals); scale sets radius and height."""
    return mr.cylinder(segments=segments)


# ---------------------------------------------------------------------- planar poses
def yaw_quat(yaw: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (w, x, y, z) [..., 4] of rotations by `yaw` about +Z (float32)."""
    half = 0.5 * yaw.to(torch.float32)
    zero = torch.zeros_like(half)
    return torch.stack((torch.cos(half), zero, zero, torch.sin(half)), -1)


def heading(yaw: torch.Tensor) -> torch.Tensor:
    """Unit forward vectors [..., 2] of bodies with `yaw` (yaw 0 faces +Y, like a mounted camera)."""
    return torch.stack((-torch.sin(yaw), torch.cos(yaw)), -1)


def planar_to_3d(pos: torch.Tensor, z) -> torch.Tensor:
    """[..., 2] planar positions -> [..., 3] with height z (scalar or broadcastable to [...])."""
    z = torch.as_tensor(z, dtype=pos.dtype, device=pos.device).expand(pos.shape[:-1])
    return torch.cat((pos, z[..., None]), -1)


def wrap_angle(angle: torch.Tensor) -> torch.Tensor:
    """Angles wrapped into [-pi, pi)."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


# ---------------------------------------------------------------------- overview camera
def top_down_camera(half_extent=(1.5, 1.5), fov_y: float = math.radians(60.0), tilt: float = 0.25):
    """(eye, target) for a camera that sees the whole arena from above.

    `tilt` moves the eye back along -Y by that fraction of its height, so the view is
    slightly oblique (walls and bodies read as 3D) and never exactly straight down.
    """
    hx, hy = (float(v) for v in half_extent)
    reach = max(hx, hy) * 1.15
    height = reach / math.tan(fov_y / 2)
    eye = torch.tensor([0.0, -tilt * height, height], dtype=torch.float64)
    target = torch.zeros(3, dtype=torch.float64)
    return eye, target


def cell_spawn(draws, num_worlds: int, margin: torch.Tensor, grid: int, half_extent: float) -> torch.Tensor:
    """Random positions [W, C, 2] (CPU, from draws: envs/levels.py) of C = len(margin) objects in
    distinct cells of a grid x grid tiling of |x|, |y| <= half_extent, in a random order of cells per world.

    Object c stays at least margin[c] inside its cell's borders, so objects whose footprint
    fits in a circle of radius margin[c] never overlap each other or the walls, and two
    circles of radius r start at least 2 (margin - r) apart.
    """
    C = margin.shape[0]
    cell = 2 * half_extent / grid
    order = draws.rand("cells.order", (num_worlds, grid * grid)).argsort(-1)[:, :C]
    centre = (torch.stack((order % grid, order // grid), -1) + 0.5) * cell - half_extent
    reach = (cell / 2 - margin).clamp_min(0)[:, None]  # [C, 1]
    return centre + (draws.rand("cells.offset", (num_worlds, C, 2)) * 2 - 1) * reach
