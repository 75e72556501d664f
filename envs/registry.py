"""Environment registry: name -> BatchedEnv subclass (or factory).

Built-in environments are listed as "module:Class" strings and imported on first use,
so a heavy or broken environment module never slows down or breaks the others.

    list_envs()                        -> ["cartpole", "spread", ...]
    make_env("spread", num_worlds=64)  -> a BatchedEnv (the batched core)
    register("my_env", MyEnv)          -> add your own
"""
from __future__ import annotations

import importlib
import inspect

from marl_render.validation import describe

# name -> "module:attribute" (imported lazily) or a class / factory returning a BatchedEnv.
_REGISTRY: dict = {
    "cartpole": "marl_render.envs.cartpole:CartPoleBalance",
    "spread": "marl_render.envs.spread:Spread",
    "tag": "marl_render.envs.tag:Tag",
    "forage": "marl_render.envs.forage:Forage",
    "push": "marl_render.envs.push:Push",
}


def register(name: str, env, *, overwrite: bool = False) -> None:
    """Register a BatchedEnv subclass, a factory (callable returning one) or a "module:attr" string."""
    if not isinstance(name, str) or not name:
        raise TypeError(f"name must be a non-empty str, got {describe(name)}")
    if not (isinstance(env, str) and ":" in env) and not callable(env):
        raise TypeError(f"env must be a BatchedEnv subclass, a callable or a 'module:attribute' string, "
                        f"got {describe(env)}")
    if name in _REGISTRY and not overwrite:
        raise ValueError(f"an environment named {name!r} is already registered; pass overwrite=True to replace it")
    _REGISTRY[name] = env


def list_envs() -> list[str]:
    """Names of all registered environments, sorted."""
    return sorted(_REGISTRY)


def env_class(name: str):
    """The class (or factory) registered under `name`, importing it if needed."""
    if not isinstance(name, str):
        raise TypeError(f"name must be a str (one of {list_envs()}), got {describe(name)}")
    if name not in _REGISTRY:
        raise ValueError(f"unknown environment {name!r}; known environments: {list_envs()}")
    entry = _REGISTRY[name]
    if isinstance(entry, str):
        module, attribute = entry.split(":")
        entry = getattr(importlib.import_module(module), attribute)
    return entry


def make_env(name: str, **kwargs):
    """The batched core of environment `name` (a BatchedEnv), built with `kwargs`.

    Unknown keyword arguments raise TypeError naming them and listing the accepted ones."""
    cls = env_class(name)
    accepted = _accepted_kwargs(cls)
    if accepted is not None:
        unknown = sorted(set(kwargs) - accepted)
        if unknown:
            raise TypeError(f"make_env({name!r}) got unknown keyword argument(s) {unknown}; "
                            f"accepted: {sorted(accepted)}")
    return cls(**kwargs)


def _accepted_kwargs(cls):
    """Keyword names a class accepts, following **kwargs up the MRO; None if unknowable."""
    if not inspect.isclass(cls):
        return None
    names = set()
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        params = inspect.signature(init).parameters.values()
        names |= {p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.name != "self"}
        if not any(p.kind == p.VAR_KEYWORD for p in params):
            return names
    return None
