"""`python -m marl_render.bench env --api ...`: every front end steps the same env in one run."""
import json
import subprocess
import sys

import pytest


def test_bench_env_compares_every_front_end_in_one_run():
    pytest.importorskip("jax")
    pytest.importorskip("stable_baselines3")
    out = subprocess.run([sys.executable, "-m", "marl_render.bench", "env", "--env", "cartpole", "--worlds", "4",
                          "--resolution", "16", "--steps", "3", "--api", "core", "vec", "sb3", "jax", "--json"],
                         capture_output=True, text=True, timeout=300, check=True).stdout
    report = json.loads(out.strip().splitlines()[-1])
    assert report["benchmark"] == "env"
    rows = report["results"]
    assert [row["api"] for row in rows] == ["core", "vec", "sb3", "jax"]
    for row in rows:
        assert row["env"] == "cartpole" and row["worlds"] == 4 and row["resolution"] == 16
        assert row["env_steps_per_s"] > 0 and 0 <= row["front_end_share"] < 1
    assert rows[0]["ratio_to_core"] == 1.0
    assert all(row["ratio_to_core"] > 0 for row in rows[1:])


def test_bench_env_rejects_an_unknown_front_end():
    result = subprocess.run([sys.executable, "-m", "marl_render.bench", "env", "--api", "gym"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and "invalid choice: 'gym'" in result.stderr


def test_bench_env_measures_every_world_and_agent_count():
    # --worlds and --agents take several values: one row per (worlds, agents) pair.
    out = subprocess.run([sys.executable, "-m", "marl_render.bench", "env", "--env", "capture_flag", "--worlds", "1",
                          "2", "--agents", "4", "6", "--resolution", "8", "--steps", "1", "--json"],
                         capture_output=True, text=True, timeout=120, check=True).stdout
    rows = json.loads(out.strip().splitlines()[-1])["results"]
    assert [(row["worlds"], row["agents"]) for row in rows] == [(1, 4), (1, 6), (2, 4), (2, 6)]
    assert all(row["agent_frames_per_s"] == pytest.approx(row["env_steps_per_s"] * row["agents"]) for row in rows)
