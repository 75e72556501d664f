"""Soak: a long run with random actions and resets, watching memory and numerics.

Steps --worlds worlds (default 64) of --env (default spread) with uniformly random
actions, auto-reset of finished worlds (--autoreset, same_step by default) and, every
--reset-every steps, reset_worlds() of a random subset (each world with probability --reset-fraction).
Every --every steps it samples the resident memory (RSS, through psutil) and
checks the simulation state; every step it checks the float observations and rewards
for NaN/Inf. --shadows adds the shadow pass; --skinned draws the agents of an arena env
(spread, tag, ...) as mr.skinned_character(), posed from the state every step, so that
their joints are packed and skinned in every frame. After --warmup steps the memory growth
is reported as MB in total and MB per 1000 steps (least-squares slope over the samples
after warm-up), for RSS and for the heap in use (glibc's mallinfo2: live allocations only,
so a leak of small blocks shows there without the noise of freed pages), and as the rise
of the RSS floor (the lowest sample of the last quarter after warm-up against the first
quarter's), which a block alive at only some samples does not move.

Writes soak.json (the result below) and soak.png (memory over steps) into --out;
progress goes to stderr.

By default glibc's malloc_trim(0) runs before each sample, so that the curve shows
memory that is still in use rather than freed memory the allocator keeps for reuse
(large freed blocks otherwise linger in RSS); --no-malloc-trim measures raw RSS.
"""
from __future__ import annotations

import gc
import json
import os
import time

import numpy as np
import torch

from .common import env_name_argument, heap_in_use_mb, machine, malloc_trim, progress, rss_mb


def add_arguments(parser):
    parser.add_argument("--env", default="spread", type=env_name_argument,
                        help="environment name (see marl_render.envs.list_envs())")
    parser.add_argument("--worlds", type=int, default=64)
    parser.add_argument("--agents", type=int, default=None, help="agents per world (env default if omitted)")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--every", type=int, default=50, help="sample memory and state every K steps")
    parser.add_argument("--warmup", type=int, default=None,
                        help="steps before memory growth is measured (default: 10%% of --steps, at least --every)")
    parser.add_argument("--reset-every", type=int, default=10, help="partial reset every N steps (0: never)")
    parser.add_argument("--reset-fraction", type=float, default=0.25, help="chance of each world to be reset")
    parser.add_argument("--max-steps", type=int, default=None, help="episode length (env default if omitted)")
    parser.add_argument("--continuous", action="store_true")
    parser.add_argument("--depth", action="store_true", help="also render depth (checked for NaN)")
    parser.add_argument("--shadows", action="store_true", help="the env's shadows on (a shadow pass every frame)")
    parser.add_argument("--autoreset", choices=("same_step", "next_step"), default="same_step",
                        help="the env's autoreset mode")
    parser.add_argument("--skinned", action="store_true",
                        help="agents drawn as a skinned character posed every step (arena envs only)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-malloc-trim", dest="malloc_trim", action="store_false",
                        help="sample raw RSS (without returning freed heap memory to the OS first)")
    parser.add_argument("--no-plot", dest="plot", action="store_false", help="do not write soak.png")
    parser.add_argument("--out", default="out/soak")


# ---------------------------------------------------------------------- memory
def render_state_count() -> int | None:
    """Panda3D RenderStates alive (a leak of render states shows here first)."""
    try:
        from panda3d.core import RenderState

        return int(RenderState.get_num_states())
    except Exception:  # diagnostics only
        return None


def slope_per_step(points: list[tuple[int, float]]) -> float:
    """Least-squares slope of (step, value) pairs; 0.0 with fewer than 2 distinct steps."""
    if len({s for s, _ in points}) < 2:
        return 0.0
    steps, values = zip(*points, strict=True)
    return float(np.polyfit(steps, values, 1)[0])


# ---------------------------------------------------------------------- skinned agents
def skinned_agents(scenario: type) -> type:
    """A subclass of the arena scenario `scenario` whose agents are mr.skinned_character(),
    every joint swinging with the agent's position (so each step packs new joints)."""
    import marl_render as mr
    from marl_render.envs.arena import ArenaScenario

    if not (isinstance(scenario, type) and issubclass(scenario, ArenaScenario)):
        raise ValueError(f"skinned agents need an arena env (an ArenaScenario: spread, tag, ...), got "
                         f"{getattr(scenario, 'name', scenario)!r}")
    character = mr.skinned_character()

    class SkinnedAgents(scenario):
        def build_scene(self, scene, overview):
            super().build_scene(scene, overview)
            scene.groups["agents"].mesh = character

        def instances(self, state, full):
            update = super().instances(state, full)
            pos = state.pos[:, :self.num_agents].to("cpu", torch.float32)
            phase = 4.0 * pos.sum(-1, keepdim=True) + torch.arange(character.num_joints)  # [W, A, J]
            pitch = 0.5 * torch.sin(phase)
            update["agents"]["joints"] = mr.quat_from_yaw_pitch_roll(torch.zeros_like(pitch), pitch,
                                                                     torch.zeros_like(pitch))
            return update

    SkinnedAgents.__name__ = SkinnedAgents.__qualname__ = f"Skinned{scenario.__name__}"
    return SkinnedAgents


