"""Task registry: name -> Scenario subclass, and make_env, which builds a driver for one.

Built-in tasks are listed as "module:Class" strings and imported on first use, so a heavy or
broken task module never slows down or breaks the others. Users add their own:

    register_env("my_task", MyTask)                # a Scenario subclass, or "my_module:MyTask"
    list_envs()                                    # [..., "my_task", ...]
    make_env("my_task", num_worlds=64, my_param=2) # a BatchedEnv (the batched core)

Every front end (make_parallel_env, make_aec_env, make_torchrl_env, make_vec_env, make_sb3_env,
make_jax_env, BenchMARL's MarlRenderTask) finds registered tasks by name. make_env also takes
the Scenario class itself instead of a name: that is how front ends pickle a task (by module
and class), so a worker process needs no registration of its own.
"""
from __future__ import annotations

import dataclasses
import importlib

from gymnasium.envs.registration import register as register_gymnasium_id
from gymnasium.envs.registration import registry as gymnasium_ids

from marl_render.validation import describe

from . import bots  # the tasks' declared bots and held-out scenarios (it reads env_class back: imported as a module)
from .core import BatchedEnv
from .focal import FocalEnv
from .multiprocess import MultiProcessEnv
from .options import OPTION_NAMES, EnvOptions
from .scenario import Scenario

# name -> "module:Class" (imported lazily) or a Scenario subclass.
_REGISTRY: dict = {
    "cartpole": "marl_render.envs.cartpole:CartPoleBalance",
    "spread": "marl_render.envs.spread:Spread",
    "tag": "marl_render.envs.tag:Tag",
    "forage": "marl_render.envs.forage:Forage",
    "push": "marl_render.envs.push:Push",
    "rooms": "marl_render.envs.rooms:Rooms",
    "speaker_listener": "marl_render.envs.speaker_listener:SpeakerListener",
    "commons": "marl_render.envs.commons:Commons",
    "capture_flag": "marl_render.envs.capture_flag:CaptureFlag",
    "clean_up": "marl_render.envs.clean_up:CleanUp",
    "coop_mining": "marl_render.envs.coop_mining:CoopMining",
    "matrix": "marl_render.envs.matrix:Matrix",
    "cooking": "marl_render.envs.cooking:Cooking",
    "territory": "marl_render.envs.territory:Territory",
}


def register_env(name: str, scenario, *, overwrite: bool = False) -> None:
    """Make a task known by `name`: a Scenario subclass, or a "module:Class" string naming one."""
    if not isinstance(name, str) or not name:
        raise TypeError(f"name must be a non-empty str, got {describe(name)}")
    is_class = isinstance(scenario, type) and issubclass(scenario, Scenario)
    if not (is_class or isinstance(scenario, str) and scenario.count(":") == 1):
        raise TypeError(f"scenario must be a Scenario subclass (marl_render.envs.Scenario) or a 'module:Class' "
                        f"string, got {describe(scenario)}")
    if name in _REGISTRY and not overwrite:
        raise ValueError(f"an environment named {name!r} is already registered; pass overwrite=True to replace it")
    _REGISTRY[name] = scenario
    _register_gymnasium_id(name)


def _register_gymnasium_id(name: str) -> None:
    """The gymnasium id "marl_render/<name>-v0": ``gymnasium.make_vec(id, num_envs=N)`` builds
    make_vec_env (N entries = worlds x agents) and, for single-agent tasks, ``gymnasium.make(id)``
    builds make_gym_env. Strings, not imports: no task module or front end is loaded here. A name
    gymnasium cannot take into an id gets none (make_vec_env still works by name)."""
    env_id = f"marl_render/{name}-v0"
    if env_id in gymnasium_ids:  # importing twice (a reload) or overwrite=True: gymnasium would warn
        return
    try:
        register_gymnasium_id(env_id, entry_point="marl_render.wrappers.gymnasium:make_gym_env",
                              vector_entry_point="marl_render.wrappers.gymnasium:gymnasium_vector_entry_point",
                              kwargs={"name": name})
    except Exception:  # gymnasium's id grammar refused the name
        return


def list_envs() -> list[str]:
    """Names of all registered tasks, sorted."""
    return sorted(_REGISTRY)


def env_class(name) -> type[Scenario]:
    """The Scenario subclass registered under `name` (imported if needed); a Scenario subclass
    is returned as it is."""
    if isinstance(name, type) and issubclass(name, Scenario):
        return name
    if not isinstance(name, str):
        raise TypeError(f"name must be a str (one of {list_envs()}) or a Scenario subclass, got {describe(name)}")
    if name not in _REGISTRY:
        raise ValueError(f"unknown environment {name!r}; known environments: {list_envs()}")
    entry = _REGISTRY[name]
    if isinstance(entry, str):
        module, attribute = entry.split(":")
        entry = getattr(importlib.import_module(module), attribute)
        if not (isinstance(entry, type) and issubclass(entry, Scenario)):
            raise TypeError(f"environment {name!r} is registered as {_REGISTRY[name]!r}, which is not a Scenario "
                            f"subclass but {describe(entry)}")
    return entry


