"""Which (view, instance) pairs can be seen: frustum culling in torch.

On a CPU rasteriser every vertex of every drawn instance costs time in every view,
even when the GPU would clip it away. Culling with bounding spheres against each
view's frustum, the agent's own body and the active mask, all batched, leaves the
shader only the pairs that can reach a pixel.
"""
from __future__ import annotations

import torch


def frustum_planes(view_projection: torch.Tensor) -> torch.Tensor:
    """Planes [..., 6, 4] (a, b, c, d; inside when a x + b y + c z + d >= 0), unit normals.

    Rows of the clip matrix combine into left, right, bottom, top, near, far planes.
    """
    r0, r1, r2, r3 = view_projection.unbind(-2)
    planes = torch.stack((r3 + r0, r3 - r0, r3 + r1, r3 - r1, r3 + r2, r3 - r2), dim=-2)
    return planes / planes[..., :3].norm(dim=-1, keepdim=True).clamp_min(1e-30)


def inside_frustum(planes: torch.Tensor, centers: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """bool [W, A, K]: whether the bounding sphere of instance k of world w meets view (w, a).

    planes [W, A, 6, 4], centers [W, K, 3] (relative to the world origin), radii [W, K].
    """
    planes = planes.to(torch.float32)  # coordinates are relative to the world origin: small
    # [W, A, 6, 1, 3] x [W, 1, 1, K, 3]: tiny operands, where an einsum/bmm costs more in dispatch.
    distance = (planes[:, :, :, None, :3] * centers.to(torch.float32)[:, None, None]).sum(-1) + planes[..., 3:4]
    return (distance >= -radii[:, None, None, :].to(torch.float32)).all(dim=2)


def pair_list(mask: torch.Tensor) -> torch.Tensor:
    """int32 flat indices view * K + instance of the True entries of mask [W, A, K], sorted by view."""
    return mask.flatten().nonzero().squeeze(1).to(torch.int32)


def mesh_radius(mesh) -> float:
    """Radius of a sphere about the mesh origin that contains the whole mesh (in every pose,
    for a skinned mesh)."""
    pose_radius = getattr(mesh, "pose_radius", None)
    if pose_radius is not None:
        return pose_radius
    positions = getattr(mesh, "positions", None)
    if positions is not None:
        return float((positions.astype("float64") ** 2).sum(axis=1).max() ** 0.5) if len(positions) else 0.0
    low, high = mesh.get_tight_bounds()
    corners = [(x, y, z) for x in (low.x, high.x) for y in (low.y, high.y) for z in (low.z, high.z)]
    return max((x * x + y * y + z * z) ** 0.5 for x, y, z in corners)
