"""Importing triton after the GL context exists must not crash the process.

Mesa's llvmpipe uses LLVM as a shared library (libLLVM-NN.so), and Mesa's loader opens
its driver with RTLD_GLOBAL, so once a GL context exists that LLVM's symbols are global.
triton (shipped with the CUDA builds of torch, imported by torch.compile and
torch._dynamo) carries its own LLVM inside _C/libtriton.so and exports its symbols.
When Python loads libtriton.so after the context, the dynamic linker binds libtriton's
calls to the global LLVM first, and libtriton's static initialisers register their
command-line options in Mesa's LLVM instead of their own: a segmentation fault in
llvm::StringMapImpl::LookupBucketFor under llvm::cl::Option::addArgument. Loaded
before the context, or opened with RTLD_DEEPBIND, libtriton binds to its own LLVM.

`install()` runs before the context is made. When triton is installed but not yet
imported, it adds an import finder that, on the first `import triton`, opens
libtriton.so with RTLD_DEEPBIND before Python does (Python then reuses the loaded
library) and removes itself. Nothing is loaded in processes that never import triton.
"""
from __future__ import annotations

import ctypes
import importlib.abc
import importlib.machinery
import logging
import os
import sys
import threading
from pathlib import Path

LOG = logging.getLogger("marl_render.gl")

_lock = threading.Lock()
_preloaded: list = []  # the opened library, kept for the life of the process


def libtriton_path() -> Path | None:
    """triton/_C/libtriton.so of the triton that `import triton` would find, without importing it."""
    spec = importlib.machinery.PathFinder.find_spec("triton")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]) / "_C" / "libtriton.so"
    return path if path.is_file() else None


class _PreloadTriton(importlib.abc.MetaPathFinder):
    """Opens libtriton.so with RTLD_DEEPBIND when `triton` is first imported; finds nothing itself."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname == "triton":
            _remove_finder()
            library = libtriton_path()
            if library is not None:
                try:
                    _preloaded.append(ctypes.CDLL(str(library), mode=os.RTLD_LOCAL | os.RTLD_NOW | os.RTLD_DEEPBIND))
                except OSError as error:  # the import goes on; it may then crash as described above
                    LOG.warning("could not preload %s with RTLD_DEEPBIND: %s", library, error)
        return None


def _remove_finder() -> None:
    with _lock:
        sys.meta_path[:] = [f for f in sys.meta_path if not isinstance(f, _PreloadTriton)]


def install() -> None:
    """Guard a later `import triton` (call before the GL context exists)."""
    if not hasattr(os, "RTLD_DEEPBIND") or "triton" in sys.modules or libtriton_path() is None:
        return  # not glibc, triton already loaded (safe), or not installed
    with _lock:
        if not any(isinstance(f, _PreloadTriton) for f in sys.meta_path):
            sys.meta_path.insert(0, _PreloadTriton())
