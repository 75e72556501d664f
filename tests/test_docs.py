"""The docs site (docs/conf.py, `make docs`) and its generated task cards (examples/make_env_docs.py).

The site builds: Sphinx reads every page and every public
docstring (autodoc), resolves every reference (nitpicky) and fails on any warning, as `make docs`
does. The test uses Sphinx's dummy builder, which does all of that but write HTML (18 against 24
CPU-seconds of the full build here); the HTML writer itself is Sphinx's and furo's own code."""
import dataclasses
import importlib.util
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from marl_render.baselines import social
from marl_render.envs import ArenaScenario, list_envs, make_env, numbered, register_env, registry

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def build(tmp_path: Path, source: Path = DOCS) -> int:
    build_main = pytest.importorskip("sphinx.cmd.build", reason="the docs extra: pip install '.[docs]'").build_main
    return build_main(["-b", "dummy", "-n", "-W", "--keep-going", "-q", "-E", "-d", str(tmp_path / "doctrees"),
                       str(source), str(tmp_path / "out")])


@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::PendingDeprecationWarning")  # myst on Sphinx 9
def test_the_site_builds_without_a_warning(tmp_path, capsys):
    code = build(tmp_path)
    assert code == 0, capsys.readouterr().err[-5000:]
    # api.md's automodule :members: lists are what it documents: no module internals beside them.
    api = (tmp_path / "doctrees" / "api.doctree").read_bytes()
    for internal in (b"marl_render.evaluate.HelpFormatter", b"marl_render.evaluate.main", b"marl_render.evaluate.write",
                     b"marl_render.envs.evaluation.main", b"marl_render.envs.evaluation.HelpFormatter"):
        assert internal not in api, internal
    for public in (b"marl_render.policies.as_policy", b"marl_render.generalise.generalise",
                   b"marl_render.bots.register_bot", b"marl_render.heldout.register_heldout", b"marl_render.sphere"):
        assert public in api, public


# ---------------------------------------------------------------------------------- task cards
def test_every_task_card_has_a_short_gif_of_its_heuristic():
    """docs/envs/NAME.gif (examples/make_env_docs.py): at most 300 KB, several frames, the first two agents'
    views (2x) beside an overview as high as them."""
    for name in list_envs():
        path = DOCS / "envs" / f"{name}.gif"
        assert path.is_file() and path.stat().st_size <= 300_000, (path, path.stat().st_size if path.exists() else 0)
        with make_env(name, num_worlds=1) as env:
            height = 2 * min(2, env.num_agents) * env.resolution[0]
        with Image.open(path) as gif:
            assert gif.format == "GIF" and gif.n_frames >= 2
            assert gif.size == (2 * env.resolution[1] + height, height), (name, gif.size)
            gif.seek(gif.n_frames - 1)
            assert np.asarray(gif.convert("RGB")).std() > 10


NUMBERS = {9: "Nine", 10: "Ten", 11: "Eleven", 12: "Twelve", 13: "Thirteen", 14: "Fourteen", 15: "Fifteen"}


def test_the_readme_and_the_landing_page_count_the_tasks_list_envs_has():
    """README.md's "N tasks" and docs/index.md's follow list_envs(), and README's gallery shows every task."""
    count = NUMBERS[len(list_envs())]
    readme = (ROOT / "README.md").read_text()
    assert f"{count} tasks, each with a card" in readme
    assert f"{count} tasks, a card each" in (DOCS / "index.md").read_text()
    gallery = readme.split("## Tasks")[1].split("## ")[0]
    assert sorted(set(re.findall(r"\]\(docs/envs/(\w+)\.md\)", gallery))) == sorted(list_envs())


def test_every_mixed_motive_card_shows_its_social_outcomes_and_episode_end():
    """The cards (examples/make_env_docs.py) say each task's default episode end; a mixed-motive task's card
    shows the social outcomes of random and the heuristic of docs/reference_returns.json, and beside MAPPO's
    on the publication worlds (marl_render.baselines.social)."""
    make_env_docs = load_make_env_docs()
    reference = json.loads((DOCS / "reference_returns.json").read_text())
    results = (DOCS / "results.md").read_text()
    mixed = [name for name in list_envs() if registry.env_class(name).mixed_motive]
    assert {"commons", "capture_flag", "clean_up", "coop_mining", "matrix"} <= set(mixed)
    for name in list_envs():
        card = (DOCS / "envs" / f"{name}.md").read_text()
        assert f"| **episode end (default)** | {registry.env_class(name).episode_end_description()} " in card
        assert ("### Social outcomes" in card) == (name in mixed), name
    for name in mixed:
        card = (DOCS / "envs" / f"{name}.md").read_text()
        for policy in ("random", "heuristic"):
            cells = " | ".join(make_env_docs.outcome(reference[name][policy][f"{key}_mean"])
                               for key in ("efficiency", "equality", "sustainability", "peace"))
            assert f"| {policy} | {cells} |" in card, (name, policy)
            assert f"| {name} | {policy} | {cells} |" in results, (name, policy)  # docs/results.md's table
        for row in social.task_rows(name, DOCS / "baselines"):  # beside MAPPO, on the publication worlds
            assert "| " + " | ".join(row) + " |" in card, (name, row)
            assert f"| {name} | " + " | ".join(row) + " |" in results, (name, row)


