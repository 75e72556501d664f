"""Optional compiled physics kernels (``EnvOptions.compile_physics``): torch.compile, or the
default path where compiling fails.

At small batches a step's physics costs its number of calls, not its arithmetic: 16
cart-poles take ~150 numpy and torch calls a step, each 0.3-2.5 us. torch.compile (inductor)
fuses a task's kernel into one C++ loop. It needs a C++ compiler at run time and takes seconds
to compile (torch caches the result on disk for later processes), so it is opt-in. Kernels are
the task's own functions run on torch; their results stay within 1e-12 of the default path's
(inductor's C++ rounds the last bit of some sin/cos values differently from torch's kernels;
tests/test_compiled.py).

A step never compiles and never raises for the compiler's sake:

* each kernel has a code object of its own, so torch's limit of 8 compiled graphs per code object
  (``recompile_limit``) is never shared between env sizes, or with the user's own compiled
  functools.partial objects (torch wraps them all in one function);
* it is called as it was compiled: grad off, inference mode off, inputs that are not inference
  tensors (inference tensors, made under the caller's ``torch.inference_mode()``, are copied
  first), so torch's guards hold and nothing recompiles (that took 0.6 s in a step);
* where a call fails all the same, the kernel warns once and steps from then on take the
  default path (``Kernel`` returns None; ``env.physics_compiled`` turns False).
"""
from __future__ import annotations

import sys
import time
import types
import warnings

import torch

_COMPILED: dict = {}  # key -> torch.compile'd function, shared by the envs of one process with the same key


class Kernel:
    """A compiled function as env steps call it: ``kernel(*args)`` is its result, or None once it
    has failed (then the caller takes its default path)."""

    def __init__(self, compiled, what: str):
        self._compiled, self.what = compiled, what

    @property
    def active(self) -> bool:
        return self._compiled is not None

    def __call__(self, *args):
        if self._compiled is None:
            return None
        try:
            return _call(self._compiled, args)
        except Exception as error:  # a recompile past the limit, a device inductor cannot build for, ...
            self._compiled = None
            warnings.warn(f"compile_physics: the compiled {self.what} failed in a step ({type(error).__name__}: "
                          f"{_first_line(error)}); this env takes the default path from now on",
                          RuntimeWarning, stacklevel=4)
            return None


def compile_kernel(function, example_args: tuple, what: str, key) -> Kernel | None:
    """A Kernel of torch.compile(function) as one graph, compiled now on `example_args` (its
    results are discarded), or None with a RuntimeWarning where compiling fails (no C++ compiler,
    a device inductor cannot build for, ...): the caller then keeps its default path. Envs whose
    kernels have the same `key` (hashable: what the function and the shapes of its arguments
    depend on) share one compiled function."""
    compiled = _COMPILED.get(key)
    if compiled is None:
        print(f"marl_render: compiling {what} with torch.compile (seconds the first time, cached after)",
              file=sys.stderr, flush=True)
        started = time.perf_counter()
        try:
            compiled = torch.compile(_own_code(function), dynamic=False, fullgraph=True)
            _call(compiled, example_args)
        except Exception as error:  # inductor's failures have many types; none may stop the env
            warnings.warn(f"compile_physics: {what} could not be compiled ({type(error).__name__}: "
                          f"{_first_line(error)}); the default path is used", RuntimeWarning, stacklevel=3)
            return None
        print(f"marl_render: compiled {what} in {time.perf_counter() - started:.1f} s", file=sys.stderr, flush=True)
        _COMPILED[key] = compiled
    return Kernel(compiled, what)


def _call(compiled, args: tuple):
    """compiled(*args) as the graph was compiled (see the module docstring)."""
    with torch.inference_mode(False), torch.no_grad():  # in this order: inference_mode(False) turns grad on
        return compiled(*(arg.clone() if arg.is_inference() else arg for arg in args))


def _own_code(function):
    """`function` called through a wrapper with a code object of its own (see the module docstring)."""
    def kernel(*args):
        return function(*args)
    return types.FunctionType(kernel.__code__.replace(), kernel.__globals__, kernel.__name__, None,
                              kernel.__closure__)


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else ""
