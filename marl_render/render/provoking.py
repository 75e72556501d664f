"""Flat-shaded meshes drawn from their shared corners.

A flat-shaded box is usually stored with 4 vertices per face (24) so that each face can
carry its own normal. On a CPU rasteriser every vertex is shaded on the main thread, for
every instance in every view. With a `flat` colour the GL takes a triangle's colour from
its provoking vertex only (the last one, by default), so the 8 corners suffice: each
triangle is rotated (winding kept) to end on a corner that carries the triangle's normal,
and a corner is copied only when every corner of a triangle already carries another
face's normal. Measured on llvmpipe with boxes: about a fifth less time per frame, the
same pixels. Texture coordinates differ per face, so textured groups keep their mesh.
"""
from __future__ import annotations

import numpy as np

from ..assets.meshes import MeshData


def shared_corner_mesh(mesh: MeshData) -> MeshData:
    """The flat-shaded `mesh` with welded corners and each triangle's normal on its last vertex.

    Raises ValueError for a mesh that is not flat-shaded (its triangles' corners would
    disagree on the normal). UVs of the result are zero."""
    if not mesh.flat:
        raise ValueError(f"mesh {mesh.name!r} is not flat-shaded: its corners cannot share vertices")
    corner_of_vertex = np.unique(mesh.positions, axis=0, return_inverse=True)[1].reshape(-1)
    corners = np.zeros((corner_of_vertex.max() + 1, 3), dtype=np.float32)
    corners[corner_of_vertex] = mesh.positions
    positions = list(corners)
    normals: list = [None] * len(positions)  # the face normal a corner carries, once chosen
    triangles = corner_of_vertex[mesh.triangles]
    face_normals = mesh.normals[mesh.triangles[:, 0]]
    # How many triangles of the same face use each corner: the corners on a face's
    # diagonal serve both of its triangles, so they are chosen first.
    face_of = {}
    for index, normal in enumerate(map(tuple, face_normals)):  # build time: a few dozen triangles
        face_of.setdefault(normal, []).append(index)
    result = np.empty_like(triangles)
    for normal, members in face_of.items():
        uses = np.bincount(triangles[members].reshape(-1), minlength=len(positions))
        for index in members:
            triangle = list(triangles[index])
            holding = [c for c in triangle if normals[c] == normal]
            free = sorted((c for c in triangle if normals[c] is None), key=lambda c: -uses[c])
            if holding or free:
                corner = (holding or free)[0]
            else:  # every corner carries another face's normal: copy one
                corner = len(positions)
                positions.append(positions[triangle[0]])
                normals.append(None)
                triangle[0] = corner
            normals[corner] = normal
            turn = triangle.index(corner) + 1
            result[index] = triangle[turn:] + triangle[:turn]
    normal_array = np.array([n if n is not None else (0.0, 0.0, 1.0) for n in normals], dtype=np.float32)
    positions = np.array(positions, dtype=np.float32)
    return MeshData(f"{mesh.name}:corners", positions, normal_array, np.zeros((len(positions), 2), np.float32),
                    np.ascontiguousarray(result, dtype=np.int32))
