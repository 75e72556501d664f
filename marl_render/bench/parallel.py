"""Multi-process throughput: one process vs TorchRL's ParallelEnv and MultiSyncCollector.

The same total number of worlds W is run three ways, random actions throughout:

  single      make_torchrl_env(num_worlds=W) in this process, env.rollout
  parallel-N  torchrl.envs.ParallelEnv(N, make_torchrl_env(num_worlds=W/N)), spawn, rollout
  collect-N   torchrl.collectors.MultiSyncCollector over N workers of W/N worlds, random policy
  processes-N make_torchrl_env(num_worlds=W, num_processes=N) in this process, env.rollout: the
              same call as `single`, its worlds stepped and rendered by N worker processes that
              write into shared output tensors (envs/multiprocess.py); --processes picks the N,
              and each such row gets `ratio_to_single`

Every worker process is started with 'spawn' and owns its own GL context. env-steps/s
counts world steps, agent-frames/s rendered agent views; "scaling" is N=2 over N=1 of the
same kind (N=1 pays the inter-process copies without any parallelism). With --lp-threads,
the worker processes are run with the Mesa llvmpipe rasteriser thread count
LP_NUM_THREADS unset (llvmpipe's default: one thread per core) and/or set to the given
value; the variable is set inside each worker before its GL context exists (env creator
wrapper for ParallelEnv, the collector's init_fn for MultiSyncCollector). The
single-process row always uses this process's setting.
"""
from __future__ import annotations

import functools
import os
import statistics
import time

import torch

from .common import env_name_argument, machine, positive_int_argument, progress

KINDS = ("single", "parallel", "collect", "processes")


def add_arguments(parser):
    parser.add_argument("--env", default="spread", type=env_name_argument)
    parser.add_argument("--worlds", type=positive_int_argument, default=64,
                        help="total worlds W (split evenly over the workers)")
    parser.add_argument("--agents", type=positive_int_argument, default=None,
                        help="agents per world (env default if omitted)")
    parser.add_argument("--resolution", type=positive_int_argument, default=64)
    parser.add_argument("--steps", type=positive_int_argument, default=30, help="batched steps per timed repeat")
    parser.add_argument("--repeats", type=positive_int_argument, default=3,
                        help="timed repeats per configuration (median reported)")
    parser.add_argument("--workers", type=positive_int_argument, nargs="+", default=[1, 2],
                        help="worker counts to measure")
    parser.add_argument("--processes", type=positive_int_argument, nargs="+", default=[1, 2],
                        help="num_processes values of the 'processes' kind (worlds split unevenly if need be)")
    parser.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    parser.add_argument("--device", default="cpu", help="torch device of the envs' tensors (e.g. cuda)")
    parser.add_argument("--lp-threads", nargs="+", default=["default", "1"],
                        help="LP_NUM_THREADS of the worker processes: 'default' (unset) and/or integers")


# --------------------------------------------------------------------------- worker-side helpers
# Module-level functions so that functools.partial(...) of them pickles under 'spawn'.
def set_env_vars(env_vars: dict) -> None:
    """Set (value str) or unset (value None) environment variables in this process."""
    for key, value in env_vars.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = str(value)


def make_env_with_vars(env_vars: dict, name: str, **kwargs):
    """make_torchrl_env(name, **kwargs) with `env_vars` set while it is built.

    Meant for worker processes: Mesa reads LP_NUM_THREADS (and MARL_RENDER_EGL_DEVICE is
    read) when the process's GL context is created, i.e. while the first env is built. The
    previous values are restored afterwards, so a parent that builds a throw-away env for
    metadata (ParallelEnv does) keeps its own settings unless this is its first GL context."""
    from marl_render.wrappers.torchrl import make_torchrl_env

    saved = {key: os.environ.get(key) for key in env_vars}
    set_env_vars(env_vars)
    try:
        return make_torchrl_env(name, **kwargs)
    finally:
        set_env_vars(saved)


def _lp_vars(lp: str) -> dict:
    return {"LP_NUM_THREADS": None} if lp == "default" else {"LP_NUM_THREADS": str(int(lp))}


