"""Optional compiled physics kernels (``EnvOptions.compile_physics``): torch.compile, or the
default path where compiling fails.

At small batches a step's physics costs its number of calls, not its arithmetic: 16
cart-poles take ~150 numpy and torch calls a step, each 0.3-2.5 us. torch.compile (inductor)
fuses a task's kernel into one C++ loop. It needs a C++ compiler at run time and takes seconds
to compile (torch caches the result on disk for later processes), so it is opt-in. Kernels are
the task's own functions run on torch; their results stay within 1e-12 of the default path's
(inductor's C++ rounds the last bit of some sin/cos values differently from torch's kernels;
tests/test_compiled.py).
"""
from __future__ import annotations

import sys
import time
import warnings

import torch


def compile_kernel(function, example_args: tuple, what: str):
    """torch.compile(function) as one graph, compiled now on `example_args` (its results are
    discarded), or None with a RuntimeWarning where compiling fails (no C++ compiler, a
    device inductor cannot build for, torch's limit of 8 compiled shapes per function reached
    by envs of as many sizes in one process, ...): the caller then keeps its default path."""
    print(f"marl_render: compiling {what} with torch.compile (seconds the first time, cached after)",
          file=sys.stderr, flush=True)
    started = time.perf_counter()
    try:
        kernel = torch.compile(function, dynamic=False, fullgraph=True)
        with torch.no_grad():  # as env steps run: a graph compiled with grad on would be compiled again
            kernel(*example_args)
    except Exception as error:  # inductor's failures have many types; none may stop the env
        reason = str(error).strip().splitlines()[0] if str(error).strip() else ""
        warnings.warn(f"compile_physics: {what} could not be compiled ({type(error).__name__}: {reason}); "
                      "the default path is used", RuntimeWarning, stacklevel=3)
        return None
    print(f"marl_render: compiled {what} in {time.perf_counter() - started:.1f} s", file=sys.stderr, flush=True)
    return kernel
