"""Run the many small tensor ops of a step on one thread.

A step is hundreds of torch ops on tensors of a few thousand elements. With torch's
default intra-op pool those ops fork onto every core, where they meet llvmpipe's
rasteriser threads and any other process: on 2 cores that made them 5-40x slower than
on one thread. Inside `single_threaded()` torch uses one thread; the caller's setting is
restored afterwards, so the user's own training code keeps its threads.
"""
from __future__ import annotations

import functools
from contextlib import contextmanager

import torch


@contextmanager
def single_threaded():
    previous = torch.get_num_threads()
    if previous == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def one_thread(method):
    """Decorator form of single_threaded()."""

    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        with single_threaded():
            return method(*args, **kwargs)

    return wrapper
