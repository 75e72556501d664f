"""The old import paths of the populations layer's modules (marl_render/populations/moved.py): each
is the moved module itself, so imports, monkeypatches, pickles and ``python -m`` reach it."""
import importlib
import pickle
import subprocess
import sys

import pytest

import marl_render
from marl_render.populations import heldout, moved


@pytest.mark.parametrize("old", sorted(moved.MOVED))
def test_an_old_path_is_the_moved_module_itself(old):
    module = importlib.import_module(old)
    assert module is importlib.import_module(moved.MOVED[old]) and sys.modules[old] is module
    parent, _, child = old.rpartition(".")
    assert getattr(importlib.import_module(parent), child) is module  # `marl_render.evaluate` as an attribute


def test_the_old_spellings_of_an_import_give_the_same_objects():
    from marl_render import evaluate as by_from_import
    from marl_render.bots import make_bot
    from marl_render.populations import bots, evaluate

    assert by_from_import is evaluate is marl_render.evaluate and make_bot is bots.make_bot


def test_a_monkeypatch_through_the_old_path_reaches_the_code_of_the_new_one(monkeypatch):
    monkeypatch.setattr("marl_render.heldout.list_heldout", lambda task=None: ["patched"])
    assert heldout.list_heldout() == ["patched"]


def test_a_pickle_that_names_the_old_module_loads_as_the_moved_class():
    scenario = heldout.heldout_scenario("tag/prey_vs_interceptors")
    written = pickle.dumps(scenario, protocol=0)  # protocol 0 names the class as text
    assert b"marl_render.populations.heldout\nHeldOutScenario" in written
    old = written.replace(b"marl_render.populations.heldout\n", b"marl_render.heldout\n")
    assert pickle.loads(old) == scenario and type(pickle.loads(old)) is heldout.HeldOutScenario


def test_python_m_of_the_old_path_runs_the_moved_command():
    done = subprocess.run([sys.executable, "-m", "marl_render.evaluate", "--list"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert "tag/prey_vs_interceptors  [visitor]  focal prey_0  background predator: interceptor, lazy_predator" \
        in done.stdout.splitlines()