# --------------------------------------------------------------------------- measurements
def _row(kind, workers, lp, worlds, agents, steps, repeat_seconds, setup_s):
    """Throughput from the median of the repeats (each `steps` batched steps of all W worlds)."""
    per_step = statistics.median(repeat_seconds) / steps
    best = min(repeat_seconds) / steps
    return {"kind": kind, "workers": workers, "lp_num_threads": lp, "worlds": worlds, "agents": agents,
            "ms_per_step": per_step * 1e3, "env_steps_per_s": worlds / per_step,
            "agent_frames_per_s": worlds * agents / per_step, "best_env_steps_per_s": worlds / best,
            "repeats": len(repeat_seconds), "setup_s": setup_s}


def _timed_rollouts(env, steps: int, repeats: int) -> list:
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        env.rollout(steps, break_when_any_done=False)
        seconds.append(time.perf_counter() - start)
    return seconds


def measure_single(args, env_kwargs) -> dict:
    from marl_render.wrappers.torchrl import make_torchrl_env

    t0 = time.perf_counter()
    env = make_torchrl_env(args.env, num_worlds=args.worlds, **env_kwargs)
    try:
        env.set_seed(0)
        env.rollout(3, break_when_any_done=False)  # warm-up: reset, shader compile, first frames
        setup = time.perf_counter() - t0
        agents = env.core.num_agents
        seconds = _timed_rollouts(env, args.steps, args.repeats)
    finally:
        env.close(raise_if_closed=False)
    return _row("single", 1, os.environ.get("LP_NUM_THREADS", "default"), args.worlds, agents,
                args.steps, seconds, setup)


def measure_processes(args, env_kwargs, processes: int) -> dict:
    """The single row's call over `processes` worker processes (num_processes=)."""
    from marl_render.wrappers.torchrl import make_torchrl_env

    t0 = time.perf_counter()
    env = make_torchrl_env(args.env, num_worlds=args.worlds, num_processes=processes, **env_kwargs)
    try:
        env.set_seed(0)
        env.rollout(3, break_when_any_done=False)  # warm-up: resets, shader compile, first frames
        setup = time.perf_counter() - t0
        agents = env.core.num_agents
        seconds = _timed_rollouts(env, args.steps, args.repeats)
    finally:
        env.close(raise_if_closed=False)
    return _row("processes", processes, os.environ.get("LP_NUM_THREADS", "default"), args.worlds, agents,
                args.steps, seconds, setup)


def measure_parallel(args, env_kwargs, workers: int, lp: str) -> dict:
    from torchrl.envs import ParallelEnv

    per_worker = args.worlds // workers
    create = functools.partial(make_env_with_vars, _lp_vars(lp), args.env, num_worlds=per_worker, **env_kwargs)
    t0 = time.perf_counter()
    env = ParallelEnv(workers, create, mp_start_method="spawn")
    try:
        env.set_seed(0)
        env.rollout(3, break_when_any_done=False)  # starts the workers
        setup = time.perf_counter() - t0
        agents = _agents(env.full_action_spec, len(env.batch_size))
        seconds = _timed_rollouts(env, args.steps, args.repeats)
    finally:
        env.close(raise_if_closed=False)
    return _row("parallel", workers, lp, per_worker * workers, agents, args.steps, seconds, setup)


def measure_collector(args, env_kwargs, workers: int, lp: str) -> dict:
    """One batch = `steps` steps of every worker's W/N worlds; one warm-up batch, then `repeats`."""
    from torchrl.collectors import MultiSyncCollector

    per_worker = args.worlds // workers
    create = functools.partial(make_env_with_vars, {}, args.env, num_worlds=per_worker, **env_kwargs)
    frames_per_batch = per_worker * workers * args.steps
    t0 = time.perf_counter()
    collector = MultiSyncCollector([create] * workers, policy=None, frames_per_batch=frames_per_batch,
                                   total_frames=frames_per_batch * (args.repeats + 1),
                                   init_fn=functools.partial(set_env_vars, _lp_vars(lp)))
    try:
        iterator = iter(collector)
        first = next(iterator)  # warm-up batch (worker start, resets, shader compile)
        setup = time.perf_counter() - t0
        agents = _agents(first, first.ndim)
        seconds, start = [], time.perf_counter()
        for batch in iterator:
            assert batch.numel() == frames_per_batch
            now = time.perf_counter()
            seconds.append(now - start)
            start = now
    finally:
        collector.shutdown()
    return _row("collect", workers, lp, per_worker * workers, agents, args.steps, seconds, setup)


