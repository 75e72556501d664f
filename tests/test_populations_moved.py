"""The old import paths of the populations layer's modules (marl_render/aliases.py, MOVED): each
is the moved module itself, so imports, monkeypatches, pickles and ``python -m`` reach it."""
import importlib
import pickle
import subprocess
import sys

import pytest

import marl_render
from marl_render import aliases
from marl_render.populations import elo, heldout

POPULATIONS_MOVED = {old: new for old, new in aliases.MOVED.items()
                     if ".populations." in new or new.endswith("task_imports")}


@pytest.mark.parametrize("old", sorted(POPULATIONS_MOVED))
def test_an_old_path_is_the_moved_module_itself(old):
    module = importlib.import_module(old)
    assert module is importlib.import_module(POPULATIONS_MOVED[old]) and sys.modules[old] is module
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


def test_a_pickle_that_names_the_old_module_loads_as_the_moved_object():
    written = pickle.dumps(elo.elo_ratings, protocol=0)  # protocol 0 names a function by module and name, as text
    assert b"marl_render.populations.elo\nelo_ratings" in written
    assert pickle.loads(written.replace(b"marl_render.populations.elo\n", b"marl_render.elo\n")) is elo.elo_ratings
    scenario = heldout.heldout_scenario("tag/prey_vs_interceptors")  # its class is the envs layer's (envs/bots.py)
    before_the_move = pickle.dumps(scenario, protocol=0).replace(b"marl_render.envs.bots\n", b"marl_render.heldout\n")
    assert b"marl_render.heldout\nHeldOutScenario" in before_the_move and pickle.loads(before_the_move) == scenario


def test_make_env_of_a_held_out_scenario_imports_no_layer_above_the_envs():
    """make_env(heldout=...) once imported marl_render.heldout, its bots and policies, and through them
    the whole trainer package (marl_render.baselines): the envs layer now resolves it alone."""
    code = ("import sys\nfrom marl_render.envs import make_env\n"
            "make_env('spread', heldout='spread/two_with_wanderer', num_worlds=1, resolution=8).close()\n"
            "print(sorted(m for m in sys.modules if m.startswith(('marl_render.populations', 'marl_render.baselines',"
            " 'marl_render.bots', 'marl_render.heldout', 'marl_render.policies'))))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_python_m_of_the_old_path_runs_the_moved_command():
    done = subprocess.run([sys.executable, "-m", "marl_render.evaluate", "--list"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert "tag/prey_vs_interceptors  [visitor]  focal prey_0  background predator: interceptor, lazy_predator" \
        in done.stdout.splitlines()
