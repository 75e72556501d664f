"""Reproducible training: the learner's arithmetic on code paths that do not depend on the CPU.

    python -m marl_render.baselines --env spread --reproducible

By default torch picks its kernels by the CPU's instruction set when it loads (ATen's AVX2 or
AVX-512 kernels, oneDNN's convolutions and bfloat16 kernels, MKL's GEMM branch), so the same
command trains bit for bit alike on two machines only if their CPUs match. The reproducible mode
pins every choice that measurements on one AMD EPYC showed to change a training run's bits
(docs/training.md, "Reproducible mode"). It does not make the bits the same across CPU models: an
Intel Xeon with AMX trains other bits than the EPYC from the first update (the golden records,
golden.py). What it pins:

- the process starts with ``ENVIRONMENT`` (read by torch, MKL and Mesa when they load, so it
  cannot be set from inside a process that has imported torch: the command line re-executes
  itself with it, ``restart``): ATen's baseline kernels, MKL's processor-independent branch and
  llvmpipe's AVX code generation;
- inside the process (``mode``): oneDNN off (convolutions through ATen), deterministic algorithms;
- the run's hyperparameters (``settings_problem``): float32 compute (no bfloat16 autocast) and one
  torch thread (reductions split over threads sum in another order).

``problems()`` lists what of the process environment is not pinned; ``cpu()`` says which CPU a run
had, for result.json and for the golden-hash test's failure message.
"""
from __future__ import annotations

import contextlib
import os
import sys

import torch

from marl_render.util.cpu import cpu_model_and_flags

# Read when each library loads; the measured effect of each is in docs/training.md.
ENVIRONMENT = {
    "ATEN_CPU_CAPABILITY": "default",  # ATen's vectorised kernels: the build's baseline, not AVX2 / AVX-512
    "MKL_CBWR": "COMPATIBLE",  # MKL's conditional numerical reproducibility: its branch documented for every x86-64 CPU
    "GALLIUM_OVERRIDE_CPU_CAPS": "avx",  # llvmpipe generates AVX code whatever more the CPU has
}
THREADS = 1
PRECISION = "float32"
# CPU flags that choose kernels: what result.json records of /proc/cpuinfo's flags.
RELEVANT_FLAGS = ("sse4_1", "sse4_2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512dq", "avx512bw", "avx512vl",
                  "avx512_vnni", "avx512_bf16", "avx512_fp16", "avx_vnni", "amx_bf16", "amx_tile", "amx_int8",
                  "amx_fp16")


def problems() -> list[str]:
    """What keeps this process from the reproducible mode: each pinned variable that is unset or
    differs, and torch's CPU capability if torch loaded without the pin. Empty when pinned."""
    found = [f"{name}={os.environ.get(name)!r} (needs {value!r})" for name, value in ENVIRONMENT.items()
             if os.environ.get(name) != value]
    capability = torch.backends.cpu.get_cpu_capability()
    if capability != "DEFAULT":
        found.append(f"torch's CPU capability is {capability} (needs DEFAULT: ATEN_CPU_CAPABILITY=default "
                     f"set before torch was imported)")
    return found


def settings_problem(precision: str, torch_threads: int) -> str | None:
    """Why hyperparameters `precision` and `torch_threads` cannot train reproducibly (None: they can)."""
    if precision != PRECISION:
        return f"precision must be {PRECISION!r} in reproducible mode (bfloat16 kernels depend on the CPU), " \
               f"got {precision!r}"
    if torch_threads != THREADS:
        return f"torch_threads must be {THREADS} in reproducible mode (reductions split over threads sum in " \
               f"another order), got {torch_threads}"
    return None


def restart(module: str = "marl_render.baselines") -> None:
    """Replace this process by ``python -m module`` with the same arguments and ``ENVIRONMENT`` set.
    Never returns; RuntimeError if the environment is already set (a restart would change nothing)."""
    if all(os.environ.get(name) == value for name, value in ENVIRONMENT.items()):
        raise RuntimeError("the reproducible mode's environment is set, yet: " + "; ".join(problems()))
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, "-m", module, *sys.argv[1:]], {**os.environ, **ENVIRONMENT})


@contextlib.contextmanager
def mode():
    """oneDNN off and deterministic algorithms while inside (both restored after). ValueError, before
    anything changes, if the process environment is not pinned (``problems``)."""
    found = problems()
    if found:
        raise ValueError("reproducible mode needs its environment set before torch is imported (the command "
                         "line `python -m marl_render.baselines --reproducible` restarts itself with it): "
                         + "; ".join(found))
    deterministic = torch.are_deterministic_algorithms_enabled()
    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    onednn = torch.backends.mkldnn.enabled
    torch.use_deterministic_algorithms(True)
    torch.backends.mkldnn.enabled = False  # not mkldnn.flags(): it also sets oneDNN's TF32 flag, with a warning
    try:
        yield
    finally:
        torch.backends.mkldnn.enabled = onednn
        torch.use_deterministic_algorithms(deterministic, warn_only=warn_only)


def cpu() -> dict:
    """The CPU model (/proc/cpuinfo's 'model name', else platform.processor()), its flags among
    RELEVANT_FLAGS, and torch's CPU capability (the ATen kernels this process runs)."""
    model, flags = cpu_model_and_flags()
    return {"model": model, "flags": [flag for flag in RELEVANT_FLAGS if flag in flags],
            "torch_cpu_capability": torch.backends.cpu.get_cpu_capability()}


def describe(record: dict) -> str:
    """One line of a cpu() record."""
    return f"{record['model']} (flags {' '.join(record['flags']) or 'none'}; torch {record['torch_cpu_capability']})"
