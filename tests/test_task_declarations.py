"""A task in one place (envs/roster.py): what a task class declares besides its rules (bots,
held-out scenarios, sides, card, training defaults) is what the populations layer, cross-play, the
trainer's defaults and the docs generator read; no central table repeats it."""
import importlib.util
import sys
from pathlib import Path

import pytest

from marl_render.baselines import settings
from marl_render.envs import env_class, register_env, registry
from marl_render.envs.arena import wander
from marl_render.envs.roster import Bot, Card, HeldOut, card_of
from marl_render.envs.spread import Spread
from marl_render.populations import bots, heldout, scores

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


class Declared(Spread):
    """Spread with every declaration of its own."""

    bots = {"circler": Bot("drives round a circle", script=wander), "noisy0.2": Bot.noisy(0.2, population="train")}
    heldout = (HeldOut("with_circler", "two focal agents with one that circles", 3, ("agent_0", "agent_1"),
                       {"agents": ("circler",)}),)
    card = Card(text="A paragraph of its own.", reward="the team's coverage", episode_end="at max_steps",
                continuous=("thrust", "turn"), info={"collisions": "pairs touching", "coverage": "summed distance"})
    training = {"frames": 3, "lr": 1e-3, "budget": {"pixels": 12_345, "state": 6_789}}
    difficulties = {}  # no presets: the card then needs no difficulty returns


@pytest.fixture
def declared(registries):
    register_env("declared_task", Declared)
    yield "declared_task"
    registry._REGISTRY.pop("declared_task", None)


def test_the_bots_and_scenarios_of_a_task_class_are_its_populations_and_held_out_scenarios(declared):
    assert bots.POPULATIONS[declared] == {"train": ("heuristic", "noisy0.2"), "test": ("circler",)}
    assert bots.describe_bot(declared, "circler") == "drives round a circle"
    assert heldout.list_heldout(declared) == ["declared_task/with_circler"]
    scenario = heldout.heldout_scenario("declared_task/with_circler")
    assert (scenario.task, scenario.focal, scenario.bots_by_role) == (declared, ("agent_0", "agent_1"),
                                                                      {"agents": ("circler",)})


def test_the_trainer_reads_a_task_classes_training_defaults_and_budget(declared):
    assert settings.step_budget(declared, "pixels") == 12_345 and settings.step_budget(declared, "state") == 6_789
    hp = settings.task_hyperparameters(declared, lr=2e-3)
    assert (hp.frames, hp.lr) == (3, 2e-3)  # the class's default, then the caller's override
    assert settings.step_budget("tag", "pixels") == 542_720 and settings.TASK_DEFAULTS["cartpole"]["resolution"] == 48
    assert "tag" not in settings.TASK_DEFAULTS and settings.step_budget("no_such_task", "pixels") == 500_000


def test_cross_play_takes_the_sides_a_task_class_declares(declared):
    class Sided(env_class("push")):
        sides = ("blue", "red")  # push's own are (red, blue)

    register_env("sided_push", Sided)
    try:
        result = scores.crossplay("sided_push", {"random": "random", "heuristic": "heuristic"}, episodes=2,
                                  resolution=8)
    finally:
        registry._REGISTRY.pop("sided_push", None)
    assert result["sides"] == ["blue", "red"]
    assert scores.crossplay("push", {"random": "random", "heuristic": "heuristic"}, episodes=2,
                            resolution=8)["sides"] == ["red", "blue"]


def test_the_docs_card_of_a_task_is_its_class_card(declared):
    spec = importlib.util.spec_from_file_location("make_env_docs", EXAMPLES / "make_env_docs.py")
    make_env_docs = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(EXAMPLES))  # make_env_docs imports record_video beside it
    try:
        spec.loader.exec_module(make_env_docs)
    finally:
        sys.path.remove(str(EXAMPLES))
    text = make_env_docs.card(declared, None, None)
    assert "A paragraph of its own." in text and "| **reward** | the team's coverage |" in text
    assert "| **episode end** | at max_steps |" in text and "| 0 | thrust |" in text
    assert "| `coverage` | [W] | float32 | summed distance |" in text
    assert card_of(Spread).reward.startswith("shared by all agents") and card_of(type("T", (Spread,), {
        "card": "prose only"})) == Card(text="prose only")
