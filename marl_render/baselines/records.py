"""What a run of ``python -m marl_render.baselines`` records besides its learning: the per-seed
commands and their summary across seeds, the versions and arithmetic its numbers rest on, and its
files (written atomically; self-play snapshots as run folders that load_policy reads)."""
from __future__ import annotations

import importlib.metadata
import os
import platform
import shutil
import tempfile

import numpy as np
import torch

from marl_render.populations import stats
from marl_render.util import strict_json

from . import reproducible


def seed_command(argv: list, seed: int, out: str, tensorboard: str | None) -> list:
    """The command line of one seed of a --seeds run: --seeds, --out and --tensorboard replaced by
    this seed's --seed, --out and --tensorboard (--out and --tensorboard take one value, --seeds
    every number that follows it)."""
    kept, dropping = [], None
    for token in argv:
        if dropping == "--seeds" and token.lstrip("-").isdigit():
            continue
        if dropping in ("--out", "--tensorboard"):
            dropping = None
            continue
        dropping = None
        if token in ("--seeds", "--out", "--tensorboard"):
            dropping = token
            continue
        if token.startswith(("--out=", "--tensorboard=", "--seeds=")):
            continue
        kept.append(token)
    return kept + ["--seed", str(seed), "--out", out] + (["--tensorboard", tensorboard] if tensorboard else [])


def seeds_summary(results: list) -> dict:
    """The final policy's return per seed, their mean with a 95% bootstrap interval over seeds, the
    references of the (shared) evaluation set and the normalised scores (random 0, heuristic 1)."""
    returns = [r["evaluation"]["policy"]["mean"] for r in results]
    random, heuristic = (results[0]["evaluation"][k]["mean"] for k in ("random", "heuristic"))
    estimate = stats.stratified_bootstrap(np.asarray(returns)[:, None], stats.mean) if len(returns) > 1 else None
    scale = heuristic - random
    return {"env": results[0]["env"], "obs": results[0]["obs"], "seeds": [r["seeds"]["train"] for r in results],
            "returns": returns, "mean": float(np.mean(returns)),
            "interval": None if estimate is None else [estimate.low, estimate.high],
            "random": random, "heuristic": heuristic,
            "normalised": [(v - random) / scale if scale else None for v in returns],
            "normalised_mean": (float(np.mean(returns)) - random) / scale if scale else None,
            "evaluation_set": evaluation_label(results[0]), "folders": [r["out"] for r in results]}


def evaluation_label(result: dict) -> str:
    """What a run's final evaluation played: its evaluation set, or the levels and env seed it was given."""
    if result.get("evaluation_levels") is None:
        return f"{result['evaluation_set']} set"
    return f"levels {result['evaluation_levels']!r}, env seed {result['seeds']['evaluation']}"


def print_seeds_summary(summary: dict) -> None:
    print(f"\n{summary['env']} from {summary['obs']}: {len(summary['seeds'])} seeds ({summary['evaluation_set']})")
    print("| seed | return | normalised | folder |\n|---:|---:|---:|---|")
    for seed, value, score, folder in zip(summary["seeds"], summary["returns"], summary["normalised"],
                                          summary["folders"], strict=True):
        print(f"| {seed} | {value:.4g} | {'n/a' if score is None else f'{score:.2f}'} | {folder} |")
    interval = "" if summary["interval"] is None else \
        f" [{summary['interval'][0]:.4g}, {summary['interval'][1]:.4g}] (95% bootstrap over seeds)"
    normalised = summary["normalised_mean"]
    print(f"mean {summary['mean']:.4g}{interval}; random {summary['random']:.4g}, heuristic "
          f"{summary['heuristic']:.4g}; normalised {'n/a' if normalised is None else f'{normalised:.2f}'}",
          flush=True)


def versions() -> dict:
    import marl_render
    # The other libraries' versions from their metadata: importing TorchRL and TensorDict costs seconds, the
    # trainer does not.
    return {"marl_render": getattr(marl_render, "__version__", "unknown"), "torch": torch.__version__,
            **{name: installed_version(name) for name in LIBRARIES}, "python": platform.python_version()}


LIBRARIES = ("torchrl", "tensordict", "numpy", "panda3d")  # besides torch, what a run's numbers rest on


def arithmetic() -> dict:
    """How this process computes: the reproducible mode's variables as set, oneDNN and deterministic
    algorithms as they are now (inside reproducible.mode() when the run uses it), torch's threads."""
    return {"environment": {name: os.environ.get(name) for name in reproducible.ENVIRONMENT},
            "onednn": torch.backends.mkldnn.enabled, "deterministic_algorithms":
                torch.are_deterministic_algorithms_enabled(), "torch_threads": torch.get_num_threads()}


def installed_version(distribution: str) -> str:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def write_atomically(path: str, write) -> None:
    """`write(file)` into a temporary file beside `path`, then rename it over `path`: a reader never
    sees a half-written file, and an interrupted run leaves the previous one (or none)."""
    folder = os.path.dirname(path) or "."
    handle, temporary = tempfile.mkstemp(dir=folder, prefix=f".{os.path.basename(path)}.")
    try:
        with os.fdopen(handle, "wb") as f:
            write(f)
        os.replace(temporary, path)
    except BaseException:
        os.unlink(temporary)
        raise


def clear_snapshots(out: str) -> int:
    """Remove the snapshot run folders (OUT/snapshots/NNN) an earlier run left in `out`, and the
    snapshots folder once empty; the count removed. A rerun replaces every file of the earlier run
    (actor.pt, result.json and curve.png are overwritten): its snapshots must not pass for the new
    run's. Done when the new run's files are written, so an interrupted run leaves the earlier one whole."""
    folder = os.path.join(out, "snapshots")
    if not os.path.isdir(folder):
        return 0
    stale = [entry for entry in os.scandir(folder) if entry.is_dir() and entry.name.isdigit()]
    for entry in stale:
        shutil.rmtree(entry.path)
    if not os.listdir(folder):
        os.rmdir(folder)
    return len(stale)


def save_snapshots(pool, result: dict, out: str) -> dict:
    """Every snapshot of `pool` as a run folder OUT/snapshots/NNN (actor.pt, then a result.json
    that load_policy reads: the run's env, obs and hyperparameters, and the snapshot's record);
    the pool's record for the run's result.json, each snapshot with its folder."""
    record = pool.record()
    for snapshot, actor in zip(record["snapshots"], pool.actors, strict=True):
        snapshot["folder"] = os.path.join("snapshots", f"{snapshot['id']:03d}")
        folder = os.path.join(out, snapshot["folder"])
        os.makedirs(folder, exist_ok=True)
        write_atomically(os.path.join(folder, "actor.pt"), lambda f, actor=actor: torch.save(actor.state_dict(), f))
        own = {key: result[key] for key in ("env", "obs", "seeds", "hyperparameters", "env_options", "versions",
                                            "vector_obs") if key in result}
        own.update(snapshot=snapshot, self_play_run="../..", env_steps=snapshot["env_steps"])
        write_atomically(os.path.join(folder, "result.json"),
                         lambda f, own=own: f.write(strict_json.dumps(own, indent=1).encode()))
    return record
