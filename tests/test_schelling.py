"""Schelling diagrams (marl_render/baselines/schelling.py)."""
from __future__ import annotations

import pytest

from marl_render.baselines.schelling import schelling


def test_a_diagram_has_a_cooperator_and_a_defector_payoff_per_count_of_other_cooperators():
    result = schelling("matrix", episodes=1, max_steps=40, num_agents=3)
    assert result["others_cooperating"] == [0, 1, 2] and result["bots"] == ["cooperator", "defector"]
    assert len(result["cooperator"]) == len(result["defector"]) == 3
    assert all(value >= 0 for value in result["cooperator"] + result["defector"])  # prisoner's dilemma payoffs
    assert isinstance(result["defecting_pays_the_individual"], bool)


def test_a_task_without_modes_is_refused():
    with pytest.raises(ValueError, match=r"spread declares no schelling = \(cooperator bot, defector bot\)"):
        schelling("spread")
