"""The old import paths of the modules that moved into marl_render/populations/ (and of
task_imports, now envs/task_imports.py), issue 40: each old path is a one-line file that makes
itself the moved module (`become`), so imports, attribute reads, monkeypatches and pickles through
the old name reach the same module object, and ``python -m <old name>`` runs the moved module."""
from __future__ import annotations

import importlib
import runpy
import sys

MOVED = {  # old dotted name -> new dotted name: the one list of this move
    "marl_render.policies": "marl_render.populations.policies",
    "marl_render.bots": "marl_render.populations.bots",
    "marl_render.heldout": "marl_render.populations.heldout",
    "marl_render.evaluate": "marl_render.populations.evaluate",
    "marl_render.elo": "marl_render.populations.elo",
    "marl_render.play": "marl_render.populations.play",
    "marl_render.generalise": "marl_render.populations.generalise",
    "marl_render.task_imports": "marl_render.envs.task_imports",
    "marl_render.baselines.networks": "marl_render.populations.networks",
    "marl_render.baselines.stats": "marl_render.populations.stats",
}


def become(name: str, spec) -> None:
    """Called by the old path's file with its ``__name__`` and ``__spec__``: that name now is the
    moved module; run as ``python -m`` (name "__main__"), the moved module runs as __main__."""
    new = MOVED[spec.name]
    if name == "__main__":
        runpy.run_module(new, run_name="__main__", alter_sys=True)
        return
    sys.modules[name] = importlib.import_module(new)
