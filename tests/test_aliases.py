"""The old import paths of moved modules (marl_render/aliases.py): each is the moved module itself,
so imports, attribute reads, monkeypatches, pickles and `python -m` through the old name reach it."""
import importlib
import pickle
import runpy
import sys

import pytest

import marl_render as mr
from marl_render import aliases
from marl_render.render import packing, row_layouts, scene


@pytest.mark.parametrize("old", sorted(aliases.MOVED))
def test_an_old_path_is_the_moved_module_itself(old):
    new = aliases.MOVED[old]
    module = importlib.import_module(old)
    assert module is importlib.import_module(new) and sys.modules[old] is sys.modules[new]
    assert module.__name__ == new and module.__spec__.name == new  # the import left the module's own spec
    assert getattr(mr, old.removeprefix("marl_render.")) is module  # `marl_render.<old name>` as an attribute


def test_the_old_spellings_of_an_import_give_the_same_module():
    import marl_render.layout as by_dotted_path
    from marl_render import layout as by_from_import
    from marl_render.layout import INSTANCE

    assert by_dotted_path is by_from_import is row_layouts and INSTANCE is row_layouts.INSTANCE


def test_an_unknown_module_is_still_missing():
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("marl_render.no_such_module")
    with pytest.raises(AttributeError, match="no attribute 'no_such_module'"):
        mr.no_such_module  # noqa: B018


def test_a_monkeypatch_through_the_old_path_reaches_the_code_that_uses_the_new_one(monkeypatch):
    changed = row_layouts.RowLayout("INSTANCE", 4, dict(row_layouts.INSTANCE.fields))
    monkeypatch.setattr("marl_render.layout.INSTANCE", changed)
    assert packing.row_layouts.INSTANCE is changed  # what the packer reads when it is built
    monkeypatch.undo()
    assert packing.row_layouts.INSTANCE is not changed


def test_a_pickle_that_names_the_old_module_loads_as_the_moved_class():
    fog = scene.Fog(color=(0.25, 0.5, 0.75), density=0.125)
    written = pickle.dumps(fog, protocol=0)  # protocol 0 names the class as text: "marl_render.render.scene\nFog"
    assert b"marl_render.render.scene\nFog" in written
    before_the_move = written.replace(b"marl_render.render.scene\n", b"marl_render.scene\n")
    loaded = pickle.loads(before_the_move)
    assert type(loaded) is scene.Fog and loaded == fog
    assert pickle.loads(pickle.dumps(fog)) == fog


def test_python_m_of_an_old_path_runs_the_moved_module_as_main(monkeypatch, capsys):
    """`python -m marl_render.info` (docs/install.md) through runpy, as `-m` does: the code runs as
    __main__ with its relative imports relative to its new package. (A fresh process, as `-m` starts,
    has not imported the old name yet; tests/test_backend.py runs the real `python -m`.)"""
    monkeypatch.delitem(sys.modules, "marl_render.info", raising=False)
    monkeypatch.setattr(sys, "argv", ["marl_render.info", "--help"])
    with pytest.raises(SystemExit) as exit_:
        runpy.run_module("marl_render.info", run_name="__main__")
    assert exit_.value.code == 0 and "usage: python -m marl_render.info" in capsys.readouterr().out
    monkeypatch.delitem(sys.modules, "marl_render.info", raising=False)
    namespace = runpy.run_module("marl_render.info")  # not as __main__: defines main(), which imports relatively
    assert namespace["__package__"] == "marl_render.render"
    assert namespace["main"]([]) == 0 and "renderer" in capsys.readouterr().out


def test_one_line_moves_a_package_with_its_submodules(monkeypatch):
    """A moved package (one line in MOVED) takes its submodules along: the old dotted name of a
    submodule is the module at the new place, never a second copy."""
    monkeypatch.setitem(aliases.MOVED, "marl_render.old_render_folder", "marl_render.render")
    import marl_render.old_render_folder.row_layouts as submodule

    assert submodule is row_layouts
    assert importlib.import_module("marl_render.old_render_folder") is sys.modules["marl_render.render"]
    for name in ("marl_render.old_render_folder", "marl_render.old_render_folder.row_layouts"):
        del sys.modules[name]
    del mr.old_render_folder
