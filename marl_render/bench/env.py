"""Environment throughput: physics + render + readback with random actions.

`--env all` runs every registered environment. env-steps/s counts world steps
(W per batched step); agent-frames/s counts rendered agent views.

`--api` picks the front end(s) that step the environment: `core` (the batched core,
make_env), `vec` (the gymnasium VectorEnv, make_vec_env), `sb3` (the Stable-Baselines3
VecEnv, make_sb3_env; needs the `sb3` extra), `jax` (make_jax_env: JAX arrays in and out
through DLPack; needs the `jax` extra). With several, they run in the same
process on the same pre-drawn actions, taking turns step by step (blocks of steps per
front end were measured to favour whichever runs second), and each row gets
`ratio_to_core` (its env-steps/s over the core's in this run). On a shared machine that
ratio is noisy; `front_end_share` is steadier: the share of each step spent outside the
core's own ``step`` (the front end's conversions), timed around the core's step. The core, `vec`
and `jax` auto-reset in gymnasium's next-step mode; `sb3` resets in the same step (SB3's
convention), which renders twice on a step where a world ends.

`--readback` picks how frames reach the env's device (the renderer's readback: "auto",
"gpu", "host", and "pbo" = through the GL pack buffer to the host); with several, they
take turns step by step as the front ends do, and each row gets `ratio_to_first_readback`.
`--impostors off auto` draws spheres as meshes / as impostors (the default, marl_render/render/impostors.py);
with both, they take turns step by step too, and each row gets `ratio_to_first_impostors`: the
before/after of impostors from one run.
Every row splits the agents' render per step into `render_ms` {pack, cull, draw, read,
copy} (BatchRenderer.last_timings).
"""
from __future__ import annotations

import itertools
import time

import numpy as np
import torch

from marl_render.render.renderer import BatchRenderer
from marl_render.util.extras import require

from .common import env_name_or_all_argument, machine, positive_int_argument, progress

APIS = ("core", "vec", "sb3", "jax")
READBACKS = BatchRenderer.READBACKS[:-1]  # "copy" is the renderer's own ablation (bench effects)
API_EXTRAS = {"sb3": ("sb3", "stable_baselines3"), "jax": ("jax", "jax")}  # api -> (extra, module it needs)


def add_arguments(parser):
    parser.add_argument("--env", default="cartpole", type=env_name_or_all_argument, help="environment name, or 'all'")
    parser.add_argument("--worlds", type=positive_int_argument, nargs="+", default=[256],
                        help="worlds per env (several: one row each)")
    parser.add_argument("--agents", type=positive_int_argument, nargs="+", default=[None],
                        help="agents per world (env default if omitted; several: one row each)")
    parser.add_argument("--resolution", type=positive_int_argument, nargs="+", default=[64])
    parser.add_argument("--steps", type=positive_int_argument, default=30, help="timed steps per front end")
    parser.add_argument("--continuous", action="store_true")
    parser.add_argument("--heldout", default=None, help="a held-out scenario of --env: its focal-only env, bots "
                        "included (agents and agent-frames count the focal agents)")
    parser.add_argument("--device", default="cpu",
                        help="torch device of the env's tensors (e.g. cuda); the GL device is chosen by EGL")
    parser.add_argument("--api", nargs="+", choices=APIS, default=["core"],
                        help="front end(s) to step through; several take turns in one run (default: core)")
    parser.add_argument("--readback", nargs="+", choices=READBACKS, default=["auto"],
                        help="how frames reach the device (several take turns in one run; pbo: through the GL "
                             "pack buffer to the host)")
    parser.add_argument("--impostors", nargs="+", choices=["off", "auto"], default=["auto"],
                        help="spheres as meshes (off) or impostors (auto, the default); both take turns in one run")


class Stepper:
    """One front end of one environment, stepped with pre-drawn numpy actions [num_envs, ...]."""

    def __init__(self, api: str, name: str, kwargs: dict, readback: str = "auto", impostors: str = "auto"):
        import marl_render.envs as envs  # the front ends are imported on use (sb3 and jax are optional extras)

        self.api, self.readback, self.impostors = api, readback, impostors
        kwargs = {**kwargs, "readback": readback, "impostors": "auto" if impostors == "auto" else False}
        if api == "core":
            self.env = envs.make_env(name, autoreset="next_step", **kwargs)
            self.core = self.env
            self.env.reset(seed=0)
            shape = (self.core.num_worlds, self.core.num_agents, *((self.core.action_dim,) if self.core.continuous
                                                                   else ()))
            self.step = lambda actions: self.env.step(torch.from_numpy(actions).reshape(shape))
        elif api == "vec":
            self.env = envs.make_vec_env(name, **kwargs)
            self.core = self.env.core
            self.env.reset(seed=0)
            self.step = self.env.step
        elif api == "jax":
            import jax.numpy as jnp

            self.env = envs.make_jax_env(name, autoreset="next_step", **kwargs)
            self.core = self.env.core
            self.env.reset(seed=0)
            shape = (self.core.num_worlds, self.core.num_agents, *((self.core.action_dim,) if self.core.continuous
                                                                   else ()))
            self.step = lambda actions: self.env.step(jnp.asarray(actions).reshape(shape))
        else:
            self.env = envs.make_sb3_env(name, **kwargs)
            self.core = self.env.venv.core
            self.env.seed(0)
            self.env.reset()
            self.step = self.env.step

        # Time the core's own step inside the front end's: the rest is the front end's cost.
        self.core_seconds = 0.0
        core_step = self.core.step

        def timed_core_step(actions):
            start = time.perf_counter()
            try:
                return core_step(actions)
            finally:
                self.core_seconds += time.perf_counter() - start

        self.core.step = timed_core_step

    def close(self):
        del self.core.step
        self.env.close()


