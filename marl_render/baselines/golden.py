"""Golden hashes of one tiny reproducible-mode training run: the check that a CPU trains bit for bit alike.

    python -m marl_render.baselines.golden                 # this machine's hashes, as JSON
    python -m marl_render.baselines.golden --write         # rewrite tests/data/reproducible_training.json
    python -m marl_render.baselines.golden --mode default --precision bfloat16 --threads 2   # the same run unpinned

The run (``TINY``: spread from pixels, 4 worlds at 16 px, 3 updates) takes seconds. Its hashes are the
sha256 of the final actor's parameters and of every update's loss terms; tests/test_reproducible.py
runs it again and compares them with the committed ones, so a machine on which the reproducible mode
does not hold fails the suite, its CPU named. The command restarts itself in the mode's environment
(reproducible.ENVIRONMENT). Rewrite the file only when the learner's arithmetic is meant to change.
``--mode default`` trains the same run without the mode, with `--precision` and `--threads` of your
choice: tools/reproducible_knobs.py compares both modes' hashes under emulated instruction sets.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import torch

from . import reproducible
from .settings import task_hyperparameters
from .training import train

GOLDEN = Path(__file__).resolve().parents[2] / "tests" / "data" / "reproducible_training.json"
TINY = {"env": "spread", "obs": "pixels", "seed": 0, "updates": 3,
        "hyperparameters": {"worlds": 4, "resolution": 16, "rollout": 8, "epochs": 2, "minibatches": 2, "hidden": 64,
                            "precision": reproducible.PRECISION, "torch_threads": reproducible.THREADS}}
LOSS_TERMS = ("loss_objective", "loss_critic", "loss_entropy", "entropy", "explained_variance")


def tensors_sha256(state: dict) -> str:
    """sha256 of a state_dict: each name, then its tensor's bytes, in name order."""
    sha = hashlib.sha256()
    for name, tensor in sorted(state.items()):
        sha.update(name.encode())
        sha.update(tensor.detach().contiguous().view(torch.uint8).numpy().tobytes())
    return sha.hexdigest()


def losses_sha256(curve: list) -> str:
    """sha256 of every update's LOSS_TERMS as float64, update by update."""
    return hashlib.sha256(np.array([[point[k] for k in LOSS_TERMS] for point in curve], np.float64).tobytes()
                          ).hexdigest()


def digests(mode: str = "reproducible", **overrides) -> dict:
    """The TINY run in `mode` ("reproducible": this process must have its environment; "default": with
    hyperparameter `overrides`, e.g. precision, torch_threads): its hashes, the first update's critic loss
    (to read), and the CPU it ran on."""
    hp = task_hyperparameters(TINY["env"], **{**TINY["hyperparameters"], **overrides})
    run = train(TINY["env"], obs=TINY["obs"], updates=TINY["updates"], seed=TINY["seed"], hyperparameters=hp,
                reproducible=mode == "reproducible")
    return {"run": TINY if mode == "reproducible" else {**TINY, "mode": mode, "overrides": overrides},
            "actor_sha256": tensors_sha256(run.trainer.actor_net.state_dict()),
            "losses_sha256": losses_sha256(run.curve), "first_loss_critic": run.curve[0]["loss_critic"],
            "torch": torch.__version__, "cpu": reproducible.cpu()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.golden", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write", action="store_true", help=f"write the hashes to {GOLDEN}")
    parser.add_argument("--mode", choices=("reproducible", "default"), default="reproducible")
    parser.add_argument("--precision", choices=("float32", "bfloat16"), default=None, help="--mode default only")
    parser.add_argument("--threads", type=int, default=None, help="torch threads, --mode default only")
    args = parser.parse_args(argv)
    overrides = {k: v for k, v in (("precision", args.precision), ("torch_threads", args.threads)) if v is not None}
    if args.mode == "reproducible" and overrides:
        parser.error(f"--precision and --threads apply to --mode default; the reproducible mode takes "
                     f"{reproducible.PRECISION} and {reproducible.THREADS} thread, got {overrides}")
    if args.write and args.mode != "reproducible":
        parser.error("--write takes the reproducible mode's hashes only, got --mode default")
    if args.mode == "reproducible" and reproducible.problems():
        reproducible.restart("marl_render.baselines.golden")
    found = digests(args.mode, **overrides)
    text = json.dumps(found, indent=1) + "\n"
    if args.write:
        GOLDEN.write_text(text)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
