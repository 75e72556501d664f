"""`python -m marl_render.bench peers`: its arithmetic and its worker protocol, without the peers' venvs."""
import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from marl_render.bench import peers, peers_worker


def block(steps, wall, cpu, resets=0, reset_wall=0.0, reset_cpu=0.0):
    return {"steps": steps, "wall": wall, "cpu": cpu, "resets": resets, "reset_wall": reset_wall,
            "reset_cpu": reset_cpu}


def test_summarise_takes_medians_and_amortises_resets_over_an_episode():
    info = {"worlds": 2, "agents": 3, "agent_view": [8, 8, 3], "episode_steps": 100}
    # stepping time is the block's minus its resets: 100, 200 and 400 steps/s; CPU 200, 400, 800.
    blocks = [block(100, 1.5, 0.75, 1, 0.5, 0.25), block(200, 1.0, 0.5), block(400, 1.25, 0.75, 1, 0.25, 0.25)]
    summary = peers.summarise(info, blocks)
    assert summary["env_steps"]["per_s"] == pytest.approx(2 * 200)
    assert summary["env_steps"]["per_cpu_s"] == pytest.approx(2 * 400)
    assert summary["reset_s"] == pytest.approx(0.375) and summary["reset_cpu_s"] == pytest.approx(0.25)
    # 100 steps at 200 steps/s (0.5 s) and one reset (0.375 s) per episode
    assert summary["env_steps"]["per_s_incl_resets"] == pytest.approx(2 * 100 / 0.875)
    assert summary["env_steps"]["per_cpu_s_incl_resets"] == pytest.approx(2 * 100 / (0.25 + 0.25))
    assert summary["agent_frames"] == {key: pytest.approx(3 * value) for key, value in summary["env_steps"].items()}
    assert summary["spread"] == pytest.approx((400 - 100) / 200)
    assert summary["cpu_per_wall"] == pytest.approx(0.5) and summary["rounds"] == 3


def test_summarise_without_timed_resets_or_agent_views():
    # resets inside step (autoreset) or a global frame only (MPE): incl. equals excl., no agent-frames
    summary = peers.summarise({"worlds": 1, "agents": 3, "episode_steps": None}, [block(50, 0.5, 0.25)] * 3)
    assert summary["env_steps"]["per_s_incl_resets"] == summary["env_steps"]["per_s"] == pytest.approx(100)
    assert summary["reset_s"] is None and summary["agent_frames"] is None
    with pytest.raises(ValueError, match="at least one block"):
        peers.summarise({"worlds": 1, "agents": 1}, [])


def test_ratios_are_ours_over_the_peer_for_every_rate():
    ours = {"env_steps": dict(zip(peers.RATE_KEYS, (10.0, 8.0, 6.0, 4.0), strict=True))}
    theirs = {"env_steps": dict(zip(peers.RATE_KEYS, (5.0, 2.0, 6.0, 8.0), strict=True))}
    assert peers.ratios(ours, theirs) == dict(zip(peers.RATE_KEYS, (2.0, 4.0, 1.0, 0.5), strict=True))


def parse(*argv):
    parser = argparse.ArgumentParser()
    peers.add_arguments(parser)
    return parser.parse_args(argv)


def test_run_names_the_missing_venv_and_its_make_target(tmp_path):
    args = parse("--only", "mpe", "--mpe-venv", str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match=r"--mpe-venv: no .*nowhere/bin/python; .*`make mpe-venv`"):
        peers.run(args)


def test_run_refuses_fewer_than_three_rounds():
    with pytest.raises(ValueError, match="--rounds must be >= 3.*got 2"):
        peers.run(parse("--rounds", "2"))


def test_worker_steps_a_marl_render_core_in_timed_blocks(tmp_path):
    worker = peers.Worker("core", sys.executable, str(tmp_path))
    try:
        info = worker.setup("marl_render_core", {"env": "cartpole", "worlds": 2, "resolution": 8})
        assert (info["system"], info["env"], info["worlds"], info["agents"]) == ("marl_render", "cartpole", 2, 1)
        assert info["agent_view"] == [8, 8, 3]
        reply = worker.block(0.05, reset=True)
        assert reply["steps"] >= 1 and reply["resets"] == 1
        assert reply["wall"] >= 0.05 + reply["reset_wall"] > 0 and reply["cpu"] >= reply["reset_cpu"] > 0
    finally:
        worker.close()
    assert worker.process.returncode == 0


def test_worker_errors_carry_the_workers_traceback(tmp_path):
    worker = peers.Worker("bad", sys.executable, str(tmp_path))
    try:
        with pytest.raises(peers.WorkerError,
                           match=r"worker bad failed in setup:(.|\n)*unknown system 'gym'; expected one of \["):
            worker.setup("gym", {})
        with pytest.raises(peers.WorkerError, match="unknown op 'jump'"):
            worker.request({"op": "jump"})
    finally:
        worker.close()


def test_a_worker_that_died_is_reported_with_its_exit_code(tmp_path):
    worker = peers.Worker("gone", sys.executable, str(tmp_path))
    worker.process.kill()
    worker.process.wait()
    try:
        with pytest.raises(peers.WorkerError, match=r"worker gone exited \(code -9\) during block"):
            worker.block(0.1, reset=False)
    finally:
        worker.close()


def test_melting_pots_expected_episode_length_from_its_stochastic_ending():
    ending = {"component": "StochasticIntervalEpisodeEnding",
              "kwargs": {"minimumFramesPerEpisode": 1000, "intervalLength": 100,
                         "probabilityTerminationPerInterval": 0.15}}
    settings = {"maxEpisodeLengthFrames": 5000,
                "simulation": {"scene": {"components": [{"component": "Neighborhoods", "kwargs": {}}, ending]}}}
    assert peers_worker.expected_episode_steps(settings) == pytest.approx(1000 + 100 * 0.85 / 0.15)
    assert peers_worker.expected_episode_steps({**settings, "maxEpisodeLengthFrames": 1200}) == 1200
    assert peers_worker.expected_episode_steps({"maxEpisodeLengthFrames": 5000, "simulation": {}}) is None


def test_the_worker_does_not_let_bench_modules_shadow_the_standard_library():
    """Run as a script, the worker's folder (marl_render/bench, which has a profile.py) must not come first on
    sys.path: cProfile's `import profile` took bench/profile.py, and PyBatchRender's envs failed to register."""
    code = ("import runpy, sys, os; sys.path.insert(0, os.path.dirname(sys.argv[1])); "
            "runpy.run_path(sys.argv[1], run_name='worker_under_test'); "
            "import cProfile, profile; print(profile.__file__)")
    done = subprocess.run([sys.executable, "-c", code, peers.WORKER], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert Path(done.stdout.strip()).parent != Path(peers.WORKER).parent  # the standard library's profile.py
