"""Meshes: procedural shapes with normals and UVs, and the triangles of model files.

Procedural meshes are unit-sized and centred at the origin, so an instance's scale
sets its size: box and plane span [-0.5, 0.5], sphere/cylinder/cone have radius 0.5
and height 1 along +Z. A capsule keeps its round ends under uniform scale only, so its
radius and length are arguments.

This module imports only numpy and the standard library at the top: the child process
that parses model files runs it on its own, without the rest of the package.
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
        arrays = (("positions", self.positions, "f"), ("normals", self.normals, "f"), ("uvs", self.uvs, "f"),
                  ("triangles", self.triangles, "iu"))
        for label, arr, kinds in arrays:
            if not isinstance(arr, np.ndarray) or arr.dtype.kind not in kinds:
                kind = "floating" if kinds == "f" else "integer"
                given = f"array of dtype {arr.dtype}" if isinstance(arr, np.ndarray) else type(arr).__name__
                raise TypeError(f"mesh {self.name!r}: {label} must be a numpy array of {kind} dtype, got {given}")
        n = len(self.positions)
        for label, arr, width in (("positions", self.positions, 3), ("normals", self.normals, 3), ("uvs", self.uvs, 2)):
            if arr.shape != (n, width):
                raise ValueError(f"mesh {self.name!r}: {label} must have shape [{n}, {width}], got {list(arr.shape)}")
            if not np.isfinite(arr).all():
                raise ValueError(f"mesh {self.name!r}: {label} must be finite (no NaN/inf)")
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
            edges = positions[base + 1] - positions[base], positions[base + 2] - positions[base]
            if np.dot(np.cross(*edges), normal) < 0:
                quad = [(a, c, b) for a, b, c in quad]
            triangles.extend(quad)
    return _mesh("box", positions, normals, uvs, triangles)


def plane() -> MeshData:
    """Unit square in the XY plane facing +Z (single-sided)."""
    positions = [(-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0)]
    normals = [(0, 0, 1)] * 4
    uvs = [(0, 0), (1, 0), (1, 1), (0, 1)]
    return _mesh("plane", positions, normals, uvs, [(0, 1, 2), (0, 2, 3)])


def lathe(name: str, profile, segments: int) -> MeshData:
    """A surface of revolution about +Z named `name`: the profile, a sequence of (radius, z,
    normal_r, normal_z, v) rings from bottom to top, swept through `segments` steps of a full
    turn (u runs 0..1 around, v as given). Rings of radius 0 touch the axis and get no
    degenerate triangles. sphere, cylinder, cone and capsule are lathes, and so are the
    skinned limbs of marl_render.skinning."""
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
    """Sphere of diameter 1 centred at the origin (a lathe about +Z): `segments` steps around,
    `rings` from pole to pole; smooth normals, u around the axis, v from bottom to top."""
    profile = []
    for j in range(rings + 1):
        phi = math.pi * j / rings - math.pi / 2  # bottom to top
        r, z = 0.5 * math.cos(phi), 0.5 * math.sin(phi)
        profile.append((r, z, math.cos(phi), math.sin(phi), j / rings))
    return lathe("sphere", profile, segments)


def cylinder(segments: int = 16) -> MeshData:
    """Closed cylinder along Z, diameter 1 and height 1, centred at the origin (z in [-0.5, 0.5]):
    flat caps, a smooth side, `segments` steps around (a lathe about +Z)."""
    profile = [
        (0.0, -0.5, 0, -1, 0.0), (0.5, -0.5, 0, -1, 0.1),  # bottom cap
        (0.5, -0.5, 1, 0, 0.1), (0.5, 0.5, 1, 0, 0.9),  # side
        (0.5, 0.5, 0, 1, 0.9), (0.0, 0.5, 0, 1, 1.0),  # top cap
    ]
    return lathe("cylinder", profile, segments)


def cone(segments: int = 16) -> MeshData:
    """Cone along Z: a base disc of diameter 1 at z = -0.5, the apex at z = 0.5; smooth side
    normals tilted by the slope, `segments` steps around (a lathe about +Z)."""
    slope = math.atan2(0.5, 1.0)  # side normal tilts up by atan(r / h)
    nr, nz = math.cos(slope), math.sin(slope)
    profile = [
        (0.0, -0.5, 0, -1, 0.0), (0.5, -0.5, 0, -1, 0.2),
        (0.5, -0.5, nr, nz, 0.2), (0.0, 0.5, nr, nz, 1.0),
    ]
    return lathe("cone", profile, segments)


def capsule(radius: float = 0.25, length: float = 1.0, segments: int = 16, rings: int = 4) -> MeshData:
    """Capsule along Z with total height `length` (>= 2 * radius)."""
    if not radius > 0 or not length >= 2 * radius:
        raise ValueError(f"capsule needs radius > 0 and length >= 2 * radius, got radius={radius}, length={length}")
    half = length / 2 - radius
    profile = []
    for j in range(rings + 1):  # bottom hemisphere
        phi = -math.pi / 2 + (math.pi / 2) * j / rings
        profile.append((radius * math.cos(phi), -half + radius * math.sin(phi), math.cos(phi), math.sin(phi),
                        0.5 * j / rings))
    for j in range(rings + 1):  # top hemisphere
        phi = (math.pi / 2) * j / rings
        profile.append((radius * math.cos(phi), half + radius * math.sin(phi), math.cos(phi), math.sin(phi),
                        0.5 + 0.5 * j / rings))
    return lathe("capsule", profile, segments)


PROCEDURAL = {"box": box, "sphere": sphere, "cylinder": cylinder, "capsule": capsule, "cone": cone, "plane": plane}


def to_panda_geom(mesh: MeshData, extra: dict | None = None):
    """Build a Panda3D GeomNode (vertex format v3n3t2) from mesh arrays in one copy each.

    extra: more float32 [N, k] vertex columns by name, interleaved after the uvs (a
    shader reads column NAME as `in vecK NAME`)."""
    from panda3d.core import (
        Geom,
        GeomNode,
        GeomTriangles,
        GeomVertexArrayFormat,
        GeomVertexData,
        GeomVertexFormat,
        InternalName,
    )

    columns = [mesh.positions, mesh.normals, mesh.uvs]
    vertex_format = GeomVertexFormat.get_v3n3t2()
    if extra:
        array_format = GeomVertexArrayFormat(vertex_format.get_array(0))
        for name, values in extra.items():
            array_format.add_column(InternalName.make(name), values.shape[1], Geom.NT_float32, Geom.C_other)
            columns.append(values)
        vertex_format = GeomVertexFormat.register_format(array_format)
    vdata = GeomVertexData(mesh.name, vertex_format, Geom.UH_static)
    vdata.unclean_set_num_rows(len(mesh.positions))
    interleaved = np.concatenate(columns, axis=1).astype(np.float32)
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


# ---------------------------------------------------------------------- model files
# Panda3D's loaders run native parsers and image decoders that can end the process on a
# corrupt file (a truncated BMP texture exits with status 1, no exception). So a model
# file is parsed in a child process, which sends back only triangle arrays; this process
# never parses it. Textures the model references are then decoded here with Pillow (see
# images.py): the renderer never shows a model's own textures (a group's `texture=`
# replaces them), but a model whose textures are corrupt is refused, not half-loaded.
# The child is started isolated (-I: neither the working directory nor PYTHON* variables reach
# its module path, so a numpy.py planted where the user runs cannot execute), dies with this
# process (Linux: PR_SET_PDEATHSIG), and works in a folder named after this process's pid, which
# a later load removes if this process died before it could (model_checks.py refuses the files
# that would keep the parser busy until the timeout).
MODEL_LOAD_TIMEOUT = 120.0  # seconds; a file that still hangs the parser is refused after this (load_model(timeout=))

# Runs meshes.py in the child without importing the marl_render package (torch is slow
# to import and not needed there); the module needs only numpy and Panda3D.
_CHILD_BOOTSTRAP = """
import importlib.util, os, sys
try:  # Linux: killed when the parent dies (prctl PR_SET_PDEATHSIG = 1, SIGKILL = 9)
    import ctypes
    ctypes.CDLL(None).prctl(1, 9)
