"""Runs a PyBatchRender script with the `cuda.cudart` its GPU frame grabber imports.

    python pbr_run.py SCRIPT [ARGS...]

PyBatchRender's GPU path (pybatchrender/renderer/frame_grabber.py) does `from cuda import cudart`,
`import cupy` and `from OpenGL.GL import GL_TEXTURE_2D`. cuda-bindings 13 removed the `cuda.cudart`
module; its runtime bindings, with the same functions and enums, are `cuda.bindings.runtime`. This
launcher makes `cuda.cudart` that module (an alias: the lent machine's cuda-bindings 13 stays the one
in use, where a 12.x cuda-python wheel would bring a second set of bindings of its own), prints what it
found, and runs SCRIPT as __main__. PyOpenGL comes from the kit's wheels.

Issue 43 names cuda-bindings >= 13.0.3 for this alias; an older one is named as such in the output,
and the run goes on (the grabber PyBatchRender prints then says whether its GPU path came up).
"""
from __future__ import annotations

import importlib
import importlib.metadata
import runpy
import sys

MINIMUM_BINDINGS = (13, 0, 3)


def install_cudart_alias() -> str:
    """Make `from cuda import cudart` give cuda.bindings.runtime (when cuda.cudart is missing); returns
    a line saying what was done."""
    try:
        from cuda import cudart  # noqa: F401  (a cuda-python 12.x has its own)

        return "cuda.cudart: the installed module"
    except ImportError:
        pass
    try:
        runtime = importlib.import_module("cuda.bindings.runtime")
    except ImportError as error:
        return f"cuda.cudart: no alias made (cuda.bindings.runtime does not import: {error})"
    import cuda

    sys.modules["cuda.cudart"] = runtime
    cuda.cudart = runtime
    try:
        version = importlib.metadata.version("cuda-bindings")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    parts = tuple(int(p) for p in version.split(".")[:3] if p.isdigit()) if version != "unknown" else ()
    old = f" (older than {'.'.join(map(str, MINIMUM_BINDINGS))})" if parts and parts < MINIMUM_BINDINGS else ""
    return f"cuda.cudart: alias of cuda.bindings.runtime, cuda-bindings {version}{old}"


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    print(f"[pbr_run] {install_cudart_alias()}", flush=True)
    script, sys.argv = argv[0], argv
    runpy.run_path(script, run_name="__main__")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
