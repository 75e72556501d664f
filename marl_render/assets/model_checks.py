"""Checks of a model file before its parser runs, for the files that would hang it.

Panda3D's parsers run in a child process (meshes.py), which the parent ends after a timeout.
Some files would make it spin until then: a glTF whose node hierarchy has a cycle, an .egg that
references a special file (``<File> { /dev/zero }``), an OBJ face with a huge number of corners
(its triangulator is quadratic: 10,000 corners take seconds, 200,000 take half an hour). They are
refused here in well under a second, naming the file and what is wrong. The checks read the
file's text (or a .glb's JSON chunk) only; anything they do not understand is left to the parser.
"""
from __future__ import annotations

import json
import os
import re
import stat
import struct

MAX_FACE_CORNERS = 10_000  # an OBJ face with more would keep the parser busy for many seconds
TEXT_LIMIT = 64 * 2 ** 20  # text formats are scanned up to this size (a larger file is left to the timeout)


def check_model_file(name: str, path: str, *, skinned: bool = False) -> None:
    """Raise ValueError naming `name` and the file for the cases of the module docstring; with
    `skinned`, also for glTF skins that panda3d-gltf would load wrong (see _check_gltf_skin)."""
    extension = os.path.splitext(path)[1].lower()
    document = _read_json(path) if extension == ".gltf" else _glb_json(path) if extension == ".glb" else None
    if document is not None:
        _check_gltf(name, path, document)
        if skinned:
            _check_gltf_skin(name, path, document)
    if extension == ".egg":
        _check_egg(name, path)
    elif extension == ".obj":
        _check_obj(name, path)


def _read_json(path: str):
    try:
        with open(path, encoding="utf-8") as f:
            return json.loads(f.read(TEXT_LIMIT))
    except (OSError, ValueError):
        return None  # not JSON, or too large: the parser reports it


def _glb_json(path: str):
    """The JSON chunk of a binary glTF, or None."""
    try:
        with open(path, "rb") as f:
            header = f.read(20)
            if len(header) < 20 or header[:4] != b"glTF":
                return None
            length, kind = struct.unpack("<II", header[12:20])
            if kind != 0x4E4F534A or length > TEXT_LIMIT:  # "JSON"
                return None
            return json.loads(f.read(length).decode("utf-8"))
    except (OSError, ValueError, UnicodeDecodeError):
        return None


def _check_gltf(name: str, path: str, document) -> None:
    """A node hierarchy with a cycle (j2 -> j1 -> j2, a node its own child) is refused."""
    if not isinstance(document, dict) or not isinstance(document.get("nodes"), list):
        return
    children = {}
    for index, node in enumerate(document["nodes"]):
        kids = node.get("children", []) if isinstance(node, dict) else []
        children[index] = [k for k in kids if isinstance(k, int)] if isinstance(kids, list) else []
    state = dict.fromkeys(children, 0)  # 0 unseen, 1 on the current path, 2 done
    for start in children:
        if state[start]:
            continue
        path_nodes, stack = [], [(start, iter(children[start]))]
        state[start] = 1
        path_nodes.append(start)
        while stack:
            node, kids = stack[-1]
            child = next(kids, None)
            if child is None:
                state[node] = 2
                stack.pop()
                path_nodes.pop()
                continue
            if child not in state:
                continue  # an index out of range: the parser's to report
            if state[child] == 1:
                cycle = path_nodes[path_nodes.index(child):] + [child]
                names = " -> ".join(_node_name(document["nodes"][i], i) for i in cycle)
                raise ValueError(f"{name}: model file {path!r} has a cycle in its node hierarchy ({names}); "
                                 "a glTF scene must be a tree")
            if state[child] == 0:
                state[child] = 1
                path_nodes.append(child)
                stack.append((child, iter(children[child])))


def _check_gltf_skin(name: str, path: str, document) -> None:
    """More than 4 influences per vertex (JOINTS_1 / WEIGHTS_1): panda3d-gltf 1.3 binds every vertex
    to joint 0 with weight 1 ("Column transform_index repeated in format"), so the file is refused."""
    for mesh in document.get("meshes", []) if isinstance(document.get("meshes"), list) else []:
        for primitive in mesh.get("primitives", []) if isinstance(mesh, dict) else []:
            attributes = primitive.get("attributes", {}) if isinstance(primitive, dict) else {}
            extra = sorted(key for key in attributes if key.startswith(("JOINTS_", "WEIGHTS_")) and key[-2:] != "_0")
            if extra:
                raise ValueError(f"{name}: model file {path!r} gives vertices more than 4 joint influences ({extra}), "
                                 "which panda3d-gltf cannot load right (every vertex would follow joint 0); "
                                 "export at most 4 influences per vertex (the 4 heaviest, renormalised)")


def _node_name(node, index: int) -> str:
    label = node.get("name") if isinstance(node, dict) else None
    return f"node {index} ({label!r})" if isinstance(label, str) else f"node {index}"


_EGG_FILE = re.compile(r"<(?:File|Texture)>\s*(?:[^{\s]*\s*)?\{\s*\"?([^\"}]+?)\"?\s*(?:<|\})", re.S)


def _check_egg(name: str, path: str) -> None:
    """Files an .egg references (<File>, <Texture>) that exist but are not regular files are refused:
    reading /dev/zero never ends."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read(TEXT_LIMIT)
    except OSError:
        return
    folder = os.path.dirname(path)
    for reference in _EGG_FILE.findall(text):
        target = os.path.join(folder, reference.strip())
        try:
            mode = os.stat(target).st_mode
        except (OSError, ValueError):
            continue  # missing references are the parser's (Panda3D skips missing textures)
        if not stat.S_ISREG(mode):
            raise ValueError(f"{name}: model file {path!r} references {reference.strip()!r}, which is not a regular "
                             "file (a device, pipe or folder); refused before parsing")


def _check_obj(name: str, path: str) -> None:
    """An OBJ face with more than MAX_FACE_CORNERS corners is refused."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            read = 0
            for number, line in enumerate(f, 1):
                read += len(line)
                if read > TEXT_LIMIT:
                    return
                if line.startswith("f ") or line.startswith("f\t"):
                    corners = len(line.split()) - 1
                    if corners > MAX_FACE_CORNERS:
                        raise ValueError(f"{name}: model file {path!r} has a face with {corners} corners on line "
                                         f"{number} (at most {MAX_FACE_CORNERS}: Panda3D's triangulator would take "
                                         "minutes); split it into smaller faces")
    except OSError:
        return
