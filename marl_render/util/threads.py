"""Run the many small tensor ops of a step on one thread.

A step is hundreds of torch ops on tensors of a few thousand elements. With torch's
default intra-op pool those ops fork onto every core, where they meet llvmpipe's
rasteriser threads and any other process: on 2 cores that made them 5-40x slower than
on one thread. Inside `limited_threads()` torch uses the given number of threads; the
caller's setting is restored afterwards, so the user's own training code keeps its
threads, and `caller_threads()` lends them back for one bulk operation (the tile copy,
which runs while the rasteriser is idle).

Thread counts are bounded by MAX_THREADS: torch accepts any positive count and starts
that many OpenMP threads at the next parallel op, and where the system cannot create
them the process dies inside libgomp (10**6 crashed an env's reset; on the 2-core test
machine 4,096 threads still started, 32,768 did not). 1024 is more than any CPU's
cores, so no useful setting is refused, and being fixed it is valid on every machine.
"""
from __future__ import annotations

import functools
import threading
from contextlib import contextmanager

import numpy as np
import torch

from .validation import describe

MAX_THREADS = 1024

_state = threading.local()  # depth of nested limited_threads() and the outermost caller's count


def thread_count(name: str, value) -> int:
    """`value` as a torch thread count: an int in [1, MAX_THREADS], else TypeError / ValueError naming `name`."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be None or an int in [1, {MAX_THREADS}], got {describe(value)}")
    if not 1 <= value <= MAX_THREADS:
        raise ValueError(f"{name} must be None or an int in [1, {MAX_THREADS}], got {value}")
    return int(value)


@contextmanager
def limited_threads(n: int | None = 1):
    """torch uses n intra-op threads inside the block (None: leave the setting alone)."""
    if n is None:
        yield
        return
    n = thread_count("n", n)  # before any state is touched
    previous = torch.get_num_threads()
    depth = getattr(_state, "depth", 0)
    if depth == 0:
        _state.caller = previous
    _state.depth = depth + 1
    if previous != n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        _state.depth = depth
        if previous != n:
            torch.set_num_threads(previous)


def single_threaded():
    return limited_threads(1)


@contextmanager
def caller_threads():
    """Inside limited_threads(): the outermost caller's thread count, for one bulk op."""
    wanted = getattr(_state, "caller", None) if getattr(_state, "depth", 0) else None
    current = torch.get_num_threads()
    if wanted is None or wanted == current:
        yield
        return
    torch.set_num_threads(wanted)
    try:
        yield
    finally:
        torch.set_num_threads(current)


def one_thread(method):
    """Decorator form of single_threaded()."""

    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        with single_threaded():
            return method(*args, **kwargs)

    return wrapper
