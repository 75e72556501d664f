"""Distributed collection with TorchRL's torch.distributed collector, two local workers.

    python examples/distributed_collect.py [--launcher mp|delayed] [--env spread] [--workers 2]
        [--worlds 8] [--resolution 32] [--steps-per-batch 8] [--batches 4] [--timeout 180] [--json] [--out DIR]

``torchrl.collectors.distributed.DistributedCollector(sync=True, backend="gloo")`` in the
main process is rank 0; each worker (ranks 1..N, 'spawn', each with its own GL context and
its own env of --worlds worlds, seeded --seed + rank - 1) runs a TorchRL Collector and sends
its batches to rank 0 over torch.distributed; rank 0 stacks them into one batch
[workers, worlds, steps] per iteration.

  --launcher mp       the collector starts the worker processes itself (launcher="mp").
  --launcher delayed  the way to use other machines: the worker processes are started
                      independently (here by this script, on a cluster by your launcher on
                      each node) and wait at the rendezvous (TorchRL's
                      ``_distributed_init_delayed``, what its submitit_delayed_launcher
                      runs); the collector uses launcher="submitit_delayed" and sends them
                      the env constructor, policy and batch size (no submitit needed).

The policy is a random policy with a parameter (per-action logits); after each batch the
main process changes the logits and calls ``update_policy_weights_()``, so the next batch
shows whether the workers received them ("favoured action share").

Everything runs on 127.0.0.1: rendezvous on tcp://localhost:PORT (PORT free, PORT+1 and
PORT+2 for TorchRL's stores), gloo pinned to the loopback interface (GLOO_SOCKET_IFNAME=lo).
(TorchRL takes rank 0's address for the weight-sync store, and for the rendezvous with
--launcher delayed, from socket.gethostbyname(socket.gethostname()): 127.0.0.1 where the
host name maps to loopback, as in most containers; the script says so if it does not.
TCPStore servers listen on all interfaces, as torch.distributed does.)
A watchdog ends the run (workers included) after --timeout seconds, exit status 124.
For several machines see docs/distributed.md.
"""
from __future__ import annotations

import argparse
import functools
import json
import multiprocessing as mp
import os
import socket
import sys
import threading
import time

import torch
from torch import nn


class LogitsRandomPolicy(nn.Module):
    """Samples each agent's action from softmax(logits) over its valid actions (action_mask).

    `logits` [num_actions] is a parameter shared by all agents, so the distributed collector
    has weights to send: zeros = uniform random actions."""

    def __init__(self, groups, num_actions: int):
        super().__init__()
        self.groups = list(groups)
        self.logits = nn.Parameter(torch.zeros(num_actions))

    def forward(self, td):
        # Imported here, as main() imports marl_render: every process the collector spawns runs this
        # file's top level again, and most of them never act.
        from marl_render.envs.masking import with_fallback

        for group in self.groups:
            mask = td.get((group, "action_mask"))
            # An agent whose mask allows nothing (one out of the episode) plays 0, which the step ignores.
            logits = self.logits.detach().expand(mask.shape).masked_fill(~with_fallback(mask), float("-inf"))
            td.set((group, "action"), torch.distributions.Categorical(logits=logits).sample())
        return td


def free_port_block(n: int = 3, host: str = "127.0.0.1") -> int:
    """A port P with P..P+n-1 free on `host` (DistributedCollector uses P and P+1, its weight
    sync store P+2)."""
    for _ in range(100):
        with socket.socket() as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
        if port + n - 1 > 65535:
            continue
        ok = True
        for p in range(port + 1, port + n):
            with socket.socket() as s:
                try:
                    s.bind((host, p))
                except OSError:
                    ok = False
                    break
        if ok:
            return port
    raise RuntimeError("no block of free ports found on 127.0.0.1")


