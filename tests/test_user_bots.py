"""A user's bots and held-out scenarios (register_bot, register_heldout) through every command line:
the evaluation and its cross-play table and heatmap, the reference returns' CLI with --import and
module:Class."""
from __future__ import annotations

import json
import sys
import textwrap

import pytest
import torch

from marl_render import bots, heldout
from marl_render import evaluate as evaluation
from marl_render.bots import bot_names, make_bot, register_bot
from marl_render.envs import evaluation as references
from marl_render.envs import make_env
from marl_render.heldout import HeldOutScenario, list_heldout, register_heldout
from marl_render.policies import ScriptedPolicy

MODULE = textwrap.dedent('''
    """A user's bots and held-out scenario for beacon_duel (tests/selfplay_user_task.py)."""
    import torch

    from marl_render.bots import register_bot
    from marl_render.heldout import HeldOutScenario, register_heldout
    from marl_render.policies import ScriptedPolicy

    import selfplay_user_task  # noqa: F401 (registers beacon_duel)


    def stay(env):
        """stands still"""
        return torch.zeros(env.num_worlds, env.num_agents, dtype=torch.int64)


    register_bot("beacon_duel", "stayer", stay)
    register_bot("beacon_duel", "rusher", factory=lambda seed: ScriptedPolicy(
        "rusher", lambda env: env.heuristic_actions()), description="runs to the beacon")
    register_heldout(HeldOutScenario("beacon_duel/red_vs_stayers", "beacon_duel", "a focal red scout against a "
                                     "blue one that stays or rushes", 2, ("red_0",), {"blue": ("stayer", "rusher")}))
''')


@pytest.fixture
def user_bots(registries, tmp_path, monkeypatch):
    """A module `user_bots` beside tests/selfplay_user_task.py that registers bots and a scenario."""
    (tmp_path / "user_bots.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.syspath_prepend(str(__import__("pathlib").Path(__file__).parent))
    monkeypatch.delitem(sys.modules, "user_bots", raising=False)
    yield "user_bots"
    sys.modules.pop("user_bots", None)


def test_a_registered_bot_plays_and_a_registered_scenario_builds_its_focal_env(user_bots):
    __import__(user_bots)
    assert bot_names("beacon_duel") == ["heuristic", "stayer", "rusher"]
    assert list_heldout("beacon_duel") == ["beacon_duel/red_vs_stayers"]
    with make_env("beacon_duel", heldout="beacon_duel/red_vs_stayers", num_worlds=2, resolution=8) as env:
        obs = env.reset(seed=0)
        assert obs["pixels"].shape == (2, 1, 8, 8, 3)
        env.step(torch.zeros(2, 1, dtype=torch.int64))
        assert sorted({name for row in env.sampled_bots() for name in row}) <= ["rusher", "stayer"]
    assert isinstance(make_bot("beacon_duel", "rusher", 3), ScriptedPolicy)
    assert bots.describe_bot("beacon_duel", "stayer") == "stands still"


def test_registration_refuses_what_it_could_not_play(registries):
    import selfplay_user_task  # noqa: F401

    stay = lambda env: torch.zeros(env.num_worlds, env.num_agents, dtype=torch.int64)  # noqa: E731
    with pytest.raises(ValueError, match="task must be a registered task"):
        register_bot("no_such_task", "x", stay)
    with pytest.raises(ValueError, match="needs a script or a factory"):
        register_bot("tag", "x")
    with pytest.raises(ValueError, match="in tag's train population"):
        register_bot("tag", "noisy0.2", population="test")
    with pytest.raises(ValueError, match="already registered"):
        register_bot("tag", "interceptor", stay)
    with pytest.raises(TypeError, match="script of bot 'x' must be callable"):
        register_bot("tag", "x", 3)
    register_bot("tag", "stayer", stay)
    with pytest.raises(ValueError, match=r"bots_by_role must name bots of tag's test population"):
        register_heldout(HeldOutScenario("tag/x", "tag", "d", 4, ("prey_0",), {"predator": ("heuristic",)}))
    with pytest.raises(ValueError, match=r"focal must name agents among"):
        register_heldout(HeldOutScenario("tag/x", "tag", "d", 4, ("prey_7",), {"predator": ("stayer",)}))
    with pytest.raises(ValueError, match=r"roles must be teams among"):
        register_heldout(HeldOutScenario("tag/x", "tag", "d", 4, ("prey_0",), {"hunters": ("stayer",)}))
    with pytest.raises(ValueError, match="already registered"):
        register_heldout(heldout.HELDOUT["tag/prey_vs_interceptors"])
    assert "tag/x" not in heldout.HELDOUT and "tag/x" not in list_heldout()


def test_every_cli_takes_a_users_bots_and_scenarios(user_bots, tmp_path, capsys):
    assert evaluation.main(["--import", user_bots, "--list"]) == 0
    assert "beacon_duel/red_vs_stayers  [visitor]" in capsys.readouterr().out
    assert evaluation.main(["--import", user_bots, "--policy", "random", "--scenario", "beacon_duel",
                            "--episodes", "2"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [row["scenario"] for row in rows] == ["beacon_duel/red_vs_stayers"]
    out = tmp_path / "cp" / "duel"
    assert evaluation.main(["--import", user_bots, "--crossplay", "beacon_duel", "--roster", "random", "heuristic",
                            "stayer", "rusher", "--crossplay-episodes", "2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    result = json.loads(out.with_suffix(".json").read_text())
    assert result["policies"] == ["random", "heuristic", "stayer", "rusher"]
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = out.with_suffix(".md").read_text()
    assert table in printed and "Win rate of the row policy" in table and "| stayer |" in table
    assert "![beacon_duel cross-play](duel.png)" in table


def test_the_reference_returns_cli_takes_import_and_module_class(user_bots, capsys):
    assert references.main(["--import", user_bots, "--env", "beacon_duel", "--episodes", "2", "--json"]) == 0
    assert set(json.loads(capsys.readouterr().out)) == {"beacon_duel"}
    assert references.main(["--env", "selfplay_user_task:BeaconDuel", "--episodes", "2", "--json"]) == 0
    assert set(json.loads(capsys.readouterr().out)) == {"selfplay_user_task:BeaconDuel"}
    with pytest.raises(SystemExit):
        references.main(["--import", "no_such_module_here", "--env", "tag"])
    assert "--import no_such_module_here: the module did not import" in capsys.readouterr().err