def _agents(spec_or_td, batch_dims: int) -> int:
    """Agents per world: the sum over groups of the agent dim of each (group, "action")."""
    return sum(spec_or_td[key].shape[batch_dims] for key in spec_or_td.keys(True, True)
               if isinstance(key, tuple) and key[-1] == "action")


def run(args) -> dict:
    torch.set_num_threads(1)  # tiny tensors in this process too; llvmpipe gets the cores
    env_kwargs = {"resolution": args.resolution, "seed": 0, "device": args.device}
    if args.agents is not None:
        env_kwargs["num_agents"] = args.agents
    for workers in args.workers if {"parallel", "collect"} & set(args.kinds) else ():
        if args.worlds % workers:
            raise SystemExit(f"--worlds {args.worlds} must be divisible by every --workers value ({workers})")
    for lp in args.lp_threads:
        if lp != "default" and not (lp.isdigit() and int(lp) >= 1):
            raise SystemExit(f"--lp-threads values must be 'default' or positive integers, got {lp!r}")
    too_many = [n for n in args.processes if n > args.worlds] if "processes" in args.kinds else []
    if too_many:
        raise SystemExit(f"--processes values must be at most --worlds ({args.worlds}), got {too_many[0]}")
    load_before = os.getloadavg()
    rows = []
    if "single" in args.kinds:
        progress(f"single: {args.env} {args.worlds} worlds at {args.resolution}px, {args.steps} steps")
        rows.append(measure_single(args, env_kwargs))
    for kind, measure in (("parallel", measure_parallel), ("collect", measure_collector)):
        if kind not in args.kinds:
            continue
        for lp in args.lp_threads:
            for workers in args.workers:
                progress(f"{kind}: {workers} worker(s) x {args.worlds // workers} worlds, LP_NUM_THREADS={lp}")
                rows.append(measure(args, env_kwargs, workers, lp))
    if "processes" in args.kinds:
        for processes in args.processes:
            progress(f"processes: {args.worlds} worlds over {processes} worker process(es)")
            rows.append(measure_processes(args, env_kwargs, processes))
    single = next((r for r in rows if r["kind"] == "single"), None)
    for row in rows:
        if row["kind"] == "processes" and single is not None:
            row["ratio_to_single"] = row["env_steps_per_s"] / single["env_steps_per_s"]
    scaling = []
    for kind in ("parallel", "collect"):
        for lp in args.lp_threads:
            by_workers = {r["workers"]: r for r in rows if r["kind"] == kind and r["lp_num_threads"] == lp}
            if 1 in by_workers and 2 in by_workers:
                scaling.append({"kind": kind, "lp_num_threads": lp,
                                "ratio_2_over_1": by_workers[2]["env_steps_per_s"] / by_workers[1]["env_steps_per_s"]})
    lp_effect = []
    for kind in ("parallel", "collect"):
        for workers in args.workers:
            by_lp = {r["lp_num_threads"]: r for r in rows if r["kind"] == kind and r["workers"] == workers}
            if "default" in by_lp:
                for lp, row in by_lp.items():
                    if lp != "default":
                        lp_effect.append({"kind": kind, "workers": workers, "lp_num_threads": lp,
                                          "ratio_over_default": row["env_steps_per_s"]
                                          / by_lp["default"]["env_steps_per_s"]})
    best = max(rows, key=lambda r: r["env_steps_per_s"]) if rows else None
    # Other processes on the machine distort every number here: the load averages tell.
    return {"benchmark": "parallel", "machine": machine(), "env": args.env, "resolution": args.resolution,
            "device": args.device,
            "cpu_count": os.cpu_count(), "load_avg_before": load_before, "load_avg_after": os.getloadavg(),
            "results": rows, "scaling": scaling, "lp_effect": lp_effect,
            "best": None if best is None else {k: best[k] for k in ("kind", "workers", "lp_num_threads",
                                                                     "env_steps_per_s")}}
