"""Meshes whose triangles each know their own corners, for the depth output.

Depth is computed per pixel from the plane of the triangle being drawn (see
shaders/batch.frag), because a value interpolated by the rasteriser carries rounding
that depends on where the view's tile sits in the framebuffer. The plane reaches the
fragment shader as a flat varying, which takes the value of the triangle's provoking
vertex (its last one). So every triangle gets a provoking vertex of its own, and that
vertex carries the triangle's two other corners as attributes (`corner_a`, `corner_b`):
the vertex shader then has all three corners and computes the plane.

Triangles are rotated (which keeps their winding) so that a vertex no other triangle
has claimed comes last; a triangle whose three vertices are all claimed gets a copy of
one. A box needs no copies, a UV sphere about one per ring segment.
"""
from __future__ import annotations

import numpy as np

from ..assets.meshes import MeshData, to_panda_geom


def with_triangle_corners(mesh: MeshData) -> dict[str, np.ndarray]:
    """Vertex columns (vertex, normal, texcoord, corner_a, corner_b) and triangles [T, 3]
    where triangle t's last vertex is the last vertex of no other triangle and holds the
    positions of the triangle's first two vertices."""
    triangles = mesh.triangles.astype(np.int64)
    claimed = np.zeros(len(mesh.positions), dtype=bool)
    rotated = np.empty_like(triangles)
    copies = []  # original vertex index of every appended copy
    # Build-time only (once per mesh per renderer); meshes have hundreds of triangles.
    for t, triangle in enumerate(triangles):
        free = [k for k in (2, 0, 1) if not claimed[triangle[k]]]
        if free:
            last = free[0]
            rotated[t] = np.roll(triangle, 2 - last)
            claimed[triangle[last]] = True
        else:
            rotated[t] = triangle
            rotated[t, 2] = len(claimed) + len(copies)
            copies.append(triangle[2])
    source = np.concatenate((np.arange(len(mesh.positions)), np.asarray(copies, dtype=np.int64)))
    positions = mesh.positions[source]
    corner_a = np.zeros_like(positions)
    corner_b = np.zeros_like(positions)
    corner_a[rotated[:, 2]] = positions[rotated[:, 0]]
    corner_b[rotated[:, 2]] = positions[rotated[:, 1]]
    return {"vertex": positions, "normal": mesh.normals[source], "texcoord": mesh.uvs[source],
            "corner_a": corner_a, "corner_b": corner_b, "triangles": rotated.astype(np.uint32)}


def to_panda_geom_with_corners(mesh: MeshData):
    """A Panda3D GeomNode of `with_triangle_corners(mesh)`; the shader reads the extra
    columns as `in vec3 corner_a, corner_b`."""
    columns = with_triangle_corners(mesh)
    rearranged = MeshData(mesh.name, columns["vertex"], columns["normal"], columns["texcoord"], columns["triangles"])
    return to_panda_geom(rearranged, extra={"corner_a": columns["corner_a"], "corner_b": columns["corner_b"]})
