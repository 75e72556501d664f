"""Multi-process collection: ParallelEnv and MultiSyncCollector over spawned workers (one GL
context each), and TorchRL's torch.distributed collector (DistributedCollector, gloo) with two
local workers on 127.0.0.1 (examples/distributed_collect.py, run as a subprocess with its own
watchdog and a hard subprocess timeout). About 45-50 s on 2 cores.

Every check that the workers contributed compares a worker's first frame with the reset
frame of an env built here with that worker's seed: distinct seeds give distinct pixels."""
from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torchrl.collectors import MultiSyncCollector
from torchrl.envs import ParallelEnv

from marl_render.bench.parallel import make_env_with_vars
from marl_render.wrappers.torchrl import make_torchrl_env

ROOT = Path(__file__).resolve().parents[1]
W, RES, SEEDS = 2, 32, (11, 12)
AGENTS = 3  # spread's default


pytestmark = pytest.mark.usefixtures("single_torch_thread")


@functools.cache
def reset_pixels(seed: int) -> torch.Tensor:
    """("agents", "pixels") [W, A, RES, RES, 3] of the first reset of spread with `seed`, built here."""
    env = make_torchrl_env("spread", num_worlds=W, resolution=RES, seed=seed)
    try:
        return env.reset()["agents", "pixels"].clone()
    finally:
        env.close()


def creators(**extra):
    return [functools.partial(make_env_with_vars, extra.pop("env_vars", {}), "spread", num_worlds=W,
                              resolution=RES, seed=seed, **extra) for seed in SEEDS]


def assert_from_seeds(first_pixels: torch.Tensor):
    """first_pixels [2, W, A, H, Wpx, 3]: worker i's first frame is the reset frame of SEEDS[i]."""
    assert not torch.equal(reset_pixels(SEEDS[0]), reset_pixels(SEEDS[1]))
    for i, seed in enumerate(SEEDS):
        assert torch.equal(first_pixels[i], reset_pixels(seed)), f"worker {i} did not produce seed {seed}'s frame"


def test_parallel_env_two_spawned_workers():
    # The LP_NUM_THREADS=1 wrapper is the bench's; it must not change the pixels, and the
    # parent (which builds one env for the specs) gets its own value back.
    lp_before = os.environ.get("LP_NUM_THREADS")
    env = ParallelEnv(2, creators(env_vars={"LP_NUM_THREADS": "1"}), mp_start_method="spawn")
    try:
        td = env.rollout(4, break_when_any_done=False)
    finally:
        env.close(raise_if_closed=False)
    assert td.batch_size == torch.Size([2, W, 4])
    pixels = td["agents", "pixels"]
    assert pixels.shape == (2, W, 4, AGENTS, RES, RES, 3) and pixels.dtype == torch.uint8
    assert td["agents", "action"].shape == (2, W, 4, AGENTS) and td["agents", "action"].dtype == torch.int64
    assert td["next", "agents", "reward"].shape == (2, W, 4, AGENTS, 1)
    assert td["next", "done"].shape == (2, W, 4, 1) and td["next", "done"].dtype == torch.bool
    assert_from_seeds(pixels[:, :, 0])
    assert os.environ.get("LP_NUM_THREADS") == lp_before


def test_multisync_collector_two_workers():
    steps = 3
    collector = MultiSyncCollector(creators(), policy=None, frames_per_batch=2 * W * steps,
                                   total_frames=2 * 2 * W * steps)
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch.numel() == 2 * W * steps
        assert batch.batch_size == torch.Size([2, W, steps])  # the workers' [W, steps] batches, stacked
        pixels = batch["agents", "pixels"]
        assert pixels.shape == (2, W, steps, AGENTS, RES, RES, 3) and pixels.dtype == torch.uint8
        assert batch["agents", "action"].shape == (2, W, steps, AGENTS)
        assert batch["next", "agents", "reward"].dtype == torch.float32
    assert_from_seeds(batches[0]["agents", "pixels"][:, :, 0])


@pytest.mark.parametrize("launcher", ["mp", "delayed"])
def test_distributed_collector_two_local_workers(tmp_path, launcher):
    # mp: the collector spawns its workers; delayed: the workers are started on their own and
    # wait at the rendezvous, as on other machines (see docs/distributed.md).
    save = tmp_path / "batches.pt"
    steps, n_batches, seed = 3, 3, SEEDS[0]
    command = [sys.executable, str(ROOT / "examples" / "distributed_collect.py"), "--launcher", launcher,
               "--workers", "2",
               "--worlds", str(W), "--resolution", str(RES), "--steps-per-batch", str(steps),
               "--batches", str(n_batches), "--seed", str(seed), "--timeout", "100",
               "--save", str(save), "--json"]
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=150)
    assert result.returncode == 0, f"rc {result.returncode}\n{result.stdout}\n{result.stderr[-4000:]}"
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert len(summary["batches"]) == n_batches
    assert summary["worker_exitcodes"] == [0, 0]
    for i, entry in enumerate(summary["batches"]):
        assert entry["shape"] == [2, W, steps]
        assert entry["pixels_shape"] == [2, W, steps, AGENTS, RES, RES, 3] and entry["pixels_dtype"] == "torch.uint8"
        if i:  # update_policy_weights_() reached both workers before their next batch
            assert entry["favoured_action_share"] == 1.0
    batches = torch.load(save, weights_only=False)
    assert [tuple(b.batch_size) for b in batches] == [(2, W, steps)] * n_batches
    first = batches[0]
    assert first["agents", "pixels"].dtype == torch.uint8
    assert first["agents", "action"].shape == (2, W, steps, AGENTS)
    assert first["next", "agents", "reward"].shape == (2, W, steps, AGENTS, 1)
    assert first["next", "agents", "reward"].dtype == torch.float32
    assert_from_seeds(first["agents", "pixels"][:, :, 0])  # worker r got seed + r - 1 = SEEDS[r - 1]
    assert not torch.equal(batches[1]["agents", "pixels"][0], batches[1]["agents", "pixels"][1])
