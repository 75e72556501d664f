"""The driver's options, as data: ``EnvOptions`` and their checks.

Every env takes the same options whatever the task (a task's own keywords are its
``Scenario.Params``). ``make_env(name, **kwargs)`` sorts the keywords into the two:

    EnvOptions(num_worlds=64, resolution=48, autoreset="next_step", seed=0)

None means "the task's default" for num_agents, resolution and max_steps. The checks run when
the driver is built (some bounds depend on the task and the GL context), each raising
TypeError / ValueError naming the option, the expected and the given: ``resolve(options, scenario,
params)`` runs them all and returns the ``Settings`` the driver is built with.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

import marl_render as mr
from marl_render.render.impostors import check_mode as check_impostors
from marl_render.render.shadows import atlas_layout
from marl_render.util.threads import thread_count
from marl_render.util.validation import describe, positive_float, positive_int, resolution_hw, torch_device

from . import levels as level_sets
from .rendering import check_memory

AUTORESET_MODES = ("next_step", "same_step")
MAX_SUBSTEPS = 1024  # physics_substeps; docs/accuracy takes 64 substeps as its reference already
MAX_LIDAR_RAYS = 1024  # every ray meets every body and box of its world: W x A x rays x bodies floats a step


@dataclasses.dataclass(frozen=True)
class EnvOptions:
    """The options every env takes (see the module docstring): num_worlds, num_agents, resolution
    (int or (H, W)), max_steps, continuous, state_obs, depth, shadows (False, True or a
    marl_render.Shadows; True: Shadows(bounds=the task's shadow_bounds)), device, seed,
    autoreset (False, "next_step", "same_step" or True = "same_step"), grayscale (one-channel
    pixels), torch_threads (default 1, at most 1024: torch intra-op threads used *inside* env
    calls, the caller's setting restored on return; None leaves torch's setting alone) and
    context (a marl_render.GLContext to render on; None: the process's default), readback ("auto",
    "gpu" or "host": how frames reach `device`, marl_render.BatchRenderer's readback), and the
    accuracy knobs multisamples (MSAA samples of the agents' views, colour only), supersample
    (k x the resolution, box-filtered down), layered and exact_tiles (two ways to make the agents'
    views bit-identical in any world slot and at any batch size, each at a cost in render time:
    docs/levels.md) and
    physics_substeps (planar physics substeps per step; None: the task's own; coarser than the
    no-tunnelling bound is refused), and
    compile_physics (torch.compile the task's physics kernel where it has one (cartpole):
    within 1e-12 of the default path, faster at small batches; seconds to compile at construction;
    a RuntimeWarning and the default path where compiling fails), lidar (rays of the "lidar"
    observation, 0: none) and lidar_range (m it is divided by; None: the arena's diagonal),
    enforce_action_mask (refuse forbidden actions: envs/masking.py), and appearance (None: off;
    "train", "heldout" or a marl_render.Appearance: each world's light, sky, floor and wall colours
    and patterns, object colour jitter and camera jitter, drawn at every reset of the world from its
    appearance_ids, see docs/appearance.md), levels (None: resets draw from the env's generator; else
    the levels the worlds play, each reset a pure function of its level id: envs/levels.py).
    """

    num_worlds: int = 1
    num_agents: int | None = None
    resolution: object = None  # int or (H, W)
    max_steps: int | None = None
    continuous: bool = False
    state_obs: bool = False
    depth: bool = False
    shadows: object = False  # False, True or a marl_render.Shadows
    device: object = "cpu"
    # How frames reach `device`: "auto" (CUDA-OpenGL interop where it works, else through the host),
    # "gpu" (interop or an error saying why) or "host"; "pbo" and "copy" are host reads for benchmarks
    # (marl_render.BatchRenderer's readback).
    readback: str = "auto"
    seed: int | None = None
    autoreset: object = False  # False, True (= "same_step"), "next_step" or "same_step"
    torch_threads: int | None = 1
    grayscale: bool = False
    context: object = None  # a marl_render.GLContext, or None for the process's default
    # Accuracy knobs (what they cost: docs/accuracy/): anti-aliasing of the agents' views and the
    # planar physics' substeps per step (None: the task's own).
    multisamples: int = 0  # MSAA samples (colour only: not with depth)
    supersample: int = 1  # render k x the resolution and box-filter it down
    # The agents' views bit-identical in any world slot and at any batch size, each view drawn into its
    # own layer (BatchRenderer(layered=True), the cheaper way) or placed exactly in its tile
    # (exact_tiles=True): docs/levels.md says what each costs.
    layered: bool = False
    exact_tiles: bool = False
    # Spheres drawn as ray-cast impostors where the effects allow (marl_render/render/impostors.py): "auto",
    # True (raise where they cannot be drawn) or False (meshes); what it changes: docs/accuracy.md.
    impostors: object = "auto"
    physics_substeps: int | None = None
    # torch.compile the task's physics kernel (cartpole): envs/compiled.py.
    compile_physics: bool = False
    # Arena tasks: the obs key "lidar", float32 [W, A, lidar] distances along that many rays (0: none),
    # each divided by lidar_range (m; None: the arena's diagonal) and capped at 1 (envs/sight.py).
    lidar: int = 0
    lidar_range: float | None = None
    # The obs key "agent_id", float32 [W, A, A + teams]: the agent's one-hot index, then its team's. For
    # one policy that plays several roles through a front end that hides who is who (the vector env, SB3).
    agent_ids: bool = False
    # Refuse a step whose actions the action mask forbids (ValueError, nothing changes); default: the
    # mask is advice that policies may read (envs/masking.py).
    enforce_action_mask: bool = False
    # Per-world looks (marl_render/appearance.py): None (off), "train", "heldout" or a marl_render.Appearance.
    appearance: object = None
    # Levels (envs/levels.py): None (off: resets draw from the env's generator), a train set (an int n,
    # a range or a list of ids), "train", "test", "published", or a level sampler.
    levels: object = None
    # Episode ends (envs/episodes.py): None (the task's default: Melting Pot's random end for mixed-motive
    # tasks, else fixed at max_steps), False (fixed), True, an envs.EpisodeEnd or (min_steps, interval, p).
    episode_end: object = None
    # The social outcome info entries (envs/episodes.py): None (on for mixed-motive tasks), True or False.
    social_metrics: object = None


OPTION_NAMES = frozenset(field.name for field in dataclasses.fields(EnvOptions))


@dataclasses.dataclass(frozen=True)
class Settings:
    """EnvOptions resolved for one task on this machine (``resolve``): every option checked, the task's
    defaults filled in, the GL context chosen, the seed drawn where none was given. The driver
    publishes those named in PUBLISHED as its attributes; the rest serve its construction."""

    num_worlds: int
    num_agents: int
    device: torch.device
    readback: str
    context: object  # the marl_render.GLContext the env renders on
    resolution: tuple  # (H, W)
    max_steps: int
    continuous: bool
    state_obs: bool
    depth: bool
    grayscale: bool
    pixel_channels: int  # 1 with grayscale, else 3
    lidar_rays: int
    lidar_range: float | None
    enforce_action_mask: bool
    agent_ids: bool
    autoreset: object  # False, "next_step" or "same_step"
    torch_threads: int | None
    seed: int
    shadows: object  # None or a marl_render.Shadows
    appearance: object  # None or a marl_render.Appearance
    levels: object  # None or a level sampler (envs/levels.py)
    effects: tuple  # the renderer's effects
    multisamples: int
    supersample: int
    compile_physics: bool
    layered: bool
    exact_tiles: bool
    impostors: object  # "auto", True or False (marl_render/render/impostors.py)
    physics_substeps: int | None  # checked by physics_substeps() once the scenario is built


PUBLISHED = ("num_worlds", "num_agents", "device", "readback", "context", "resolution", "max_steps", "continuous",
             "state_obs", "depth", "grayscale", "pixel_channels", "lidar_rays", "lidar_range", "enforce_action_mask",
             "agent_ids", "autoreset", "torch_threads", "seed", "shadows", "appearance", "levels")


def resolve(options: EnvOptions, scenario, params) -> Settings:
    """The Settings of `options` for the Scenario subclass `scenario` with `params`, checked in this
    order; finally the batch is checked against the machine's memory (views and pixels, before the
    scenario allocates anything) and the context against a fork (ForkedContextError now, not a torch
    deadlock later)."""
    num_worlds = positive_int("num_worlds", options.num_worlds)
    agents = num_agents(scenario.num_agents_for(params, options.num_agents), scenario)
    context = options.context
    if context is not None and not isinstance(context, mr.GLContext):
        raise TypeError(f"context must be a marl_render.GLContext or None, got {describe(context)}")
    env_device = device(options.device)
    frames_readback = readback(options.readback)
    if context is None:  # with a CUDA device, the first context opens the EGL device that is that device
        cuda_index = None if env_device.type != "cuda" else (
            torch.cuda.current_device() if env_device.index is None else env_device.index)
        context = mr.backend.context_for_cuda(cuda_index)
    context.check_usable()
    gl_limit = context.info().max_framebuffer_size
    hw = resolution(options.resolution, scenario, gl_limit)
    steps = max_steps(options.max_steps, scenario)
    continuous = flag("continuous", options.continuous)
    state_obs = flag("state_obs", options.state_obs)
    depth = flag("depth", options.depth)
    grayscale = flag("grayscale", options.grayscale)
    lidar_rays, lidar_range = lidar(options.lidar, options.lidar_range, scenario)
    enforce_action_mask = flag("enforce_action_mask", options.enforce_action_mask)
    agent_ids = flag("agent_ids", options.agent_ids)
    if enforce_action_mask and continuous:
        raise ValueError("enforce_action_mask applies to discrete actions (continuous=False), which have an "
                         "action mask; got enforce_action_mask=True with continuous=True")
    autoreset = autoreset_mode(options.autoreset)
    torch_threads = None if options.torch_threads is None else thread_count("torch_threads", options.torch_threads)
    given_seed = seed("seed", options.seed)
    drawn_seed = int(torch.Generator().seed() % 2 ** 63) if given_seed is None else given_seed
    scene_shadows = shadows(options.shadows, scenario.shadow_bounds)
    effects = ("lighting", "depth") if depth else ("lighting",)
    effects += ("shadows",) if scene_shadows else ()
    looks = appearance(options.appearance)
    levels = level_sets.as_sampler(options.levels)
    if levels is not None and not scenario.has_levels():
        raise ValueError(f"levels={describe(options.levels)} needs a task whose resets draw from "
                         f"spawn_level(draws) (envs/levels.py); {scenario.__name__} implements only "
                         f"spawn(generator): levels must be None for it")
    effects += ("appearance",) if looks is not None else ()
    if scene_shadows:  # an atlas GL cannot hold is named as such, not as a memory shortage
        atlas_layout(num_worlds, scene_shadows.resolution, gl_limit)
    # Views and pixels alone, before the scenario allocates anything; the driver checks the whole scene.
    check_memory(mr.Scene(num_worlds=num_worlds, agents_per_world=agents, resolution=hw, effects=effects),
                 num_worlds, agents, hw)
    context.check_usable()  # in a forked child: ForkedContextError now, not a torch deadlock below
    return Settings(
        num_worlds=num_worlds, num_agents=agents, device=env_device, readback=frames_readback, context=context,
        resolution=hw,
        max_steps=steps, continuous=continuous, state_obs=state_obs, depth=depth, grayscale=grayscale,
        pixel_channels=1 if grayscale else 3, lidar_rays=lidar_rays, lidar_range=lidar_range,
        enforce_action_mask=enforce_action_mask, agent_ids=agent_ids, autoreset=autoreset,
        torch_threads=torch_threads, seed=drawn_seed, shadows=scene_shadows, appearance=looks, levels=levels,
        effects=effects, multisamples=multisamples(options.multisamples),
        supersample=positive_int("supersample", options.supersample),
        compile_physics=flag("compile_physics", options.compile_physics),
        layered=flag("layered", options.layered), exact_tiles=flag("exact_tiles", options.exact_tiles),
        impostors=check_impostors(options.impostors),
        physics_substeps=options.physics_substeps)


def flag(name: str, value) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a bool, got {describe(value)}")
    return bool(value)


def multisamples(value) -> int:
    """MSAA samples of the agents' views: an int >= 0 (numpy ints too, as the other options take)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"multisamples must be an int >= 0 (0: no MSAA), got {describe(value)}")
    if value < 0:
        raise ValueError(f"multisamples must be an int >= 0 (0: no MSAA), got {value}")
    return int(value)


def shadows(value, bounds) -> mr.Shadows | None:
    """None (no shadows) or the Shadows settings of the scene."""
    if isinstance(value, mr.Shadows):
        return value
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"shadows must be a bool or a marl_render.Shadows, got {describe(value)}")
    return mr.Shadows(bounds=bounds) if value else None


def appearance(value) -> mr.Appearance | None:
    """None (the effect off) or the Appearance each world's look is drawn from at its resets."""
    if value is None or isinstance(value, mr.Appearance):
        return value
    want = f"None, one of {list(mr.appearance.SPLITS)} or a marl_render.Appearance"
    if not isinstance(value, str):
        raise TypeError(f"appearance must be {want}, got {describe(value)}")
    if value not in mr.appearance.SPLITS:
        raise ValueError(f"appearance must be {want}, got {value!r}")
    return mr.Appearance(split=value)


def autoreset_mode(value) -> bool | str:
    """False, "next_step" or "same_step"; True means "same_step" (see envs/core.py)."""
    want = f"False, True (= 'same_step') or one of {list(AUTORESET_MODES)}"
    if isinstance(value, (bool, np.bool_)):
        return "same_step" if value else False
    if not isinstance(value, str):
        raise TypeError(f"autoreset must be {want}, got {describe(value)}")
    if value not in AUTORESET_MODES:
        raise ValueError(f"autoreset must be {want}, got {value!r}")
    return value


def seed(name: str, value) -> int | None:
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be None or an int in [0, 2**63), got {describe(value)}")
    if not 0 <= int(value) < 2 ** 63:
        raise ValueError(f"{name} must be None or an int in [0, 2**63), got {value}")
    return int(value)


def device(value) -> torch.device:
    return torch_device("device", value)


def readback(value) -> str:
    """How frames reach the device: one of marl_render.BatchRenderer.READBACKS."""
    return mr.interop.check_readback(value, mr.BatchRenderer.READBACKS)


def num_agents(value, scenario) -> int:
    low, high = scenario.agent_range
    value = scenario.default_num_agents if value is None else value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"num_agents must be an int in [{low}, {high}], got {describe(value)}")
    if not low <= value <= high:
        raise ValueError(f"num_agents must be an int in [{low}, {high}] for {scenario.name}, got {value}")
    return int(value)


def resolution(value, scenario, gl_limit: int) -> tuple:
    hw = resolution_hw(scenario.default_resolution if value is None else value)
    if max(hw) > gl_limit:
        raise ValueError(f"resolution must be at most {gl_limit} pixels per side (GL limit), got {hw}")
    return hw


def physics_substeps(value, scenario):
    """The scenario's planar physics (PhysicsConfig) with `value` substeps per step."""
    if scenario.physics is None:
        raise ValueError(f"physics_substeps applies to tasks with planar physics (envs/planar.py); "
                         f"{scenario.name} has none, got physics_substeps={value!r}")
    substeps = positive_int("physics_substeps", value)
    if substeps > MAX_SUBSTEPS:  # each substep is a pass of Python calls: a huge count would hang every step
        raise ValueError(f"physics_substeps must be an int in [1, {MAX_SUBSTEPS}], got {substeps}")
    try:
        return dataclasses.replace(scenario.physics, substeps=substeps)
    except ValueError as exc:  # too coarse: bodies would tunnel through each other
        raise ValueError(f"physics_substeps={substeps} is too coarse for {scenario.name} "
                         f"(default {scenario.physics.substeps}): {exc}") from None


def lidar(rays, reach, scenario) -> tuple:
    """(rays, reach) of the lidar observation: rays an int in [0, MAX_LIDAR_RAYS] (0: none), reach None
    (the task's default) or a finite number > 0 of metres, for tasks that have planar geometry."""
    if isinstance(rays, (bool, np.bool_)) or not isinstance(rays, (int, np.integer)):
        raise TypeError(f"lidar must be an int in [0, {MAX_LIDAR_RAYS}] (rays; 0: no lidar), got {describe(rays)}")
    if not 0 <= rays <= MAX_LIDAR_RAYS:
        raise ValueError(f"lidar must be an int in [0, {MAX_LIDAR_RAYS}] (rays; 0: no lidar), got {rays}")
    if reach is not None:
        reach = positive_float("lidar_range", reach)
        if not rays:
            raise ValueError(f"lidar_range applies with lidar > 0 (rays), got lidar_range={reach} and lidar=0")
    if rays and not scenario.has_lidar():
        raise ValueError(f"lidar applies to arena tasks (ArenaScenario: walls, obstacles and bodies to hit); "
                         f"{scenario.name} has none, got lidar={rays}")
    return int(rays), reach


def max_steps(value, scenario) -> int:
    steps = positive_int("max_steps", scenario.default_max_steps if value is None else value)
    if steps >= 2 ** 63:  # compared with the int64 step counters
        raise ValueError(f"max_steps must be an int in [1, 2**63), got {steps}")
    return steps
