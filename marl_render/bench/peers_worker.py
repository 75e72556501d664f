"""Worker process of `python -m marl_render.bench peers`: one system, stepped in timed blocks on request.

Started as a script (``PYTHON peers_worker.py``) by the driver, with the Python of the venv
that holds the system: the peers' side venvs (Melting Pot, MPE, PyBatchRender) do not have
marl_render installed, so this file imports only the standard library at the top and each
system's own packages when that system is built.

Protocol: one JSON object per line on stdin, one reply per line on stdout.

  {"op": "setup", "system": NAME, "config": {...}}  -> {"info": {...}}   build, reset, warm up
  {"op": "block", "seconds": S, "reset": bool}       -> {"steps", "wall", "cpu", "resets", "reset_wall", "reset_cpu"}
  {"op": "close"}                                    -> {} and exit

A block optionally starts with a reset, then steps with random actions for S seconds; a
reset that an ending episode needs inside the block is made and timed too.
"wall" and "cpu" cover the whole block (cpu: time.process_time of this process, which counts
all its threads, the GL rasteriser's included); "reset_wall" / "reset_cpu" the resets in it.
A failing request is answered with {"error": traceback}. Anything the libraries print goes
to stderr: stdout carries the protocol only.
"""
from __future__ import annotations

import importlib
import importlib.metadata
import json
import os
import sys
import time
import traceback

# Started as a script, Python puts this folder first on sys.path, where bench's own modules (profile.py,
# env.py, ...) shadow the standard library's and the systems' modules of those names: cProfile's `import
# profile` found bench/profile.py, which broke PyBatchRender's import (its envs' registration swallowed the
# ImportError: "Unknown environment: 'CartPole-v0'"). The systems import from their venvs only.
HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [entry for entry in sys.path if os.path.abspath(entry or os.curdir) != HERE]

WARMUP_STEPS = 5


def _version(distribution: str):
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


class MeltingPot:
    """A Melting Pot substrate (dm-meltingpot on dmlab2d): every player's RGB view each step."""

    def __init__(self, substrate: str = "commons_harvest__open", seed: int = 0):
        import numpy as np
        from meltingpot import substrate as substrates

        config = substrates.get_config(substrate)
        self.env = substrates.build(substrate, roles=config.default_player_roles)
        action_spec = self.env.action_spec()
        self.agents, self.num_actions = len(action_spec), action_spec[0].num_values
        self.rng = np.random.default_rng(seed)
        view = self.env.observation_spec()[0]["RGB"].shape
        self.info = {"system": "meltingpot", "substrate": substrate, "agents": self.agents, "worlds": 1,
                     "agent_view": list(view),
                     "episode_steps": expected_episode_steps(config.lab2d_settings_builder(
                         config=config, roles=config.default_player_roles)),
                     "episode_rule": "StochasticIntervalEpisodeEnding (expected length)",
                     "versions": {name: _version(name) for name in ("dm-meltingpot", "dmlab2d", "tensorflow")}}

    def reset(self):
        self.env.reset()

    def step(self) -> bool:
        return self.env.step(self.rng.integers(0, self.num_actions, self.agents).tolist()).last()


def expected_episode_steps(settings) -> float | None:
    """Mean episode length of a substrate that ends episodes by StochasticIntervalEpisodeEnding:
    at least `minimumFramesPerEpisode` steps, then every `intervalLength` steps it ends with
    probability p, so on average interval * (1 - p) / p more (capped at maxEpisodeLengthFrames).
    `settings`: the substrate's lab2d settings. None if it has no such rule."""
    found = []

    def visit(node):
        if isinstance(node, dict) or hasattr(node, "items"):
            items = dict(node.items())
            if items.get("component") == "StochasticIntervalEpisodeEnding":
                found.append(items["kwargs"])
            for value in items.values():
                visit(value)
        elif isinstance(node, (list, tuple)):
            for value in node:
                visit(value)

    visit(settings)
    if not found:
        return None
    rule = found[0]
    p = rule["probabilityTerminationPerInterval"]
    mean = rule["minimumFramesPerEpisode"] + rule["intervalLength"] * (1 - p) / p
    return min(mean, settings.get("maxEpisodeLengthFrames", mean))