except (OSError, AttributeError):  # elsewhere the parent's timeout still bounds the child
    pass
if os.getppid() != int(sys.argv[5]):  # the parent died before the line above: nobody waits for the result
    sys.exit(3)
sys.path[:0] = sys.argv[6].split(os.pathsep)  # the parent's: -I drops PYTHONPATH, where an install may live
spec = importlib.util.spec_from_file_location("marl_render_model_child", sys.argv[1])
module = importlib.util.module_from_spec(spec)
sys.modules[spec.name] = module
spec.loader.exec_module(module)
getattr(module, sys.argv[4])(sys.argv[2], sys.argv[3])
"""


def load_model(path, *, name: str = "mesh", timeout: float | None = None) -> MeshData:
    """Triangles of a model file Panda3D reads (.egg, .bam, and through Assimp .gltf, .obj,
    .fbx, ...), in the model's frame with its node transforms applied, as MeshData.

    Raises FileNotFoundError for a missing file and ValueError for anything that is not a
    regular file, not a model, corrupt or without triangles, or that references a texture
    file that is not a complete image (textures that cannot be found are left out, as
    Panda3D does); every message names `name` and the file. `timeout` (seconds, default
    MODEL_LOAD_TIMEOUT = 120) bounds the parse; files known to hang the parser (a cycle in a
    glTF hierarchy, an .egg referencing a device, an OBJ face of more than 10,000 corners)
    are refused before it starts."""
    path, result = parse_model_file(path, name, skinned=False, timeout=timeout)
    return _mesh(os.path.basename(path), result["positions"], result["normals"], result["uvs"], result["triangles"])


def parse_model_file(path, name: str, *, skinned: bool, timeout: float | None = None) -> tuple[str, dict]:
    """(absolute path, numpy arrays by name) of the model file `path`, parsed by Panda3D in a
    child process: the triangles (positions, normals, uvs, triangles) and, when `skinned`, the
    skin too (joint_names, parents, pivots, skin_joints, skin_weights). load_model and
    skinning.load_skinned_model build their meshes from it; errors as load_model documents
    them, each naming `name` and the file."""
    import subprocess
    import sys
    import tempfile

    from ..util.validation import positive_float, regular_file
    from .model_checks import check_model_file

    timeout = MODEL_LOAD_TIMEOUT if timeout is None else positive_float("timeout", timeout)
    path = os.path.abspath(regular_file(name, path, kind="model"))
    check_model_file(name, path, skinned=skinned)
    writer = "_write_skin_arrays" if skinned else "_write_model_arrays"
    _remove_orphaned_folders(tempfile.gettempdir())
    with tempfile.TemporaryDirectory(prefix=f"marl_render_model_{os.getpid()}_") as folder:
        output = os.path.join(folder, "arrays.npz")
        try:
            child = subprocess.run([sys.executable, "-I", "-c", _CHILD_BOOTSTRAP, __file__, path, output, writer,
                                    str(os.getpid()), os.pathsep.join(p for p in sys.path if p)],
                                   stdin=subprocess.DEVNULL, capture_output=True, timeout=timeout, cwd=folder)
        except subprocess.TimeoutExpired:
            raise ValueError(f"{name}: model file {path!r} was still loading after {timeout:g} s; refused (raise "
                             f"load_model's timeout if the file is just large)") from None
        except OSError as error:
            raise RuntimeError(f"the Python interpreter {sys.executable!r} (sys.executable) could not be started to "
                               f"parse {name}'s model file in a child process: {error!r}") from None
        log = child.stderr.decode(errors="replace")
        if "No module named 'panda3d'" in log or "No module named 'numpy'" in log:
            missing = "panda3d" if "'panda3d'" in log else "numpy"
            raise RuntimeError(f"{missing} cannot be imported by {sys.executable!r} (sys.executable), which parses "
                               f"model files in a child process; install it for that interpreter") from None
        printed = child.stdout.decode(errors="replace")  # panda3d-gltf reports on stdout
        if "Could not find joint in jvtmap" in log + printed:  # it dropped (or misbound) a vertex's joint
            raise ValueError(f"{name}: model file {path!r} has vertices that follow a joint its skin does not list; "
                             "refused (its influences would be dropped or bound to another joint)")
        textures = _textures_in_log(log)
        _check_textures(name, path, textures)  # first: a corrupt texture is the likely cause of a crash
        if child.returncode != 0 or not os.path.exists(output):
            last = f" while reading its texture {textures[-1]!r}" if textures else ""
            raise ValueError(f"{name}: model file {path!r} could not be loaded: Panda3D's loader ended with exit "
                             f"status {child.returncode}{last}.{_messages(log)}")
        with np.load(output, allow_pickle=False) as arrays:
            result = {key: arrays[key] for key in arrays.files}
    if "error" in result:
        reason = str(result["error"])
        if "is unrecognized" in log:
            reason = f"is not a model file: Panda3D has no loader for its extension {os.path.splitext(path)[1]!r}"
            log = ""  # its list of every known extension is too long for a message
        raise ValueError(f"{name}: model file {path!r} {reason}.{_messages(log)}")
    return path, result


def _remove_orphaned_folders(root: str) -> None:
    """Remove the work folders of loads whose process died before it could (named with its pid)."""
    import shutil

    try:
        entries = os.listdir(root)
    except OSError:
        return
    for entry in entries:
        parts = entry.split("_")
        if not entry.startswith("marl_render_model_") or len(parts) < 5 or not parts[3].isdigit():
            continue
        pid = int(parts[3])
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            shutil.rmtree(os.path.join(root, entry), ignore_errors=True)
        except OSError:
            continue


def _textures_in_log(log: str) -> list[str]:
    """Image files Panda3D opened for a model, from its "Loading texture A [and alpha component B]" lines."""
    files = []
    for line in log.splitlines():
        if "Loading texture " in line:
            files += line.split("Loading texture ", 1)[1].strip().split(" and alpha component ")
    return list(dict.fromkeys(files))


def _messages(log: str) -> str:
    """The last lines Panda3D wrote, less its progress notes, to end an error message with."""
    lines = [line for line in log.strip().splitlines()
             if line.strip() and not line.startswith((":loader: loading file type", ":gobj: Loading texture"))]
    return " Panda3D said:\n" + "\n".join(lines[-6:]) if lines else ""


def _check_textures(name: str, path: str, textures: list[str]) -> None:
    from .images import decode_image

    for texture in textures:
        if not os.path.isfile(texture):
            continue  # not found: Panda3D leaves it out (and the renderer never shows a model's textures)
        try:
            decode_image(texture)
        except ValueError as reason:
            raise ValueError(f"{name}: model file {path!r} references the texture {texture!r}, which is not a "
                             f"complete image: {reason}") from None


UNLOADABLE_MODEL = "could not be loaded by Panda3D (not a model file, or a corrupt one)"


def _load_panda_model(path: str):
    """In the child process: the model file as a NodePath through Panda3D's loader (no model
    cache, errors reported), or None when Panda3D cannot load it."""
    from panda3d.core import Filename, Loader, LoaderOptions, NodePath

    options = LoaderOptions(LoaderOptions.LF_no_cache | LoaderOptions.LF_report_errors)
    node = Loader.get_global_ptr().load_sync(Filename.from_os_specific(path), options)
    return None if node is None else NodePath(node)


def _write_model_arrays(path: str, output: str) -> None:
    """In the child process: load `path` with Panda3D and save its triangles to `output` (.npz).

    The log names every texture just before Panda3D decodes it, so that the parent can say
    which one ended the process if one does."""
    from panda3d.core import loadPrcFileData

    loadPrcFileData("marl_render model child", "notify-level-gobj info")
    model = _load_panda_model(path)
    if model is None:
        np.savez(output, error=UNLOADABLE_MODEL)
        return
    parts = [_geom_arrays(geom, geom_node.get_net_transform().get_mat())
             for geom_node in model.find_all_matches("**/+GeomNode") for geom in geom_node.node().get_geoms()]
    parts = [part for part in parts if len(part[3])]
    if not parts:
        np.savez(output, error="contains no triangles")
        return
    offsets = np.cumsum([0] + [len(part[0]) for part in parts[:-1]])
    positions, normals, uvs = (np.concatenate([part[k] for part in parts]) for k in range(3))
    triangles = np.concatenate([part[3] + offset for part, offset in zip(parts, offsets, strict=True)])
    np.savez(output, positions=positions, normals=normals, uvs=uvs, triangles=triangles)


def _write_skin_arrays(path: str, output: str) -> None:
    """In the child process: the triangles and the skin of a skinned model (.gltf/.glb through
    panda3d-gltf, .egg/.bam characters through Panda3D) saved to `output` (.npz).

    The joints are those the vertices follow plus the joints between them (parents before
    children); pivots are the joints' bind-pose positions in the model's frame. Geometry
    without skin follows an extra root joint "(model)" at the origin."""
    from panda3d.core import GeomVertexReader, InternalName, LMatrix4f, NodePath

    if path.lower().endswith((".gltf", ".glb")):
        try:
            import gltf
        except ImportError:
            np.savez(output, error="is a glTF file, and skinned glTF needs the panda3d-gltf package "
                                   "(pip install 'marl-render[gltf]')")
            return
        model = NodePath(gltf.load_model(path))
    else:
        model = _load_panda_model(path)
        if model is None:
            np.savez(output, error=UNLOADABLE_MODEL)
            return
    parts, joints, skin_matrix = [], {}, None  # joints: pointer -> CharacterJoint
    for geom_node in model.find_all_matches("**/+GeomNode"):
        matrix = geom_node.get_net_transform().get_mat()
        for geom in geom_node.node().get_geoms():
            vertex_data = geom.get_vertex_data()
            table = vertex_data.get_transform_blend_table()
            influences = []  # per vertex: [(joint pointer, weight)]
            if table is not None:
                if skin_matrix is not None and not skin_matrix.almost_equal(matrix):
                    np.savez(output, error="has skinned meshes under different node transforms (not supported)")
                    return
                skin_matrix = LMatrix4f(matrix)
                reader = GeomVertexReader(vertex_data, InternalName.get_transform_blend())
                blends = []
                for index in range(table.get_num_blends()):
                    blend = table.get_blend(index)
                    pairs = []
                    for k in range(blend.get_num_transforms()):
                        transform = blend.get_transform(k)
                        if type(transform).__name__ != "JointVertexTransform":
                            continue  # not a joint (a character without a skeleton has user transforms)
                        joint = transform.get_joint()
                        joints[joint.this] = joint
                        pairs.append((joint.this, blend.get_weight(k)))
                    blends.append(pairs)
                influences = [blends[reader.get_data1i()] for _ in range(vertex_data.get_num_rows())]
            arrays = _geom_arrays(geom, matrix)
            if len(arrays[3]):
                parts.append((*arrays, influences))
    if not parts:
        np.savez(output, error="contains no triangles")
        return
    if not joints:
        np.savez(output, error="has no skin (no vertex follows a joint); load it with load_model")
        return
    # Parents from the joints' children, then every joint below the followed ones, roots first.
    parent = {}
    pending = list(joints.values())
    while pending:
        joint = pending.pop()
        for child in joint.get_children():
            if type(child).__name__ == "CharacterJoint":
                parent[child.this] = joint.this
                if child.this not in joints:
                    joints[child.this] = child
                    pending.append(child)
    order, frontier = [], [key for key in joints if key not in parent]
    while frontier:
        order += frontier
        frontier = [key for key in joints if parent.get(key) in frontier]
    index = {key: k for k, key in enumerate(order)}
    model_joint = len(order)  # the extra root of vertices that follow no joint, if there are any
    skin_joints, skin_weights = [], []
    for part in parts:
        count = len(part[0])
        part_joints = np.full((count, 4), model_joint, np.int64)
        part_weights = np.zeros((count, 4))
        for row, pairs in enumerate(part[4]):
            heaviest = sorted(pairs, key=lambda pair: -pair[1])[:4]  # at most four influences
            for k, (key, weight) in enumerate(heaviest):
                part_joints[row, k], part_weights[row, k] = index[key], weight
        total = part_weights.sum(1, keepdims=True)
        part_weights = np.divide(part_weights, total, out=np.zeros_like(part_weights), where=total > 0)
        part_joints[total[:, 0] <= 0] = model_joint
        part_weights[total[:, 0] <= 0, 0] = 1.0
        skin_joints.append(part_joints)
        skin_weights.append(part_weights)
    skin_joints, skin_weights = np.concatenate(skin_joints), np.concatenate(skin_weights)
    unskinned = bool(((skin_joints == model_joint) & (skin_weights > 0)).any())
    names, seen = [], set()
    for key in order:
        label = joints[key].get_name() or "joint"
        while label in seen:  # joint names must be distinct
            label += "'"
        seen.add(label)
        names.append(label)
    pivots = []
    for key in order:
        net = LMatrix4f()
        joints[key].get_net_transform(net)
        pivots.append(tuple(skin_matrix.xform_point(net.get_row3(3))))
    parents = [index.get(parent.get(key), -1) for key in order]
    if unskinned:
        names.append("(model)")
        pivots.append((0.0, 0.0, 0.0))
        parents.append(-1)
    else:  # unused slots (weight 0) must still name a joint
        skin_joints[skin_joints == model_joint] = 0
    offsets = np.cumsum([0] + [len(part[0]) for part in parts[:-1]])
    positions, normals, uvs = (np.concatenate([part[k] for part in parts]) for k in range(3))
    triangles = np.concatenate([part[3] + offset for part, offset in zip(parts, offsets, strict=True)])
    np.savez(output, positions=positions, normals=normals, uvs=uvs, triangles=triangles,
             joint_names=np.array(names), parents=np.array(parents), pivots=np.array(pivots, dtype=np.float64),
             skin_joints=skin_joints, skin_weights=skin_weights)


def _geom_arrays(geom, matrix):
    """(positions, normals, uvs, triangles) of one Panda3D Geom, transformed by its node's
    net transform. Points and lines are left out: the renderer draws triangles."""
    from panda3d.core import Geom, GeomVertexFormat

    vertex_data = geom.get_vertex_data()
    has_normals = vertex_data.has_column("normal")
    rows = np.frombuffer(memoryview(vertex_data.convert_to(GeomVertexFormat.get_v3n3t2()).get_array(0)),
                         dtype=np.float32).reshape(-1, 8).astype(np.float64)
    triangles = []
    for primitive in geom.get_primitives():
        if primitive.get_primitive_type() != Geom.PT_polygons:
            continue
        primitive = primitive.decompose().make_copy()  # strips and fans -> triangles
        primitive.make_indexed()
        primitive.set_index_type(Geom.NT_uint32)
        triangles.append(np.frombuffer(memoryview(primitive.get_vertices()), dtype=np.uint32).reshape(-1, 3))
    triangles = np.concatenate(triangles).astype(np.int64) if triangles else np.zeros((0, 3), np.int64)
    # Panda3D multiplies row vectors: p' = p M. Normals take the inverse transpose.
    m = np.array(matrix, dtype=np.float64)
    positions = rows[:, :3] @ m[:3, :3] + m[3, :3]
    if np.linalg.det(m[:3, :3]) < 0:  # a mirroring transform turns faces inside out: restore the winding
        triangles = triangles[:, ::-1]
    if has_normals:
        normals = rows[:, 3:6] @ np.linalg.inv(m[:3, :3]).T
    else:
        normals = _vertex_normals(positions, triangles)
    lengths = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, lengths, out=np.zeros_like(normals), where=lengths > 0)
    return positions, normals, rows[:, 6:8], triangles


def _vertex_normals(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, for models that do not store any."""
    corners = positions[triangles]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(positions)
    for corner in range(3):
        np.add.at(normals, triangles[:, corner], face_normals)
    return normals
