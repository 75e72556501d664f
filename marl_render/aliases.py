"""The old import paths of moved modules: each is the moved module itself, not a copy.

`import marl_render.layout` (or `from marl_render import renderer`, a pickle or checkpoint that
names `marl_render.scene.Scene`, `python -m marl_render.info`) finds the module at its new path
and hands out that same module object, so a monkeypatch through either name reaches the one
module. MOVED is the one table: old dotted name -> new dotted name, one line per moved module
or package (a package's submodules follow it: `marl_render.baselines.run` after a line for
`marl_render.baselines`). marl_render/__init__.py installs the finder before anything else.
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys

MOVED = {
    # util: small shared helpers every layer may import
    "marl_render.extras": "marl_render.util.extras",
    "marl_render.keyed_random": "marl_render.util.keyed_random",
    "marl_render.strict_json": "marl_render.util.strict_json",
    "marl_render.threads": "marl_render.util.threads",
    "marl_render.transforms": "marl_render.util.transforms",
    "marl_render.triton_guard": "marl_render.util.triton_guard",
    "marl_render.validation": "marl_render.util.validation",
    # assets: meshes, model files, skins, images
    "marl_render.images": "marl_render.assets.images",
    "marl_render.meshes": "marl_render.assets.meshes",
    "marl_render.model_checks": "marl_render.assets.model_checks",
    "marl_render.skinning": "marl_render.assets.skinning",
    # render: GL, frame maths, the shaders' Python side
    "marl_render.appearance": "marl_render.render.appearance",
    "marl_render.backend": "marl_render.render.backend",
    "marl_render.culling": "marl_render.render.culling",
    "marl_render.info": "marl_render.render.gl_report",
    "marl_render.interop": "marl_render.render.interop",
    "marl_render.layout": "marl_render.render.row_layouts",
    "marl_render.memory": "marl_render.render.memory",
    "marl_render.packing": "marl_render.render.packing",
    "marl_render.panda_buffers": "marl_render.render.panda_buffers",
    "marl_render.provoking": "marl_render.render.provoking",
    "marl_render.readback": "marl_render.render.readback",
    "marl_render.renderer": "marl_render.render.renderer",
    "marl_render.scene": "marl_render.render.scene",
    "marl_render.shaders": "marl_render.render.shaders",
    "marl_render.shadows": "marl_render.render.shadows",
    "marl_render.sky": "marl_render.render.sky",
    "marl_render.tiling": "marl_render.render.tiling",
    "marl_render.triangle_corners": "marl_render.render.triangle_corners",
}


def resolve(name: str) -> str:
    """The module's path now: `name` itself unless it, or a package above it, moved."""
    head, tail = name, ""
    while head:
        if head in MOVED:
            return MOVED[head] + tail
        head, dot, last = head.rpartition(".")
        tail = dot + last + tail
    return name


class _Spec(importlib.machinery.ModuleSpec):
    """The old name's spec. Its `parent` is the new one's: `python -m <old name>` runs the module's
    code under it, and the code's relative imports are relative to where it lives now. A moved
    package keeps its search path (`python -m <old package>` runs its __main__)."""

    def __init__(self, name: str, real: importlib.machinery.ModuleSpec):
        super().__init__(name, _Loader(real.name), is_package=real.submodule_search_locations is not None)
        if self.submodule_search_locations is not None:
            self.submodule_search_locations = list(real.submodule_search_locations)
        self.target = real.name

    @property
    def parent(self) -> str:
        return self.target if self.submodule_search_locations is not None else self.target.rpartition(".")[0]


class _Loader(importlib.abc.Loader):
    def __init__(self, target: str):
        self.target = target
        self.real_spec = None

    def create_module(self, spec):
        module = importlib.import_module(self.target)  # the module itself, imported under its new name
        self.real_spec = module.__spec__
        return module

    def exec_module(self, module) -> None:
        # The import gave the module this alias's spec; it keeps its own (reload, runpy, pickle by reference).
        module.__spec__ = self.real_spec

    def get_code(self, name: str):  # runpy: `python -m <old name>` runs the module's code as __main__
        real = importlib.util.find_spec(self.target)
        return real.loader.get_code(self.target)


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if not name.startswith("marl_render."):
            return None
        new = resolve(name)
        if new == name:
            return None
        real = importlib.util.find_spec(new)
        return None if real is None else _Spec(name, real)


FINDER = _Finder()


def install() -> None:
    """Put the finder first on sys.meta_path (once): an old name never reaches the path finders."""
    if FINDER not in sys.meta_path:
        sys.meta_path.insert(0, FINDER)


def moved_attribute(package: str, name: str):
    """`package.name` for an old module name read as an attribute (`marl_render.shaders` after
    `import marl_render`); None when no module by that name moved."""
    old = f"{package}.{name}"
    return importlib.import_module(old) if resolve(old) != old else None