class MPE:
    """PettingZoo MPE (mpe2) simple_spread, parallel API; with render=True one rgb_array frame per step."""

    def __init__(self, agents: int = 3, render: bool = True, max_cycles: int = 25, seed: int = 0):
        import numpy as np
        from mpe2 import simple_spread_v3

        self.render = render
        self.env = simple_spread_v3.parallel_env(N=agents, max_cycles=max_cycles,
                                                 render_mode="rgb_array" if render else None)
        self.env.reset(seed=seed)
        self.num_actions = self.env.action_space(self.env.possible_agents[0]).n
        self.rng = np.random.default_rng(seed)
        frame = self.env.render() if render else None
        self.info = {"system": "mpe", "env": "simple_spread_v3", "agents": agents, "worlds": 1,
                     "frame": list(frame.shape) if frame is not None else None, "episode_steps": max_cycles,
                     "versions": {name: _version(name) for name in ("mpe2", "pettingzoo", "pygame-ce")}}

    def reset(self):
        self.env.reset()

    def step(self) -> bool:
        ended = _random_parallel_step(self.env, self.rng, self.num_actions)
        if self.render:
            self.env.render()
        return ended


def _random_parallel_step(env, rng, num_actions: int) -> bool:
    """One step of a PettingZoo parallel env with uniformly random discrete actions; True when
    every agent has left (the episode is over)."""
    agents = env.agents
    draws = rng.integers(0, num_actions, len(agents)).tolist()
    env.step(dict(zip(agents, draws, strict=True)))
    return not env.agents


class MarlRenderParallel:
    """One world of a marl-render task through the PettingZoo parallel API (make_parallel_env)."""

    def __init__(self, env: str, agents: int | None = None, resolution: int = 64, max_steps: int | None = None,
                 seed: int = 0, impostors: object = "auto"):
        import numpy as np

        from marl_render.wrappers.pettingzoo import make_parallel_env

        kwargs = {"resolution": resolution, "seed": seed, "impostors": impostors}
        if agents is not None:
            kwargs["num_agents"] = agents
        if max_steps is not None:
            kwargs["max_steps"] = max_steps
        self.env = make_parallel_env(env, **kwargs)
        self.env.reset(seed=seed)
        self.num_actions = self.env.action_space(self.env.possible_agents[0]).n
        self.rng = np.random.default_rng(seed)
        core = self.env.core
        self.info = {"system": "marl_render", "api": "pettingzoo parallel", "env": env, "agents": core.num_agents,
                     "worlds": 1, "agent_view": list(self.env.observation_space(self.env.possible_agents[0]).shape),
                     "episode_steps": core.max_steps, "versions": {"marl-render": _version("marl-render")},
                     "lp_num_threads": os.environ.get("LP_NUM_THREADS")}

    def reset(self):
        self.env.reset()

    def step(self) -> bool:
        return _random_parallel_step(self.env, self.rng, self.num_actions)


class MarlRenderCore:
    """A batched marl-render core (make_env, autoreset next_step) stepped as `bench env` steps it."""

    ACTION_BATCHES = 64  # pre-drawn random action batches, used in turn

    def __init__(self, env: str, worlds: int, agents: int | None = None, resolution: int = 64,
                 max_steps: int | None = None, seed: int = 0, compile_physics: bool = False,
                 impostors: object = "auto"):
        import torch

        import marl_render.envs as envs
        from marl_render.bench.env import draw_actions

        kwargs = {"num_worlds": worlds, "resolution": resolution, "seed": seed, "autoreset": "next_step",
                  "compile_physics": compile_physics, "impostors": impostors}
        if agents is not None:
            kwargs["num_agents"] = agents
        if max_steps is not None:
            kwargs["max_steps"] = max_steps
        self.env = envs.make_env(env, **kwargs)
        self.env.reset(seed=seed)
        core = self.env
        shape = (core.num_worlds, core.num_agents, *((core.action_dim,) if core.continuous else ()))
        self.actions = [torch.from_numpy(a).reshape(shape) for a in draw_actions(core, self.ACTION_BATCHES, seed)]
        self.count = 0
        self.info = {"system": "marl_render", "api": "core", "env": env, "agents": core.num_agents,
                     "worlds": core.num_worlds, "agent_view": [*core.resolution, 3], "episode_steps": core.max_steps,
                     "physics_compiled": core.physics_compiled,
                     "versions": {"marl-render": _version("marl-render")},
                     "lp_num_threads": os.environ.get("LP_NUM_THREADS")}

    def reset(self):
        self.env.reset()

    def step(self) -> bool:
        self.env.step(self.actions[self.count % len(self.actions)])
        self.count += 1
        return False  # worlds reset themselves (autoreset) inside step


