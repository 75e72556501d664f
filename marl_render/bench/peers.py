"""marl-render against peer systems, on the same machine, in alternating timed blocks.

Each comparison starts one worker process (peers_worker.py) per system and configuration,
each with the Python of the venv that holds that system, and talks to it over its stdin /
stdout. The workers take turns block by block (who goes first rotates each round, after one
untimed warm-up round), so every system sees the same machine conditions; each number is the
median over the rounds. The peers' venvs are built by `make peers-venvs` (Makefile; pins in
constraints-peers-*.txt):

  meltingpot     Melting Pot commons_harvest__open (7 players, an 88x88 RGB view each;
                 .venv-meltingpot) against marl-render commons with 7 agents at 88 px: one world
                 through make_parallel_env (PettingZoo parallel API) and the batched core
                 (make_env) at --worlds worlds. Every round starts with a reset.
  mpe            PettingZoo MPE simple_spread_v3 (mpe2; 3 agents; .venv-mpe) with one 700x700
                 rgb_array render per step and without rendering, against marl-render spread
                 with 3 agents at 64 px through make_parallel_env, both with 25-step episodes.
  pybatchrender  PyBatchRender CartPole-v0 (.venv-pybatchrender) at --pbr-worlds worlds, 64 px,
                 stepped as its own benchmark steps it, against marl-render cartpole's batched
                 core stepped as `bench env` steps it. Both reset finished worlds inside step.

Actions are uniformly random. Rates: "per_s" counts steps without the resets that are timed
apart (an explicit reset, or one an ending episode needs); "incl_resets" amortises the
median reset over an episode of the system's length L: L / (L / rate + reset). Melting Pot
ends episodes at random (at least 1000 steps, then with probability 0.15 every 100 steps),
so L is its expected length, and marl-render commons runs with max_steps = L rounded.
Resets inside a step (the batched cores' autoreset, PyBatchRender) are in both rates.
"per_cpu_s" divides by the worker's process_time (all its threads) instead of wall time.
env-steps count world steps; agent-frames rendered agent views (env-steps x agents).
Ratios are marl-render over the peer, of env-steps (the agents per world match within each
comparison, so these are also the agent-frame ratios).
"""
from __future__ import annotations

import json
import math
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time

from .common import machine, positive_int_argument, positive_seconds_argument, progress, write_report

COMPARISONS = ("meltingpot", "mpe", "pybatchrender")
WORKER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "peers_worker.py")
# comparison -> (venv option, default venv, Makefile target that builds it)
VENVS = {"meltingpot": ("meltingpot_venv", ".venv-meltingpot", "meltingpot-venv"),
         "mpe": ("mpe_venv", ".venv-mpe", "mpe-venv"),
         "pybatchrender": ("pybatchrender_venv", ".venv-pybatchrender", "pybatchrender-venv")}
RATE_NAMES = {"per_s": "/s", "per_s_incl_resets": "/s incl. resets", "per_cpu_s": "/CPU-s",
              "per_cpu_s_incl_resets": "/CPU-s incl. resets"}
RATE_KEYS = tuple(RATE_NAMES)
STDERR_TAIL = 3000  # characters of a failed worker's stderr quoted in the error
# The workers get the environment this process started with: marl_render sets defaults of its
# own in os.environ when it makes a GL context (LP_NUM_THREADS), which the peers must not inherit.
LAUNCH_ENVIRON = dict(os.environ)


def add_arguments(parser):
    parser.add_argument("--only", nargs="+", choices=COMPARISONS, default=list(COMPARISONS),
                        help="comparisons to run (default: all)")
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds (>= 3; medians are reported)")
    parser.add_argument("--block-seconds", type=positive_seconds_argument, default=1.0,
                        help="stepping time of one block")
    parser.add_argument("--worlds", type=positive_int_argument, nargs="+", default=[16, 64, 256],
                        help="worlds of the batched marl-render commons in the meltingpot comparison")
    parser.add_argument("--pbr-worlds", type=positive_int_argument, nargs="+", default=[16, 64],
                        help="worlds of both systems in the pybatchrender comparison")
    for comparison, (dest, default, target) in VENVS.items():
        parser.add_argument("--" + dest.replace("_", "-"), default=default,
                            help=f"venv of the {comparison} peer (built by `make {target}`)")
    parser.add_argument("--compile-physics", action="store_true",
                        help="also run marl-render's cartpole with compile_physics=True against PyBatchRender")
    parser.add_argument("--lp-num-threads", type=positive_int_argument, default=None,
                        help="LP_NUM_THREADS (llvmpipe's rasteriser threads) of every worker; default: each "
                             "system's own (marl-render: 2 per core; llvmpipe's: 1 per core)")
    parser.add_argument("--with-meshes", action="store_true",
                        help="meltingpot: every marl-render row again with spheres as meshes (impostors=False)")
    parser.add_argument("--out", default=None, help="also write DIR/peers.json and DIR/peers.md")