def has_compiled_physics(name) -> bool:
    """Whether the task has a compiled physics kernel (make_env(..., compile_physics=True))."""
    return env_class(name).compile_physics is not Scenario.compile_physics


def split_kwargs(scenario: type[Scenario], kwargs: dict) -> tuple:
    """(EnvOptions, scenario.Params) from make_env's keywords; unknown keywords are a TypeError
    naming them and listing the accepted ones."""
    if not (isinstance(scenario.Params, type) and dataclasses.is_dataclass(scenario.Params)):
        raise TypeError(f"{scenario.__name__}.Params must be a dataclass of the task's keywords (with their "
                        f"defaults), got {describe(scenario.Params)}")
    param_names = {field.name for field in dataclasses.fields(scenario.Params)}
    kwargs = with_difficulty(scenario, kwargs)
    unknown = sorted(set(kwargs) - OPTION_NAMES - param_names)
    if unknown:
        raise TypeError(f"make_env({scenario.name!r}) got unknown keyword argument(s) {unknown}; "
                        f"accepted: {sorted(OPTION_NAMES | param_names | {'difficulty'})}")
    options = EnvOptions(**{k: v for k, v in kwargs.items() if k in OPTION_NAMES})
    params = scenario.Params(**{k: v for k, v in kwargs.items() if k in param_names})
    return options, params


def with_difficulty(scenario: type[Scenario], kwargs: dict) -> dict:
    """kwargs with difficulty= replaced by its preset's keywords (Scenario.difficulties); the
    keywords given explicitly win over the preset's."""
    if kwargs.get("difficulty") is None:
        return {k: v for k, v in kwargs.items() if k != "difficulty"}
    difficulty, presets = kwargs["difficulty"], scenario.difficulties
    if not presets:
        raise ValueError(f"difficulty={difficulty!r}: {scenario.__name__} has no difficulty presets "
                         f"(Scenario.difficulties is empty); pass its keywords instead")
    if not isinstance(difficulty, str) or difficulty not in presets:
        raise ValueError(f"difficulty must be one of {sorted(presets)} (or None), got {describe(difficulty)}")
    explicit = {k: v for k, v in kwargs.items() if k != "difficulty"}
    return {**presets[difficulty], **explicit}


def make_env(name, *, heldout=None, background=None, num_processes=None, **kwargs):
    """The batched core of task `name` (a registered name or a Scenario subclass), built with
    `kwargs`: the driver's options (EnvOptions) and the task's own keywords (its Params).

    With `num_processes` (an int in [1, num_worlds]; None: this process), the worlds are split over
    that many worker processes, each with its own GL context, writing into one set of shared
    output tensors: a MultiProcessEnv (envs/multiprocess.py, docs/distributed.md).

    With `heldout` (a name of ``marl_render.heldout.list_heldout()``: a task's own scenario or a
    registered one, envs/bots.py; or a HeldOutScenario) or
    `background` (a Population of bots by role), a focal-only env (envs/focal.py) over that core:
    only the focal agents are exposed, bots play the others."""
    scenario = env_class(name)
    if heldout is not None and background is not None:
        raise ValueError("pass heldout (a held-out scenario, which brings its own bots) or background (a Population), "
                         "not both")
    if heldout is not None:
        held = bots.heldout_scenario(heldout)
        if held.task != scenario.name and env_class(held.task) is not scenario:
            raise ValueError(f"heldout {held.name!r} is a scenario of {held.task!r}, not of {scenario.name!r}")
        fixed = held.env_kwargs()
        clash = sorted(k for k in set(fixed) & set(kwargs) if kwargs[k] != fixed[k])
        if clash:
            raise ValueError(f"heldout {held.name!r} fixes {clash} to {[fixed[k] for k in clash]}; got "
                             f"{[kwargs[k] for k in clash]}")
        # The scenario's keywords would win over the preset's as explicit ones do: refuse that alike.
        preset = with_difficulty(scenario, {"difficulty": kwargs.get("difficulty")})
        clash = sorted(k for k in set(fixed) & set(preset) if preset[k] != fixed[k])
        if clash:
            raise ValueError(f"heldout {held.name!r} fixes {clash} to {[fixed[k] for k in clash]}; "
                             f"difficulty={kwargs['difficulty']!r} sets {[preset[k] for k in clash]}: pass a "
                             f"difficulty that leaves them alone, or none")
        kwargs = {**kwargs, **fixed}
    options, params = split_kwargs(scenario, kwargs)
    if num_processes is not None:
        if heldout is not None or background is not None:
            raise ValueError(f"num_processes applies to the batched core; it cannot be combined with heldout or "
                             f"background (bots), got num_processes={num_processes!r}")
        return MultiProcessEnv(scenario, options, params, num_processes)
    core = BatchedEnv(scenario, options, params)
    if heldout is None and background is None:
        return core
    try:
        return FocalEnv(core, held.population(core.seed) if heldout is not None else background)
    except BaseException:
        core.close()
        raise


for _name in _REGISTRY:  # the built-in tasks' gymnasium ids
    _register_gymnasium_id(_name)