def test_the_schelling_diagrams_are_committed_and_shown_on_their_cards():
    """clean_up's and matrix's Schelling diagrams (python -m marl_render.baselines.schelling): the JSON and
    PNG under docs/schelling/, their numbers on the cards and their verdicts the numbers' own."""
    for name in ("clean_up", "matrix"):
        assert registry.env_class(name).schelling
        result = json.loads((DOCS / "schelling" / f"{name}.json").read_text())
        assert result["task"] == name and len(result["cooperator"]) == len(result["defector"]) == result["num_agents"]
        assert result["defecting_pays_the_individual"] == all(
            d > c for c, d in zip(result["cooperator"], result["defector"], strict=True))
        assert result["cooperating_pays_the_group"] == (result["cooperator"][-1] > result["defector"][0])
        with Image.open(DOCS / "schelling" / f"{name}.png") as picture:
            assert picture.format == "PNG" and np.asarray(picture.convert("RGB")).std() > 10
        card = (DOCS / "envs" / f"{name}.md").read_text()
        assert f"](../schelling/{name}.png)" in card
        assert "| " + " | ".join(f"{v:.3g}" for v in result["cooperator"]) + " |" in card
        assert "| " + " | ".join(f"{v:.3g}" for v in result["defector"]) + " |" in card
        assert f"](schelling/{name}.png)" in (DOCS / "results.md").read_text()


@dataclasses.dataclass(frozen=True)
class HoldParams:
    radius: float = 0.5  # how near the centre counts as holding it (m)
    bonus: float = 2.0


class Hold(ArenaScenario):
    """Hold the centre: a tiny task of this test's own, registered as a user would."""

    name = "hold_centre_card"
    Params = HoldParams
    default_num_agents, default_max_steps, default_resolution = 2, 4, 8
    physics_terms = frozenset({"walls", "drag"})

    def setup(self):
        self.setup_arena({"agents": numbered("agent", self.num_agents)}, state_dim=6, radius=0.15, max_speed=2.0)

    def initial_state(self):
        return self.at_rest(torch.zeros(self.num_worlds, self.num_agents, 2), torch.zeros(self.num_worlds,
                                                                                          self.num_agents))

    def spawn(self, generator):
        W, A = self.num_worlds, self.num_agents
        return self.at_rest(torch.rand(W, A, 2, generator=generator) * 2 - 1, torch.zeros(W, A))

    def rules(self, before, moved, actions, alive, generator):
        near = moved.pos[:, :self.num_agents].norm(dim=-1) < self.params.radius
        return moved, near.float() * self.params.bonus, torch.zeros_like(alive), {}

    def observation(self, state, alive):
        return self.own_obs(state)

    def heuristic(self, state, alive):
        return torch.ones(self.num_worlds, self.num_agents, dtype=torch.int64)  # forward


def load_make_env_docs():
    spec = importlib.util.spec_from_file_location("make_env_docs", ROOT / "examples" / "make_env_docs.py")
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(ROOT / "examples"))  # it imports record_video, as it does when run
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(ROOT / "examples"))
    return module


@pytest.fixture
def make_env_docs():
    module = load_make_env_docs()
    register_env(Hold.name, Hold)
    yield module
    registry._REGISTRY.pop(Hold.name, None)


def test_a_user_registered_task_gets_the_same_card(make_env_docs, tmp_path):
    text = make_env_docs.card(Hold.name, None, str(tmp_path))
    assert text.startswith(f"# {Hold.name}\n") and "\nHold the centre: a tiny task of this test's own" in text
    assert "| `radius` | `0.5` | how near the centre counts as holding it (m) |" in text
    assert "| `bonus` | `2.0` |  |" in text  # no comment: a blank meaning, not an error
    assert "| **agents (default)** | 2 (`num_agents` 1 to 64) |" in text and "| **max_steps** | 4 |" in text
    assert "| `pixels` | [W, 2, 8, 8, 3] | uint8 |" in text and "| `state` | [W, 2, 6] | float32 |" in text
    assert f"Not measured yet: `python -m marl_render.envs.evaluation --env {Hold.name}`" in text
    assert f"Not measured: `python -m marl_render.bench env --env {Hold.name}" in text
    picture = np.asarray(Image.open(tmp_path / f"{Hold.name}.png").convert("RGB"))
    assert picture.shape[0] >= 256 and picture.std() > 10
    with Image.open(tmp_path / f"{Hold.name}.gif") as gif:  # frames 0..3 of the 4-step episode, one a step
        assert gif.n_frames == 4 and gif.size == (2 * 8 + 2 * 2 * 8, 2 * 2 * 8)