class WorkerError(RuntimeError):
    """A worker answered with an error or exited; the message quotes its traceback or stderr."""


class Worker:
    """One peers_worker.py process running `python`; its stderr goes to a log file."""

    def __init__(self, label: str, python: str, log_dir: str, lp_num_threads: int | None = None):
        self.label = label
        self.log_path = os.path.join(log_dir, f"{label}.log")
        self._log = open(self.log_path, "w")
        env = dict(LAUNCH_ENVIRON, PYTHONUNBUFFERED="1", SDL_VIDEODRIVER="dummy", SDL_AUDIODRIVER="dummy",
                   TF_CPP_MIN_LOG_LEVEL="2")
        if lp_num_threads is not None:
            env["LP_NUM_THREADS"] = str(lp_num_threads)
        self.process = subprocess.Popen([python, WORKER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        stderr=self._log, text=True, env=env)
        self.info = None

    def request(self, message: dict) -> dict:
        try:
            self.process.stdin.write(json.dumps(message) + "\n")
            self.process.stdin.flush()
            line = self.process.stdout.readline()
        except BrokenPipeError:
            line = ""
        if not line:
            raise WorkerError(f"worker {self.label} exited (code {self.process.wait()}) during {message['op']}; "
                              f"its stderr ends with:\n{self.stderr_tail()}")
        reply = json.loads(line)
        if "error" in reply:
            raise WorkerError(f"worker {self.label} failed in {message['op']}:\n{reply['error']}")
        return reply

    def setup(self, system: str, config: dict) -> dict:
        self.info = self.request({"op": "setup", "system": system, "config": config})["info"]
        return self.info

    def block(self, seconds: float, reset: bool) -> dict:
        return self.request({"op": "block", "seconds": seconds, "reset": reset})

    def stderr_tail(self) -> str:
        self._log.flush()
        with open(self.log_path) as f:
            return f.read()[-STDERR_TAIL:]

    def begin_close(self):
        """Ask the worker to exit without waiting for it (several exit at once)."""
        if self.process.poll() is None and not self.process.stdin.closed:
            try:
                self.process.stdin.write(json.dumps({"op": "close"}) + "\n")
                self.process.stdin.close()
            except OSError:
                pass

    def close(self):
        self.begin_close()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.process.stdout.close()
        self._log.close()


# --------------------------------------------------------------------------- summaries (pure)
def summarise(info: dict, blocks: list) -> dict:
    """Median rates of one system over its timed blocks (worker replies); see the module docstring."""
    if not blocks:
        raise ValueError("summarise needs at least one block")
    worlds, agents, length = info["worlds"], info["agents"], info.get("episode_steps")
    per_s = statistics.median(b["steps"] / (b["wall"] - b["reset_wall"]) for b in blocks)
    per_cpu_s = statistics.median(b["steps"] / (b["cpu"] - b["reset_cpu"]) for b in blocks)
    with_resets = [b for b in blocks if b["resets"]]
    reset_s = statistics.median(b["reset_wall"] / b["resets"] for b in with_resets) if with_resets else None
    reset_cpu_s = statistics.median(b["reset_cpu"] / b["resets"] for b in with_resets) if with_resets else None
    steps = {"per_s": per_s, "per_cpu_s": per_cpu_s,
             "per_s_incl_resets": amortise(per_s, reset_s, length),
             "per_cpu_s_incl_resets": amortise(per_cpu_s, reset_cpu_s, length)}
    block_rates = [b["steps"] / (b["wall"] - b["reset_wall"]) for b in blocks]
    summary = {"env_steps": {key: worlds * value for key, value in steps.items()},
               "agent_frames": {key: worlds * agents * value for key, value in steps.items()}
               if info.get("agent_view") else None,
               "reset_s": reset_s, "reset_cpu_s": reset_cpu_s, "episode_steps": length,
               "cpu_per_wall": statistics.median((b["cpu"] - b["reset_cpu"]) / (b["wall"] - b["reset_wall"])
                                                 for b in blocks),
               "spread": (max(block_rates) - min(block_rates)) / per_s, "rounds": len(blocks),
               "steps_per_block": statistics.median(b["steps"] for b in blocks)}
    return summary


def amortise(rate: float, reset: float | None, length: float | None) -> float:
    """Steps per second with one reset of `reset` seconds every `length` steps (no reset timed: `rate`)."""
    if reset is None or length is None:
        return rate
    return length / (length / rate + reset)


def ratios(ours: dict, peer: dict) -> dict:
    """marl-render over the peer for every env-steps rate (summaries of `summarise`)."""
    return {key: ours["env_steps"][key] / peer["env_steps"][key] for key in RATE_KEYS}


# --------------------------------------------------------------------------- runs
def alternate(workers: list, rounds: int, seconds: float, reset: bool) -> dict:
    """label -> timed blocks: one untimed warm-up round, then `rounds` rounds, the starting worker rotating."""
    blocks = {worker.label: [] for worker in workers}
    for worker in workers:
        worker.block(seconds, reset)
    for r in range(rounds):
        turn = r % len(workers)
        for worker in workers[turn:] + workers[:turn]:
            blocks[worker.label].append(worker.block(seconds, reset))
        progress(f"  round {r + 1}/{rounds}: " + ", ".join(
            f"{label} {b[-1]['steps'] / (b[-1]['wall'] - b[-1]['reset_wall']):.0f} steps/s"
            for label, b in blocks.items()))
    return blocks


def run_group(specs: list, args, reset: bool, log_dir: str) -> dict:
    """specs: (label, python, system, config or a function of the infos so far -> config).
    Returns label -> {"info", "summary", "blocks"}."""
    workers, infos = [], {}
    try:
        for label, python, system, config in specs:
            worker = Worker(label, python, log_dir, args.lp_num_threads)
            workers.append(worker)
            config = config(infos) if callable(config) else config
            progress(f"  setting up {label} ({system} {config})")
            infos[label] = worker.setup(system, config)
        blocks = alternate(workers, args.rounds, args.block_seconds, reset)
    finally:
        for worker in workers:
            worker.begin_close()
        for worker in workers:
            worker.close()
    return {label: {"info": infos[label], "summary": summarise(infos[label], blocks[label]),
                    "blocks": blocks[label]} for label in blocks}


def command_line(args) -> str:
    """The command that runs this measurement again, every option spelled out."""
    words = ["python", "-m", "marl_render.bench", "peers", "--only", *dict.fromkeys(args.only),
             "--rounds", str(args.rounds), "--block-seconds", str(args.block_seconds),
             "--worlds", *map(str, args.worlds), "--pbr-worlds", *map(str, args.pbr_worlds)]
    for dest, default, _ in VENVS.values():
        if getattr(args, dest) != default:
            words += ["--" + dest.replace("_", "-"), getattr(args, dest)]
    if args.compile_physics:
        words.append("--compile-physics")
    if args.lp_num_threads is not None:
        words += ["--lp-num-threads", str(args.lp_num_threads)]
    if args.out:
        words += ["--out", args.out]
    return " ".join(shlex.quote(word) for word in words)


def venv_python(args, comparison: str) -> str:
    dest, _, target = VENVS[comparison]
    python = os.path.join(getattr(args, dest), "bin", "python")
    if not os.path.exists(python):
        raise FileNotFoundError(f"--{dest.replace('_', '-')}: no {python}; build the {comparison} venv with "
                                f"`make {target}` (or `make peers-venvs`)")
    return python


def compare_meltingpot(args, log_dir: str) -> dict:
    def commons(infos, **extra):
        return {"env": "commons", "agents": infos["meltingpot"]["agents"],
                "resolution": infos["meltingpot"]["agent_view"][0],
                "max_steps": round(infos["meltingpot"]["episode_steps"]), **extra}

    specs = [("meltingpot", venv_python(args, "meltingpot"), "meltingpot", {"substrate": "commons_harvest__open"}),
             ("marl_render_parallel", sys.executable, "marl_render_parallel", commons)]
    specs += [(f"marl_render_core_{w}", sys.executable, "marl_render_core",
               lambda infos, w=w: commons(infos, worlds=w)) for w in args.worlds]
    if args.with_meshes:  # the same with spheres drawn as meshes (impostors=False): before and after in one run
        specs += [(f"{label}_meshes", python, system,
                   lambda infos, config=config: {**config(infos), "impostors": False})
                  for label, python, system, config in specs[1:]]
    systems = run_group(specs, args, reset=True, log_dir=log_dir)
    peer = systems["meltingpot"]["summary"]
    return {"systems": systems, "ratios": {f"{label}/meltingpot": ratios(system["summary"], peer)
                                           for label, system in systems.items() if label != "meltingpot"}}


def compare_mpe(args, log_dir: str) -> dict:
    python = venv_python(args, "mpe")
    specs = [("mpe_render", python, "mpe", {"agents": 3, "render": True}),
             ("mpe_no_render", python, "mpe", {"agents": 3, "render": False}),
             ("marl_render_parallel", sys.executable, "marl_render_parallel",
              lambda infos: {"env": "spread", "agents": 3, "resolution": 64,
                             "max_steps": infos["mpe_render"]["episode_steps"]})]
    systems = run_group(specs, args, reset=True, log_dir=log_dir)
    ours = systems["marl_render_parallel"]["summary"]
    return {"systems": systems, "ratios": {f"marl_render_parallel/{peer}": ratios(ours, systems[peer]["summary"])
                                           for peer in ("mpe_render", "mpe_no_render")}}


def compare_pybatchrender(args, log_dir: str) -> dict:
    python = venv_python(args, "pybatchrender")
    specs = []
    ours = {"marl_render_core": False}  # label -> compile_physics
    if args.compile_physics:
        ours["marl_render_core_compiled"] = True
    for w in args.pbr_worlds:
        specs += [(f"pybatchrender_{w}", python, "pybatchrender",
                   {"env": "CartPole-v0", "worlds": w, "resolution": 64})]
        specs += [(f"{label}_{w}", sys.executable, "marl_render_core",
                   {"env": "cartpole", "worlds": w, "resolution": 64, "compile_physics": compiled})
                  for label, compiled in ours.items()]
    systems = run_group(specs, args, reset=False, log_dir=log_dir)
    return {"systems": systems, "ratios": {f"{label}_{w}/pybatchrender_{w}": ratios(
        systems[f"{label}_{w}"]["summary"], systems[f"pybatchrender_{w}"]["summary"])
        for w in args.pbr_worlds for label in ours}}


RUNNERS = {"meltingpot": compare_meltingpot, "mpe": compare_mpe, "pybatchrender": compare_pybatchrender}


def run(args) -> dict:
    if args.rounds < 3:
        raise ValueError(f"--rounds must be >= 3 (medians of at least 3 rounds), got {args.rounds}")
    if not 0 < args.block_seconds < math.inf:  # inf would never end a block
        raise ValueError(f"--block-seconds must be a finite number > 0, got {args.block_seconds}")
    if args.lp_num_threads is not None and args.lp_num_threads < 1:
        raise ValueError(f"--lp-num-threads must be >= 1, got {args.lp_num_threads}")
    comparisons = list(dict.fromkeys(args.only))
    pythons = {comparison: venv_python(args, comparison) for comparison in comparisons}  # all checked up front
    start, load_before = time.perf_counter(), os.getloadavg()
    result = {"benchmark": "peers", "machine": {**machine(), "cpu_count": os.cpu_count()},
              "command": command_line(args),
              "settings": {"rounds": args.rounds, "block_seconds": args.block_seconds,
                           "lp_num_threads": args.lp_num_threads, "pythons": pythons},
              "comparisons": {}}
    with tempfile.TemporaryDirectory(prefix="marl_render_peers_") as log_dir:
        for comparison in comparisons:
            progress(f"peers: {comparison}")
            result["comparisons"][comparison] = RUNNERS[comparison](args, log_dir)
    result["seconds"] = time.perf_counter() - start
    result["load_average"] = {"before": load_before, "after": os.getloadavg()}
    if args.out:
        write_report(args.out, "peers", result, markdown(result))
    return result


# --------------------------------------------------------------------------- report
NOTES = """\
## What is compared

* **meltingpot**: dm-meltingpot 2.4.1 on dmlab2d 1.0.2 (Python 3.11), built from its sdist with
  the download of its bot models patched out (`make meltingpot-venv`): substrates work,
  scenarios (which need the bots) do not. `commons_harvest__open` has 7 players; every step
  renders each player's 88x88 RGB view (11 x 11 cells of 8 px sprites, top-down, egocentric)
  and a 144x192 `WORLD.RGB`. Its episodes end at random: at least 1,000 steps, then with
  probability 0.15 every 100 steps (expected length 1,567); its reset rebuilds the level.
  marl-render `commons` (envs/commons.py) is the analogue in 3D: apples in patches that regrow
  only next to apples, a zap that tags agents out for a while; each agent's 88x88 view is a
  perspective render of the arena. It runs with `max_steps` = Melting Pot's expected episode
  length (its default is 300). Rows `marl_render_core_W` are the batched core at W worlds.
* **mpe**: PettingZoo MPE `simple_spread_v3` (mpe2 1.1.1), 3 agents, 25-step episodes (its
  default `max_cycles`); `mpe_render` calls `render()` after every step: one 700x700 frame of the
  whole scene (pygame), no per-agent views. marl-render `spread` with 3 agents renders the 3
  agents' 64x64 views every step, with `max_steps` = 25.
* **pybatchrender**: PyBatchRender (git, branch clawding, commit in the Makefile) `CartPole-v0`,
  64x64, stepped as its own `clawding/tests/benchmark_one_env.py` steps it; marl-render
  `cartpole` stepped as `python -m marl_render.bench env --env cartpole --worlds W` steps it.
  Both reset finished worlds inside `step`. With `--compile-physics`, rows
  `marl_render_core_compiled_W` add marl-render's cartpole with `compile_physics=True` (its
  physics kernel through torch.compile; compiled before the timed blocks). Its own benchmark, to cross-check:
  `cd .venv-pybatchrender/src/pybatchrender && ../../bin/python -m clawding.tests.benchmark_one_env
  --env CartPole-v0 --num-scenes 16 --steps 200` (its "fps" is env-steps/s). Its
  `examples/scripts/cartpole_benchmark.py` needs Python >= 3.12 (nested quotes in an f-string);
  the venv is Python 3.11, the version of the CPU torch 2.13.0 wheel used here.
* Building the venvs downloads TensorFlow and more for Melting Pot (a few minutes). PyBatchRender
  is cloned from GitHub; where GitHub cannot be reached, point `make` at a clone or mirror:
  `make pybatchrender-venv PYBATCHRENDER_GIT=/path/to/pybatchrender` (the commit is pinned).
* Each worker runs with its system's own `LP_NUM_THREADS` unless `--lp-num-threads` is given
  (marl-render sets 2 per core; llvmpipe's default, which PyBatchRender gets, is 1 per core).
* Columns: "/s" excludes resets timed apart, "incl. resets" amortises the median reset over an
  episode of the "episode" length (see marl_render/bench/peers.py); "CPU-s" is the worker's
  process time (all threads); "CPU/wall" the worker's CPU time over wall time while stepping;
  "spread" (max - min) / median of the rounds' steps/s.
"""


def _f(value, digits=0):
    return "-" if value is None else f"{value:,.{digits}f}"


def markdown(result: dict) -> list:
    lines = ["# marl-render against peer systems", "",
             "Written by `python -m marl_render.bench peers` (marl_render/bench/peers.py; its docstring says what",
             "is measured). To reproduce:", "", "```",
             "make peers-venvs      # .venv-meltingpot, .venv-mpe, .venv-pybatchrender (see the Makefile)",
             result["command"], "```", "",
             f"Machine: {result['machine']['gl_renderer']}, {result['machine']['cpu_count']} CPUs; load average "
             f"{result['load_average']['before'][0]:.1f} before, {result['load_average']['after'][0]:.1f} after; "
             f"{result['settings']['rounds']} rounds of {result['settings']['block_seconds']} s blocks, "
             f"{result['seconds']:.0f} s in all.", ""]
    for name, comparison in result["comparisons"].items():
        systems = comparison["systems"]
        lines += [f"## {name}", "", "| system | worlds | agents | episode | reset ms | " + " | ".join(
            f"{unit}{rate}" for unit in ("env-steps", "agent-frames") for rate in RATE_NAMES.values())
            + " | CPU/wall | spread |", "|---|" + "---:|" * 14]
        for label, system in systems.items():
            info, s = system["info"], system["summary"]
            rates = [_f(s[unit] and s[unit][key]) for unit in ("env_steps", "agent_frames") for key in RATE_KEYS]
            reset_ms = _f(s["reset_s"] and 1e3 * s["reset_s"], 1)
            lines.append(f"| {label} | {info['worlds']} | {info['agents']} | {_f(s['episode_steps'])} | {reset_ms} | "
                         + " | ".join(rates) + f" | {s['cpu_per_wall']:.2f} | {s['spread']:.2f} |")
        lines += ["", "| ratio (marl-render / peer) | " + " | ".join(RATE_NAMES.values()) + " |",
                  "|---|---:|---:|---:|---:|"]
        for label, r in comparison["ratios"].items():
            lines.append(f"| {label} | " + " | ".join(f"{r[key]:.2f}" for key in RATE_KEYS) + " |")
        lines.append("")
    return lines + NOTES.splitlines()
