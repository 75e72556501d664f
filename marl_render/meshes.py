"""Meshes: procedural shapes with normals and UVs, and model files Panda3D can load.

Procedural meshes are unit-sized and centred at the origin, so an instance's scale
sets its size: box and plane span [-0.5, 0.5], sphere/cylinder/cone have radius 0.5
and height 1 along +Z. A capsule keeps its round ends under uniform scale only, so its
radius and length are arguments.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MeshData:
    """Triangle mesh in numpy: positions [N,3], normals [N,3], uvs [N,2], triangles [T,3]."""

    name: str
    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    triangles: np.ndarray

    @functools.cached_property
    def flat(self) -> bool:
        """True when every triangle's three vertices share one normal (flat shading)."""
        corners = self.normals[self.triangles]  # [T, 3, 3]
        return bool(np.abs(corners - corners[:, :1]).max(initial=0.0) < 1e-6)

    def __post_init__(self):
        n = len(self.positions)
        for label, arr, width in (("positions", self.positions, 3), ("normals", self.normals, 3), ("uvs", self.uvs, 2)):
            if arr.shape != (n, width):
                raise ValueError(f"mesh {self.name!r}: {label} must have shape [{n}, {width}], got {list(arr.shape)}")
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3:
            raise ValueError(f"mesh {self.name!r}: triangles must have shape [T, 3], got {list(self.triangles.shape)}")
        if len(self.triangles) and (self.triangles.min() < 0 or self.triangles.max() >= n):
            raise ValueError(f"mesh {self.name!r}: triangle indices must be in [0, {n}), got range "
                             f"[{self.triangles.min()}, {self.triangles.max()}]")


def _mesh(name, positions, normals, uvs, triangles) -> MeshData:
    return MeshData(
        name,
        np.ascontiguousarray(positions, dtype=np.float32),
        np.ascontiguousarray(normals, dtype=np.float32),
        np.ascontiguousarray(uvs, dtype=np.float32),
        np.ascontiguousarray(triangles, dtype=np.int32),
    )


def box() -> MeshData:
    """Unit cube [-0.5, 0.5]^3 with flat normals (4 vertices per face)."""
    positions, normals, uvs, triangles = [], [], [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            normal = np.zeros(3)
            normal[axis] = sign
            u_axis, v_axis = [a for a in range(3) if a != axis]
            base = len(positions)
            for u, v in ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)):
                p = np.zeros(3)
                p[axis], p[u_axis], p[v_axis] = 0.5 * sign, u, v
                positions.append(p)
                normals.append(normal)
                uvs.append((u + 0.5, v + 0.5))
            quad = [(base, base + 1, base + 2), (base, base + 2, base + 3)]
            # Counter-clockwise seen from outside.
            if np.dot(np.cross(positions[base + 1] - positions[base], positions[base + 2] - positions[base]), normal) < 0:
                quad = [(a, c, b) for a, b, c in quad]
            triangles.extend(quad)
    return _mesh("box", positions, normals, uvs, triangles)


def plane() -> MeshData:
    """Unit square in the XY plane facing +Z (single-sided)."""
    positions = [(-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0)]
    normals = [(0, 0, 1)] * 4
    uvs = [(0, 0), (1, 0), (1, 1), (0, 1)]
    return _mesh("plane", positions, normals, uvs, [(0, 1, 2), (0, 2, 3)])


def _lathe(name, profile, segments):
    """Surface of revolution about Z from a profile of (radius, z, normal_r, normal_z, v)."""
    positions, normals, uvs, triangles = [], [], [], []
    rings = len(profile)
    for i in range(segments + 1):
        angle = 2 * math.pi * i / segments
        c, s = math.cos(angle), math.sin(angle)
        for r, z, nr, nz, v in profile:
            positions.append((r * c, r * s, z))
            normals.append((nr * c, nr * s, nz))
            uvs.append((i / segments, v))
    for i in range(segments):
        for j in range(rings - 1):
            a = i * rings + j
            b = (i + 1) * rings + j
            # Where the profile touches the axis (r = 0) one of the two triangles of a
            # quad has zero area: leave it out, it would only cost vertex work.
            if profile[j][0] > 1e-9:
                triangles.append((a, b, b + 1))
            if profile[j + 1][0] > 1e-9:
                triangles.append((a, b + 1, a + 1))
    mesh_normals = np.asarray(normals, dtype=np.float64)
    lengths = np.linalg.norm(mesh_normals, axis=1, keepdims=True)
    mesh_normals = mesh_normals / np.where(lengths > 0, lengths, 1)
    return _mesh(name, positions, mesh_normals, uvs, triangles)