def start_watchdog(seconds: float) -> threading.Timer:
    """After `seconds`, kill the worker processes this process started and exit(124)."""

    def expire():
        print(f"distributed_collect: timed out after {seconds:.0f} s; stopping", file=sys.stderr, flush=True)
        for child in mp.active_children():
            try:
                os.kill(child.pid, 9)
            except OSError:
                pass
        os._exit(124)

    timer = threading.Timer(seconds, expire)
    timer.daemon = True
    timer.start()
    return timer


def remote_worker(rank: int, master_addr: str, port: int, world_size: int, backend: str = "gloo") -> None:
    """What one worker node runs for --launcher delayed: join the rendezvous as `rank`, then
    receive the env constructor / policy from rank 0 and collect until told to stop."""
    os.environ.setdefault("GLOO_SOCKET_IFNAME", "lo")  # loopback here; the node's NIC on a cluster
    from torchrl.collectors.distributed.generic import _distributed_init_delayed

    _distributed_init_delayed(rank, backend, master_addr, port, world_size)


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--launcher", choices=("mp", "delayed"), default="mp", help="how workers start (see above)")
    parser.add_argument("--env", default="spread", help="environment")
    parser.add_argument("--workers", type=int, default=2, help="worker processes")
    parser.add_argument("--worlds", type=int, default=8, help="worlds per worker")
    parser.add_argument("--resolution", type=int, default=32, help="pixels per side of each view")
    parser.add_argument("--steps-per-batch", type=int, default=8, help="steps per worker per batch")
    parser.add_argument("--batches", type=int, default=4, help="batches to collect")
    parser.add_argument("--seed", type=int, default=0, help="worker r (1..N) gets seed + r - 1")
    parser.add_argument("--port", type=int, default=0, help="rendezvous port (0: a free one)")
    parser.add_argument("--timeout", type=float, default=180.0, help="watchdog, seconds for the whole run")
    parser.add_argument("--out", default=None, help="folder: write summary.json and batches.pt (the list of "
                                                    "batches, TensorDicts) there")
    parser.add_argument("--save", default=None, help="torch.save the list of batches (TensorDicts) to this file")
    parser.add_argument("--json", action="store_true", help="print a JSON summary as the last line")
    return parser.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    watchdog = start_watchdog(args.timeout)
    os.environ.setdefault("GLOO_SOCKET_IFNAME", "lo")  # inherited by the spawned workers
    mp.set_start_method("spawn", force=True)  # GL contexts do not survive fork

    from torchrl.collectors.distributed import DistributedCollector

    from marl_render.wrappers.torchrl import make_torchrl_env

    # Groups and action count from a one-world env (this process renders for the
    # collector's template batch anyway; the context is per process).
    probe = make_torchrl_env(args.env, num_worlds=1, resolution=8)
    groups, num_actions = list(probe.group_map), probe.core.num_actions
    probe.close()
    if num_actions is None:
        raise SystemExit("this example's policy samples discrete actions; pick a discrete env")
    policy = LogitsRandomPolicy(groups, num_actions)

    creators = [functools.partial(make_torchrl_env, args.env, num_worlds=args.worlds, resolution=args.resolution,
                                  seed=args.seed + rank) for rank in range(args.workers)]
    frames_per_batch = args.workers * args.worlds * args.steps_per_batch
    port = args.port or free_port_block()
    host = "localhost" if args.launcher == "mp" else socket.gethostbyname(socket.gethostname())
    print(f"rank 0: {args.workers} workers x {args.worlds} worlds of {args.env} at {args.resolution}px, "
          f"launcher {args.launcher}, rendezvous tcp://{host}:{port}, backend gloo", flush=True)
    start = time.perf_counter()
    remote = []
    if args.launcher == "delayed":
        # Stand-ins for processes started on other nodes. Rank 0 binds its rendezvous to
        # socket.gethostbyname(socket.gethostname()) in this mode (TorchRL's choice).
        master = socket.gethostbyname(socket.gethostname())
        if not master.startswith("127."):
            print(f"note: this host name resolves to {master}; rank 0 listens there", file=sys.stderr)
        spawn = mp.get_context("spawn")
        remote = [spawn.Process(target=remote_worker, args=(rank, "127.0.0.1", port, args.workers + 1),
                                name=f"collector-node-{rank}") for rank in range(1, args.workers + 1)]
        for process in remote:
            process.start()
    try:
        collector = DistributedCollector(
            creators, policy, frames_per_batch=frames_per_batch, total_frames=frames_per_batch * args.batches,
            sync=True, launcher="submitit_delayed" if args.launcher == "delayed" else "mp", backend="gloo",
            tcp_port=port, collector_kwargs={"auto_register_policy_transforms": False})
    except BaseException:
        for process in remote:
            process.kill()
        raise
    setup_s = time.perf_counter() - start
    batches, summaries, t_first, t0 = [], [], None, None
    try:
        for i, batch in enumerate(collector):
            now = time.perf_counter()
            if t_first is None:
                t_first = now
            favoured = (i - 1) % num_actions  # set after the previous batch (none for batch 0)
            share = None if i == 0 else float(sum((batch[g, "action"] == favoured).float().mean() for g in groups)
                                              / len(groups))
            pixels = batch[groups[0], "pixels"]
            summaries.append({"shape": list(batch.shape), "pixels_shape": list(pixels.shape),
                              "pixels_dtype": str(pixels.dtype), "favoured_action_share": share})
            print(f"batch {i}: {tuple(batch.shape)} [workers, worlds, steps]; ({groups[0]!r}, 'pixels') "
                  f"{tuple(pixels.shape)} {pixels.dtype}; per-worker mean pixel "
                  f"{[round(v, 2) for v in pixels.float().flatten(1).mean(1).tolist()]}"
                  + ("" if share is None else f"; favoured action {favoured} share {share:.2f}"), flush=True)
            batches.append(batch)
            if i + 1 < args.batches:
                with torch.no_grad():  # a stand-in for a training step: favour action i next batch
                    policy.logits.fill_(-30.0)
                    policy.logits[i % num_actions] = 0.0
                collector.update_policy_weights_()
        end = time.perf_counter()
        t0 = time.perf_counter()
        # The exhausted iterator has told every node to shut down. With launcher="submitit_delayed"
        # collector.shutdown() does not wait for the nodes before closing its stores (the nodes
        # then die with SIGABRT), so wait for them first.
        for process in remote:
            process.join(timeout=30)
    finally:
        t0 = time.perf_counter() if t0 is None else t0
        collector.shutdown()
        for process in remote:
            process.join(timeout=30)
        shutdown_s = time.perf_counter() - t0
    workers = remote or collector.jobs
    exitcodes = [process.exitcode for process in workers]
    agents = sum(batches[0][g, "action"].shape[batches[0].ndim] for g in groups)
    timed = len(batches) - 1
    fps = timed * frames_per_batch / (end - t_first) if timed else float("nan")
    print(f"setup {setup_s:.1f} s (workers start, connect, first frames), shutdown {shutdown_s:.1f} s; "
          f"{fps:.0f} env-steps/s, {fps * agents:.0f} agent-frames/s over batches 1..{len(batches) - 1}; "
          f"worker exit codes {exitcodes}", flush=True)
    summary = {"launcher": args.launcher, "workers": args.workers, "worlds_per_worker": args.worlds,
               "resolution": args.resolution, "port": port, "batches": summaries, "env_steps_per_s": fps,
               "agent_frames_per_s": fps * agents, "setup_s": setup_s, "shutdown_s": shutdown_s,
               "worker_exitcodes": exitcodes}
    if args.save:
        torch.save(batches, args.save)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        torch.save(batches, os.path.join(args.out, "batches.pt"))
        with open(os.path.join(args.out, "summary.json"), "w") as f:
            json.dump(summary, f, indent=2)
        print(f"wrote {os.path.join(args.out, 'summary.json')} and batches.pt", flush=True)
    if args.json:
        print(json.dumps(summary))
    watchdog.cancel()
    return summary


if __name__ == "__main__":
    main()