# ---------------------------------------------------------------------- checks
def _first_non_finite(label: str, tensor: torch.Tensor, step: int) -> dict | None:
    if not tensor.is_floating_point():
        return None
    bad = ~torch.isfinite(tensor)
    if not bool(bad.any()):
        return None
    index = bad.nonzero()[0].tolist()
    return {"step": step, "what": label, "count": int(bad.sum()), "index": index,
            "value": float(tensor[tuple(index)])}


def non_finite_values(step: int, obs: dict, reward: torch.Tensor, state: dict | None = None) -> list[dict]:
    """Records of NaN/Inf in the float observations, the rewards and (if given) the env state."""
    found = [_first_non_finite(f"obs[{key!r}]", value, step) for key, value in obs.items()]
    found.append(_first_non_finite("reward", reward, step))
    for key, value in (state or {}).items():
        if isinstance(value, torch.Tensor):
            found.append(_first_non_finite(f"state[{key!r}]", value, step))
    return [f for f in found if f is not None]


# ---------------------------------------------------------------------- run
def soak(env_name: str = "spread", worlds: int = 64, steps: int = 2000, *, agents: int | None = None,
         resolution: int = 64, every: int = 50, warmup: int | None = None, reset_every: int = 10,
         reset_fraction: float = 0.25, max_steps: int | None = None, continuous: bool = False,
         depth: bool = False, seed: int = 0, trim: bool = True, shadows: bool = False,
         autoreset: str = "same_step", skinned: bool = False) -> dict:
    """Run the soak and return its result dict (see the module docstring)."""
    from marl_render.envs import make_env
    from marl_render.envs.registry import env_class

    if steps < 1 or every < 1 or worlds < 1:
        raise ValueError(f"steps, every and worlds must be >= 1, got {steps}, {every}, {worlds}")
    if not 0.0 <= reset_fraction <= 1.0:
        raise ValueError(f"reset_fraction must be in [0, 1], got {reset_fraction}")
    if warmup is None:
        warmup = max(every, steps // 10)
    warmup = min(max(warmup, 0), steps)
    kwargs = {"num_worlds": worlds, "resolution": resolution, "continuous": continuous, "seed": seed,
              "autoreset": autoreset, "state_obs": True, "depth": depth, "shadows": shadows}
    if agents is not None:
        kwargs["num_agents"] = agents
    if max_steps is not None:
        kwargs["max_steps"] = max_steps

    scenario = skinned_agents(env_class(env_name)) if skinned else env_name

    def sample(step: int, elapsed: float) -> dict:
        gc.collect()
        trimmed = malloc_trim() if trim else False
        return {"step": step, "rss_mb": rss_mb(), "heap_in_use_mb": heap_in_use_mb(), "elapsed_s": elapsed,
                "malloc_trim": trimmed, "render_states": render_state_count()}

    rss_before = rss_mb()
    env = make_env(scenario, **kwargs)
    try:
        generator = torch.Generator().manual_seed(seed)
        obs = env.reset(seed=seed)
        non_finite = non_finite_values(0, obs, torch.zeros(()), env.get_state())
        samples = [sample(0, 0.0)]
        partial_resets = auto_resets = 0
        start = time.perf_counter()
        step_seconds = 0.0
        for step in range(1, steps + 1):
            actions = env.random_actions(generator)
            began = time.perf_counter()
            obs, reward, _terminated, _truncated, info = env.step(actions)
            if reset_every and step % reset_every == 0:
                mask = torch.rand(worlds, generator=generator) < reset_fraction
                if bool(mask.any()):
                    obs = env.reset_worlds(mask)
                    partial_resets += int(mask.sum())
            step_seconds += time.perf_counter() - began
            auto_resets += int(info["done_worlds"].sum())
            check_state = step % every == 0 or step == steps
            if len(non_finite) < 100:
                non_finite += non_finite_values(step, obs, reward, env.get_state() if check_state else None)
            if check_state:
                samples.append(sample(step, time.perf_counter() - start))
                last = samples[-1]
                progress(f"soak {env_name}: step {step}/{steps}, rss {last['rss_mb']:.1f} MB, "
                         f"{step / max(last['elapsed_s'], 1e-9):.1f} steps/s, non-finite {len(non_finite)}")
        elapsed = time.perf_counter() - start
        num_agents = env.num_agents
    finally:
        env.close()

    after_warmup = [s for s in samples if s["step"] >= warmup]
    base = after_warmup[0] if after_warmup else samples[-1]
    end = samples[-1]
    measured_steps = end["step"] - base["step"]
    growth = end["rss_mb"] - base["rss_mb"]
    slope = slope_per_step([(s["step"], s["rss_mb"]) for s in after_warmup])
    heap = [(s["step"], s["heap_in_use_mb"]) for s in after_warmup if s["heap_in_use_mb"] is not None]
    heap_slope = slope_per_step(heap) * 1000.0 if heap else None
    # A block alive at some samples and not at others (a frame, a step's temporaries) moves the
    # slope; a leak also lifts the lowest readings: the last quarter's minimum against the first's.
    quarter = max(len(after_warmup) // 4, 1)
    rss_floor_growth = (min(s["rss_mb"] for s in after_warmup[-quarter:])
                        - min(s["rss_mb"] for s in after_warmup[:quarter])) if after_warmup else 0.0
    states = [s["render_states"] for s in after_warmup if s["render_states"] is not None]
    return {
        "benchmark": "soak", "machine": machine(),
        "env": env_name, "worlds": worlds, "agents": num_agents, "resolution": resolution,
        "continuous": continuous, "depth": depth, "shadows": shadows, "autoreset": autoreset, "skinned": skinned,
        "seed": seed,
        "steps": steps, "every": every, "warmup": warmup,
        "reset_every": reset_every, "reset_fraction": reset_fraction, "malloc_trim": trim,
        "partial_resets": partial_resets, "auto_resets": auto_resets,
        "seconds": elapsed, "steps_per_s": steps / elapsed, "env_steps_per_s": steps * worlds / elapsed,
        "agent_frames_per_s": steps * worlds * num_agents / elapsed,
        "ms_per_step": step_seconds / steps * 1e3,
        "rss_before_env_mb": rss_before, "rss_start_mb": samples[0]["rss_mb"],
        "rss_after_warmup_mb": base["rss_mb"], "rss_end_mb": end["rss_mb"],
        "rss_peak_mb": max(s["rss_mb"] for s in samples),
        "growth_mb": growth, "growth_steps": measured_steps,
        "growth_mb_per_1000_steps": slope * 1000.0, "heap_in_use_mb_per_1000_steps": heap_slope,
        "rss_floor_growth_mb": rss_floor_growth,
        "render_states_growth": (states[-1] - states[0]) if len(states) >= 2 else None,
        "non_finite_count": len(non_finite), "non_finite": non_finite[:20],
        "samples": samples,
    }


def plot(result: dict, path: str) -> str:
    """soak.png: RSS against steps, warm-up shaded. matplotlib if present, else a plain PIL chart."""
    steps = [s["step"] for s in result["samples"]]
    rss = [s["rss_mb"] for s in result["samples"]]
    title = (f"soak {result['env']}: {result['worlds']} worlds x {result['agents']} agents, "
             f"{result['resolution']}px; growth {result['growth_mb']:+.1f} MB "
             f"({result['growth_mb_per_1000_steps']:+.2f} MB/1000 steps)")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return _plot_pil(steps, rss, result["warmup"], title, path)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    ax.axvspan(0, result["warmup"], color="0.9", label="warm-up")
    ax.plot(steps, rss, marker="o", markersize=3)
    ax.set_xlabel("step")
    ax.set_ylabel("resident memory (MB)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _plot_pil(steps, rss, warmup, title, path):
    from PIL import Image, ImageDraw

    width, height, margin = 800, 450, 50
    image = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(image)
    low, high = min(rss), max(rss)
    high = high if high > low else low + 1.0
    last = max(max(steps), 1)

    def xy(step, value):
        return (margin + (width - 2 * margin) * step / last,
                height - margin - (height - 2 * margin) * (value - low) / (high - low))

    draw.rectangle([xy(0, high), xy(min(warmup, last), low)], fill=(230, 230, 230))
    draw.line([xy(s, v) for s, v in zip(steps, rss, strict=True)] or [xy(0, low)], fill=(31, 119, 180), width=2)
    draw.rectangle([margin, margin, width - margin, height - margin], outline="black")
    draw.text((margin, 15), title, fill="black")
    draw.text((margin, height - margin + 8), f"step 0 .. {last}", fill="black")
    draw.text((5, margin), f"{high:.0f} MB", fill="black")
    draw.text((5, height - margin - 10), f"{low:.0f} MB", fill="black")
    image.save(path)
    return path


def run(args) -> dict:
    result = soak(args.env, args.worlds, args.steps, agents=args.agents, resolution=args.resolution,
                  every=args.every, warmup=args.warmup, reset_every=args.reset_every,
                  reset_fraction=args.reset_fraction, max_steps=args.max_steps, continuous=args.continuous,
                  depth=args.depth, seed=args.seed, trim=args.malloc_trim, shadows=args.shadows,
                  autoreset=args.autoreset, skinned=args.skinned)
    os.makedirs(args.out, exist_ok=True)
    files = {"json": os.path.join(args.out, "soak.json")}
    if args.plot:
        files["png"] = plot(result, os.path.join(args.out, "soak.png"))
    result["files"] = files
    with open(files["json"], "w") as f:
        json.dump(result, f, indent=2, default=str)
    heap = result["heap_in_use_mb_per_1000_steps"]
    progress(f"soak: {result['steps_per_s']:.1f} steps/s, growth after warm-up {result['growth_mb']:+.1f} MB "
             f"({result['growth_mb_per_1000_steps']:+.2f} MB/1000 steps"
             + ("" if heap is None else f"; heap in use {heap:+.3f} MB/1000 steps")
             + f"; floor {result['rss_floor_growth_mb']:+.1f} MB), non-finite values: "
             f"{result['non_finite_count']}; wrote {', '.join(files.values())}")
    return result