def sphere(segments: int = 16, rings: int = 8) -> MeshData:
    profile = []
    for j in range(rings + 1):
        phi = math.pi * j / rings - math.pi / 2  # bottom to top
        r, z = 0.5 * math.cos(phi), 0.5 * math.sin(phi)
        profile.append((r, z, math.cos(phi), math.sin(phi), j / rings))
    return _lathe("sphere", profile, segments)


def cylinder(segments: int = 16) -> MeshData:
    profile = [
        (0.0, -0.5, 0, -1, 0.0), (0.5, -0.5, 0, -1, 0.1),  # bottom cap
        (0.5, -0.5, 1, 0, 0.1), (0.5, 0.5, 1, 0, 0.9),  # side
        (0.5, 0.5, 0, 1, 0.9), (0.0, 0.5, 0, 1, 1.0),  # top cap
    ]
    return _lathe("cylinder", profile, segments)


def cone(segments: int = 16) -> MeshData:
    slope = math.atan2(0.5, 1.0)  # side normal tilts up by atan(r / h)
    nr, nz = math.cos(slope), math.sin(slope)
    profile = [
        (0.0, -0.5, 0, -1, 0.0), (0.5, -0.5, 0, -1, 0.2),
        (0.5, -0.5, nr, nz, 0.2), (0.0, 0.5, nr, nz, 1.0),
    ]
    return _lathe("cone", profile, segments)


def capsule(radius: float = 0.25, length: float = 1.0, segments: int = 16, rings: int = 4) -> MeshData:
    """Capsule along Z with total height `length` (>= 2 * radius)."""
    if not radius > 0 or not length >= 2 * radius:
        raise ValueError(f"capsule needs radius > 0 and length >= 2 * radius, got radius={radius}, length={length}")
    half = length / 2 - radius
    profile = []
    for j in range(rings + 1):  # bottom hemisphere
        phi = -math.pi / 2 + (math.pi / 2) * j / rings
        profile.append((radius * math.cos(phi), -half + radius * math.sin(phi), math.cos(phi), math.sin(phi), 0.5 * j / rings))
    for j in range(rings + 1):  # top hemisphere
        phi = (math.pi / 2) * j / rings
        profile.append((radius * math.cos(phi), half + radius * math.sin(phi), math.cos(phi), math.sin(phi), 0.5 + 0.5 * j / rings))
    return _lathe("capsule", profile, segments)


PROCEDURAL = {"box": box, "sphere": sphere, "cylinder": cylinder, "capsule": capsule, "cone": cone, "plane": plane}


def to_panda_geom(mesh: MeshData):
    """Build a Panda3D GeomNode (vertex format v3n3t2) from mesh arrays in one copy each."""
    from panda3d.core import Geom, GeomNode, GeomTriangles, GeomVertexData, GeomVertexFormat

    vdata = GeomVertexData(mesh.name, GeomVertexFormat.get_v3n3t2(), Geom.UH_static)
    vdata.unclean_set_num_rows(len(mesh.positions))
    interleaved = np.concatenate((mesh.positions, mesh.normals, mesh.uvs), axis=1).astype(np.float32)
    array = vdata.modify_array(0)
    memoryview(array).cast("B")[:] = interleaved.tobytes()
    prim = GeomTriangles(Geom.UH_static)
    prim.set_index_type(Geom.NT_uint32)
    index_array = prim.modify_vertices()
    index_array.unclean_set_num_rows(mesh.triangles.size)
    memoryview(index_array).cast("B")[:] = mesh.triangles.astype(np.uint32).tobytes()
    geom = Geom(vdata)
    geom.add_primitive(prim)
    node = GeomNode(mesh.name)
    node.add_geom(geom)
    return node


def load_model(path: str):
    """Load any model file Panda3D reads (.egg, .bam, .gltf with panda3d-gltf, ...) as one node."""
    from panda3d.core import Filename, Loader, LoaderOptions, NodePath

    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"model path must be a str or os.PathLike, got {type(path).__name__}")
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"model file {path!r} does not exist")
    options = LoaderOptions(LoaderOptions.LF_no_cache | LoaderOptions.LF_report_errors)
    node = Loader.get_global_ptr().load_sync(Filename.from_os_specific(os.path.abspath(path)), options)
    if node is None:
        raise ValueError(f"model file {path!r} could not be loaded by Panda3D (unknown format or corrupt file)")
    model = NodePath(node)
    model.flatten_strong()
    if model.find_all_matches("**/+GeomNode").get_num_paths() == 0:
        raise ValueError(f"model file {path!r} contains no geometry")
    return model
