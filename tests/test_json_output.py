"""What the project writes as JSON is strict JSON: a value that is not a number is null, never a bare
NaN or Infinity token (JavaScript's JSON.parse and json.loads with parse_constant reject those)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from marl_render import evaluate as evaluation
from marl_render import strict_json
from marl_render.baselines import marl_eval

DOCS = Path(__file__).resolve().parent.parent / "docs"


def strict(text: str):
    def refuse(token):
        raise AssertionError(f"bare {token} token")
    return json.loads(text, parse_constant=refuse)


def test_every_json_file_under_docs_is_strict_json():
    files = sorted(DOCS.rglob("*.json"))
    assert len(files) > 100  # the published runs, held-out tables, cross-play matrices, ...
    for path in files:
        try:
            strict(path.read_text())
        except AssertionError as error:
            pytest.fail(f"{path.relative_to(DOCS.parent)}: {error}")


def test_the_published_held_out_tables_read_null_as_not_a_number():
    rows = strict((DOCS / "heldout" / "random.json").read_text())
    undefined = [row for row in rows if row["normalised_score"] is None]
    assert [row["scenario"] for row in undefined] == ["tag/pair_with_interceptor", "speaker_listener/deaf_listener"]
    page = evaluation.heldout_page({"random": undefined}, "command", "note")
    assert "| tag/pair_with_interceptor | " in page and " | n/a | " in page


def test_strict_json_writes_null_for_non_finite_values_and_refuses_bare_tokens():
    value = {"a": math.nan, "b": [1.5, -math.inf, np.float64("nan"), np.float32(2.0)], "c": (math.inf,), "d": "NaN"}
    text = strict_json.dumps(value)
    assert strict(text) == {"a": None, "b": [1.5, None, None, 2.0], "c": [None], "d": "NaN"}
    with pytest.raises(ValueError, match=r"not strict JSON: the bare token NaN"):
        strict_json.loads('{"a": NaN}')


def test_evaluate_prints_and_writes_null_where_the_normalised_score_is_undefined(tmp_path, capsys):
    # One step of spread: no focal reward can differ yet between random and the heuristic, so the
    # normalised score (score - random) / (heuristic - random) is undefined.
    argv = ["--policy", "random", "--scenario", "spread/one_among_nearest", "--episodes", "2", "--max-steps", "1",
            "--resolution", "8"]
    assert evaluation.main(argv) == 0
    printed = strict(capsys.readouterr().out)
    assert printed[0]["random_return"] == printed[0]["heuristic_return"]
    assert printed[0]["normalised_score"] is None
    assert evaluation.main([*argv, "--out", str(tmp_path / "rows")]) == 0
    assert strict((tmp_path / "rows.json").read_text())[0]["normalised_score"] is None


def test_marl_eval_json_writes_null_for_a_nan_checkpoint(tmp_path):
    result = {"env": "spread", "obs": "pixels", "seeds": {"train": 0}, "env_steps": 100,
              "evaluation": {"policy": {"mean": 1.0, "per_episode": [1.0, 1.0]}},
              "checkpoints": [{"env_steps": 50, "mean": math.nan, "per_episode": [math.nan, 2.0]}]}
    marl_eval.write({"spread": {"pixels": [result]}}, tmp_path / "marl_eval.json")
    data = strict((tmp_path / "marl_eval.json").read_text())
    assert data["marl_render"]["spread"]["mappo_pixels"]["seed_0"]["step_0"]["return"] == [None, 2.0]
