"""Golden hashes of one tiny reproducible-mode training run, per CPU: the check that a machine trains
bit for bit as others of its CPU did.

    python -m marl_render.baselines.golden                 # this machine's hashes, as JSON
    python -m marl_render.baselines.golden --write         # record them for this CPU (tests/data/)
    python -m marl_render.baselines.golden --mode default --precision bfloat16 --threads 2   # the same run unpinned

The run (``TINY``: spread from pixels, 4 worlds at 16 px, 3 updates) takes seconds. Its hashes are the
sha256 of the final actor's parameters and of every update's loss terms. The file keeps one record per
CPU (model, instruction-set flags, torch's kernel capability) and torch version, because the bits are
not the same across CPUs: an AMD EPYC and an Intel Xeon with AMX gave different hashes from the first
update (docs/training.md). tests/test_reproducible.py runs it again and compares with the record of
this machine's CPU, so a machine that trains other bits than its CPU did fails the suite; a CPU without
a record is checked for run-to-run identity only. Each record also keeps ``primitives()``, hashes of
the kernels the learner runs through, so that two CPUs' records say which kernels differ. The command
restarts itself in the mode's environment (reproducible.ENVIRONMENT). Record a CPU once; rewrite the
records only when the learner's arithmetic is meant to change.
``--mode default`` trains the same run without the mode, with `--precision` and `--threads` of your
choice: tools/reproducible_knobs.py compares both modes' hashes under emulated instruction sets.
"""
from __future__ import annotations

import argparse
import contextlib
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


def _exact_floats(count: int, salt: int) -> torch.Tensor:
    """`count` float32 values in [-8, 8) from integer arithmetic only (a hash of the index, scaled by a
    power of two: exact, so the inputs cannot depend on the CPU)."""
    index = torch.arange(count, dtype=torch.int64)
    return (((index * 2654435761 + salt * 40503) % 2 ** 20).to(torch.float32) / 2 ** 16) - 8.0


def primitives() -> dict:
    """sha256 (16 hex digits) of each kind of kernel the learner's arithmetic runs through, on fixed
    exact inputs, in this process's mode: MKL's GEMM (small and blocked sizes), convolutions with a
    batch under 16 (ATen's own, through GEMM) and of 16 or more (where torch uses NNPACK, which picks
    its blocking from the CPU's cache sizes) with their gradients, MKL's vector maths (exp, log, tanh,
    sqrt), glibc's (sin, cos, atan2 through ATen), a softmax and a long sum."""
    threads = torch.get_num_threads()
    torch.set_num_threads(reproducible.THREADS)  # GEMM's and convolutions' sums split by thread otherwise
    try:
        return _primitive_hashes()
    finally:
        torch.set_num_threads(threads)


def _sha(tensor: torch.Tensor) -> str:
    """16 hex digits of the sha256 of a tensor's bytes."""
    return hashlib.sha256(tensor.detach().contiguous().numpy().tobytes()).hexdigest()[:16]


def _primitive_hashes() -> dict:
    x = _exact_floats(1 << 16, 1)
    found = {"gemm_64x97x33": _sha(_exact_floats(64 * 97, 2).view(64, 97) @ _exact_floats(97 * 33, 3).view(97, 33)),
             "gemm_512x1568x128": _sha(_exact_floats(512 * 1568, 4).view(512, 1568) / 64
                                       @ (_exact_floats(1568 * 128, 5).view(1568, 128) / 64))}
    weight = (_exact_floats(32 * 16 * 9, 6).view(32, 16, 3, 3) / 64).requires_grad_()
    for batch in (4, 48):  # torch convolves a batch of 16 or more through NNPACK where it is built in
        images = (_exact_floats(batch * 16 * 15 * 15, 7 + batch).view(batch, 16, 15, 15) / 8).requires_grad_()
        out = torch.nn.functional.conv2d(images, weight, stride=2)
        (out * out).sum().backward()
        found[f"conv_batch{batch}"] = _sha(out)
        found[f"conv_batch{batch}_gradients"] = _sha(torch.cat((images.grad.flatten(), weight.grad.flatten())))
        weight.grad = None
    found.update({"exp": _sha(torch.exp(x)), "log": _sha(torch.log(x.abs() + 2 ** -10)), "tanh": _sha(torch.tanh(x)),
                  "sqrt": _sha(torch.sqrt(x.abs())), "sin": _sha(torch.sin(x)), "cos": _sha(torch.cos(x)),
                  "atan2": _sha(torch.atan2(x, x.flip(0))), "log_softmax": _sha(torch.log_softmax(x.view(64, -1), -1)),
                  "sum": _sha(x.sum())})
    return found


def digests(mode: str = "reproducible", **overrides) -> dict:
    """The TINY run in `mode` ("reproducible": this process must have its environment; "default": with
    hyperparameter `overrides`, e.g. precision, torch_threads): its hashes, the first update's critic loss
    (to read), and the CPU it ran on."""
    hp = task_hyperparameters(TINY["env"], **{**TINY["hyperparameters"], **overrides})
    reproducible_mode = mode == "reproducible"
    run = train(TINY["env"], obs=TINY["obs"], updates=TINY["updates"], seed=TINY["seed"], hyperparameters=hp,
                reproducible=reproducible_mode)
    with reproducible.mode() if reproducible_mode else contextlib.nullcontext():
        kernels = primitives()
    return {"run": TINY if reproducible_mode else {**TINY, "mode": mode, "overrides": overrides},
            "actor_sha256": tensors_sha256(run.trainer.actor_net.state_dict()),
            "losses_sha256": losses_sha256(run.curve), "first_loss_critic": run.curve[0]["loss_critic"],
            "torch": torch.__version__, "cpu": reproducible.cpu(), "primitives": kernels}


def recorded(path: Path = GOLDEN) -> dict:
    """The committed records: {"run": TINY, "machines": [a record of digests() per CPU and torch]}."""
    return json.loads(path.read_text())


def same_cpu(a: dict, b: dict) -> bool:
    """Whether two records were made on the same CPU (model, flags, torch's capability) and torch version."""
    return a["cpu"] == b["cpu"] and a["torch"] == b["torch"]


def record_for(found: dict, records: dict) -> dict | None:
    """The record made on the CPU and torch version of `found` (``same_cpu``), if any."""
    return next((machine for machine in records["machines"] if same_cpu(machine, found)), None)


def with_record(found: dict, records: dict) -> dict:
    """`records` with `found` as its CPU's record (replacing that CPU's old one, the others kept)."""
    if found["run"] != TINY:
        raise ValueError(f"only the reproducible mode's tiny run is recorded, got run {found['run']!r}")
    entry = {key: value for key, value in found.items() if key != "run"}
    others = [machine for machine in records["machines"] if not same_cpu(machine, found)]
    return {"run": TINY, "machines": [*others, entry]}


def differing_primitives(a: dict, b: dict) -> list[str]:
    """The primitives whose hashes differ between two records (those either lacks are left out)."""
    first, second = a.get("primitives") or {}, b.get("primitives") or {}
    return sorted(name for name in first.keys() & second.keys() if first[name] != second[name])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.golden", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write", action="store_true", help=f"record the hashes for this CPU in {GOLDEN}")
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
    if args.write:
        GOLDEN.write_text(json.dumps(with_record(found, recorded()), indent=1) + "\n")
    sys.stdout.write(json.dumps(found, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