def draw_actions(core, count: int, seed: int = 0) -> list:
    """`count` batches of uniformly random valid actions as numpy [W * A(, action_dim)]."""
    rng = np.random.default_rng(seed)
    n = core.num_worlds * core.num_agents
    if core.continuous:
        return [rng.uniform(-1, 1, (n, core.action_dim)).astype(np.float32) for _ in range(count)]
    return [rng.integers(0, core.num_actions, n) for _ in range(count)]


def measure(name: str, worlds: int, resolution: int, steps: int, agents=None, continuous=False,
            apis=("core",), device: str = "cpu", heldout: str | None = None, readbacks=("auto",),
            impostors=("auto",)) -> list:
    kwargs = {"num_worlds": worlds, "resolution": resolution, "continuous": continuous, "seed": 0, "device": device}
    if heldout is not None:
        kwargs["heldout"] = heldout
    # CUDA work is asynchronous: wait for it before reading the clock, or a step is timed short.
    synchronize = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    if agents is not None:
        kwargs["num_agents"] = agents
    variants = [(api, readback, drawn) for drawn in impostors for readback in readbacks for api in apis]
    steppers = []
    try:
        for api, readback, drawn in variants:
            steppers.append(Stepper(api, name, kwargs, readback, drawn))
        core = steppers[0].core
        warmup = 3
        actions = draw_actions(core, warmup + steps)
        seconds = dict.fromkeys(variants, 0.0)
        render_seconds = {variant: {} for variant in variants}
        for a in actions[:warmup]:
            for stepper in steppers:
                stepper.step(a)
        for stepper in steppers:
            stepper.core_seconds = 0.0
        for k, a in enumerate(actions[warmup:]):
            turn = k % len(steppers)  # who goes first rotates, so that no front end always follows another
            for stepper in steppers[turn:] + steppers[:turn]:
                variant = (stepper.api, stepper.readback, stepper.impostors)
                synchronize()
                start = time.perf_counter()
                stepper.step(a)
                synchronize()
                seconds[variant] += time.perf_counter() - start
                for stage, spent in stepper.core.renderer.last_timings.items():
                    render_seconds[variant][stage] = render_seconds[variant].get(stage, 0.0) + spent
        rows = []
        for stepper in steppers:
            variant = (stepper.api, stepper.readback, stepper.impostors)
            per_step = seconds[variant] / steps
            row = {"env": name if heldout is None else f"{name} heldout={heldout}", "api": stepper.api,
                   "readback": stepper.readback, "impostors": stepper.impostors, "worlds": worlds,
                   "agents": core.num_agents,
                   "resolution": resolution, "device": str(core.device), "ms_per_step": per_step * 1e3,
                   "env_steps_per_s": worlds / per_step,
                   "agent_frames_per_s": worlds * core.num_agents / per_step,
                   "render_share": sum(render_seconds[variant].values()) / seconds[variant],
                   "render_ms": {stage: spent / steps * 1e3 for stage, spent in render_seconds[variant].items()},
                   "front_end_share": 1 - stepper.core_seconds / seconds[variant]}
            if "core" in apis:
                row["ratio_to_core"] = seconds[("core", stepper.readback, stepper.impostors)] / seconds[variant]
            if len(readbacks) > 1:
                first = seconds[(stepper.api, readbacks[0], stepper.impostors)]
                row["ratio_to_first_readback"] = first / seconds[variant]
            if len(impostors) > 1:
                first = seconds[(stepper.api, stepper.readback, impostors[0])]
                row["ratio_to_first_impostors"] = first / seconds[variant]
            rows.append(row)
        return rows
    finally:
        for stepper in steppers:
            stepper.close()


def check_extras(args) -> None:
    """MissingExtraError, before any env is made, for a front end whose extra is not installed."""
    for api in args.api:
        if api in API_EXTRAS:
            extra, module = API_EXTRAS[api]
            require(extra, f"bench env --api {api}", module)


def run(args) -> dict:
    from marl_render.envs import list_envs

    names = list_envs() if args.env == "all" else [args.env]
    apis = tuple(dict.fromkeys(args.api))  # in the given order, once each
    readbacks = tuple(dict.fromkeys(args.readback))
    rows = []
    for name, worlds, agents, resolution in itertools.product(names, args.worlds, args.agents, args.resolution):
        each = "default" if agents is None else agents
        progress(f"env {name}: {worlds} worlds of {each} agents at {resolution}px, {args.steps} steps "
                 f"through {', '.join(apis)}")
        rows += measure(name, worlds, resolution, args.steps, agents, args.continuous, apis, args.device, args.heldout,
                        readbacks, tuple(dict.fromkeys(args.impostors)))
    return {"benchmark": "env", "machine": machine(), "results": rows}