class PyBatchRender:
    """A PyBatchRender TorchRL env (its envs auto-reset inside step), stepped as its own benchmark does."""

    def __init__(self, env: str = "CartPole-v0", worlds: int = 16, resolution: int = 64):
        import pybatchrender as pbr

        self.env = pbr.envs.make(env, num_scenes=worlds, tile_resolution=(resolution, resolution), render=True,
                                 offscreen=True)
        self.td = self.env.reset()
        self.step()
        pixels = self.td.get("pixels", None)  # its envs leave pixels out when rendering fails
        expected = (worlds, 3, resolution, resolution)
        if pixels is None or tuple(pixels.shape) != expected:
            raise RuntimeError(f"PyBatchRender {env} returned pixels of shape "
                               f"{None if pixels is None else tuple(pixels.shape)}, expected {expected}")
        self.info = {"system": "pybatchrender", "env": env, "agents": 1, "worlds": worlds,
                     "agent_view": [resolution, resolution, 3], "episode_steps": None,
                     "versions": {name: _version(name) for name in ("pybatchrender", "panda3d", "torch", "torchrl")},
                     "lp_num_threads": os.environ.get("LP_NUM_THREADS")}

    def reset(self):
        self.td = self.env.reset()

    def step(self) -> bool:
        td = self.td
        td["action"] = self.env.action_spec.rand()
        self.td = self.env.step(td)["next"]
        return False


SYSTEMS = {"meltingpot": MeltingPot, "mpe": MPE, "marl_render_parallel": MarlRenderParallel,
           "marl_render_core": MarlRenderCore, "pybatchrender": PyBatchRender}


def run_block(system, seconds: float, reset: bool) -> dict:
    """A reset if asked, then steps for `seconds` (at least one step); see the module docstring."""
    resets, reset_wall, reset_cpu = 0, 0.0, 0.0

    def timed_reset():
        nonlocal resets, reset_wall, reset_cpu
        wall, cpu = time.perf_counter(), time.process_time()
        system.reset()
        reset_wall += time.perf_counter() - wall
        reset_cpu += time.process_time() - cpu
        resets += 1

    start_wall, start_cpu = time.perf_counter(), time.process_time()
    if reset:
        timed_reset()
    deadline = time.perf_counter() + seconds  # of stepping: a slow first reset does not shorten it
    steps = 0
    while True:
        ended = system.step()
        steps += 1
        if ended:
            timed_reset()
        if time.perf_counter() >= deadline:
            break
    return {"steps": steps, "wall": time.perf_counter() - start_wall, "cpu": time.process_time() - start_cpu,
            "resets": resets, "reset_wall": reset_wall, "reset_cpu": reset_cpu}


def handle(request: dict, state: dict) -> dict:
    op = request.get("op")
    if op == "setup":
        start = time.perf_counter()
        if request.get("system") not in SYSTEMS:
            raise ValueError(f"unknown system {request.get('system')!r}; expected one of {sorted(SYSTEMS)}")
        system = SYSTEMS[request["system"]](**request.get("config", {}))
        system.reset()
        for _ in range(WARMUP_STEPS):
            if system.step():
                system.reset()
        state["system"] = system
        return {"info": {**system.info, "setup_s": time.perf_counter() - start, "python": sys.version.split()[0]}}
    if op == "block":
        return run_block(state["system"], float(request["seconds"]), bool(request.get("reset", False)))
    if op == "close":
        return {}
    raise ValueError(f"unknown op {op!r}; expected setup, block or close")


def main() -> int:
    protocol = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # what the libraries print (also from C) goes to stderr
    sys.stdout = sys.stderr
    state = {}
    for line in sys.stdin:
        request = json.loads(line)
        try:
            reply = handle(request, state)
        except Exception:
            reply = {"error": traceback.format_exc()}
        protocol.write(json.dumps(reply) + "\n")
        if request.get("op") == "close":
            break
    return 0


if __name__ == "__main__":
    sys.exit(main())
