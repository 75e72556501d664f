"""Shared pieces of the benchmarks: timing, progress, memory, the reference arena scene, reports."""
from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import functools
import gc
import json
import math
import os
import platform
import sys
import time

import psutil
import torch

import marl_render as mr
from marl_render.util.cpu import cpu_model_and_flags


def positive_int_argument(text: str) -> int:
    """argparse type: an int >= 1 (the error names the value; argparse adds the option)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an int >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an int >= 1, got {value}")
    return value


def positive_seconds_argument(text: str) -> float:
    """argparse type: a finite number of seconds > 0 (nan and inf would time nothing or never stop)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds > 0, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds > 0, got {text!r}")
    return value


def env_name_argument(text: str) -> str:
    """argparse type: the name of a registered env (checked before any work, not at the first make)."""
    from marl_render.envs import list_envs

    if text not in list_envs():
        raise argparse.ArgumentTypeError(f"unknown env {text!r}; known: {list_envs()}")
    return text


def env_name_or_all_argument(text: str) -> str:
    """argparse type: the name of a registered env, or 'all'."""
    return text if text == "all" else env_name_argument(text)


def env_spec_argument(text: str) -> str:
    """argparse type: NAME or NAME:AGENTS of a registered env (AGENTS an int >= 1), or 'all'."""
    from marl_render.envs.registry import env_class

    name, colon, agents = text.partition(":")
    if text != "all":
        env_name_argument(name)
    if colon:
        try:
            count = int(agents)
        except ValueError:
            count = 0
        if count < 1:
            raise argparse.ArgumentTypeError(f"expected NAME:AGENTS with AGENTS an int >= 1, got {text!r}")
        low, high = env_class(name).agent_range
        if not low <= count <= high:
            raise argparse.ArgumentTypeError(f"{name} takes {low} to {high} agents, got {text!r}")
    return text


def progress(message: str) -> None:
    """Progress goes to stderr so that --json output stays clean."""
    print(message, file=sys.stderr, flush=True)


def time_per_call(function, steps: int, warmup: int = 3) -> float:
    """Median-free simple mean of `steps` calls after `warmup` calls, in seconds."""
    for _ in range(warmup):
        function()
    start = time.perf_counter()
    for _ in range(steps):
        function()
    return (time.perf_counter() - start) / steps


def rss_mb() -> float:
    """Resident set size of this process in MB."""
    return psutil.Process().memory_info().rss / 2 ** 20


@functools.lru_cache(maxsize=1)
def _libc_malloc_trim():
    try:
        trim = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    return trim


def malloc_trim() -> bool:
    """Return freed heap memory to the OS (glibc only); False where unavailable.

    glibc keeps freed blocks for reuse, so without this a reading of RSS counts memory that
    is no longer in use (and may drop later, in the middle of another measurement)."""
    trim = _libc_malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]


@functools.lru_cache(maxsize=1)
def _libc_mallinfo2():
    try:
        function = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallinfo2  # glibc >= 2.33
    except (OSError, AttributeError):
        return None
    function.restype = _MallInfo2
    function.argtypes = []
    return function


def heap_in_use_mb() -> float | None:
    """Bytes of malloc's heap in live allocations (glibc's mallinfo2: arenas plus mmapped
    blocks, free chunks not counted), in MB; None where unavailable. Unlike RSS it does not
    move with freed memory the allocator keeps, so a leak of small blocks shows up in it."""
    mallinfo2 = _libc_mallinfo2()
    if mallinfo2 is None:
        return None
    info = mallinfo2()
    return (info.uordblks + info.hblkhd) / 2 ** 20


def settled_rss_mb() -> float:
    """RSS after collecting garbage and returning freed heap memory: memory still in use."""
    gc.collect()
    malloc_trim()
    return rss_mb()


def machine() -> dict:
    from marl_render.render import backend

    info = backend.gl_info()
    return {"gl_renderer": info.renderer, "gl_version": info.gl_version, "python": platform.python_version(),
            "torch": torch.__version__, "cpu_threads": torch.get_num_threads(), "cpu_model": cpu_model_and_flags()[0]}


def arena_scene(worlds: int, agents: int, resolution, instances: int = 10, effects=("lighting",),
                floor_role=None) -> mr.Scene:
    """Floor (of role floor_role) + `instances` per world: the agents' capsules (cameras mounted) and boxes."""
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=resolution, effects=effects)
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[12, 12, 1], color=[0.35, 0.55, 0.35],
                     role=floor_role)
    scene.add_group("agents", mr.capsule(0.25, 0.9, segments=8, rings=2), capacity=agents)
    scene.add_group("boxes", "box", capacity=max(instances - agents, 1))
    scene.mount_cameras("agents", list(range(agents)), offset=(0.0, 0.0, 0.3))
    return scene


class RandomMotion:
    """Random poses for arena_scene, the same sequence for every renderer given a seed."""

    def __init__(self, scene: mr.Scene, seed: int = 0):
        self.scene = scene
        self.generator = torch.Generator().manual_seed(seed)

    def next(self) -> dict:
        W = self.scene.num_worlds
        g = self.generator
        updates = {}
        for name, group in self.scene.groups.items():
            C = group.capacity
            position = torch.rand(W, C, 3, generator=g) * 8 - 4
            position[..., 2] = 0.45
            yaw = torch.rand(W, C, generator=g) * 2 * math.pi
            updates[name] = dict(position=position, rotation=mr.quat_from_yaw_pitch_roll(yaw),
                                 active=torch.ones(W, C, dtype=torch.bool),
                                 color=torch.rand(W, C, 3, generator=g) * 0.8 + 0.2)
        return updates


def apply(renderer, updates: dict) -> None:
    for name, kwargs in updates.items():
        renderer.update(name, **kwargs)


def write_report(out: str, name: str, result: dict, markdown: list[str] | None = None, **json_options) -> None:
    """DIR/name.json from `result` and, given lines, DIR/name.md; creates DIR."""
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, f"{name}.json"), "w") as f:
        json.dump(result, f, indent=2, **json_options)
    if markdown is not None:
        with open(os.path.join(out, f"{name}.md"), "w") as f:
            f.write("\n".join(markdown) + "\n")
