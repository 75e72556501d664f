"""Held-out scenarios in Melting Pot's sense: a task, its parameters, which slots are focal, and the
background bots by role, all drawn from the task's test population (populations/bots.py). Each task
declares its own on its class (``heldout``: envs.roster.HeldOut, named "<task>/<name>" here); the
envs layer resolves them (envs/bots.py: make_env(heldout=...) needs nothing above it), this module
lists them and registers a user's with ``register_heldout``.

    list_heldout()                       # every scenario's name, e.g. "tag/prey_vs_interceptors"
    HELDOUT["tag/prey_vs_interceptors"]  # its HeldOutScenario
    make_env("tag", heldout="tag/prey_vs_interceptors", num_worlds=32)   # its focal-only env

Tags: "resident" when the focal agents are the majority of the slots, else "visitor".

A user's task gets scenarios with ``register_heldout(HeldOutScenario(...))`` once its test bots
are registered (``marl_render.bots.register_bot``; docs/authoring.md).
"""
from __future__ import annotations

import dataclasses

from marl_render.envs.bots import (
    HELDOUT,
    POPULATIONS,
    REGISTERED_SCENARIOS,
    HeldOutScenario,
    declared,
    heldout_scenario,
    scenarios,
)
from marl_render.envs.registry import list_envs, make_env
from marl_render.util.validation import describe

# The run-time half lives with the tasks' declarations (envs/bots.py), so that make_env(heldout=...)
# needs no layer above the envs; these names are this module's too, as they always were.
__all__ = ["HELDOUT", "HeldOutScenario", "declared", "heldout_scenario", "list_heldout", "register_heldout"]


def register_heldout(scenario: HeldOutScenario, *, overwrite: bool = False) -> None:
    """Make `scenario` known to make_env(heldout=...), list_heldout and every command line
    (``python -m marl_render.evaluate --scenario NAME`` or ``--scenario TASK``). Its task must be
    registered, its bots in the task's test population (``register_bot``), its focal agents and
    roles among the task's agents and teams at its ``num_agents`` and ``params`` (checked on a
    one-world env)."""
    if not isinstance(scenario, HeldOutScenario):
        raise TypeError(f"scenario must be a HeldOutScenario, got {type(scenario).__name__}")
    if not isinstance(scenario.name, str) or not scenario.name:
        raise ValueError(f"scenario.name must be a non-empty str, got {scenario.name!r}")
    if scenario.name == "all" or scenario.name in list_envs():  # --scenario TASK and --scenario all mean the lists
        raise ValueError(f"scenario.name must not be 'all' or a task's name ({scenario.name!r} stands for a list of "
                         f"scenarios on the command lines): call it e.g. {scenario.task}/{scenario.name}")
    if not isinstance(overwrite, bool):  # a truthy "no" would replace a registered scenario
        raise TypeError(f"overwrite must be a bool, got {describe(overwrite)}")
    if not isinstance(scenario.description, str):
        raise TypeError(f"scenario.description must be a str (one line), got {describe(scenario.description)}")
    if not isinstance(scenario.params, dict) or "num_agents" in scenario.params:
        raise ValueError(f"scenario {scenario.name!r}: params must be a dict of the task's keywords other than "
                         f"num_agents (scenario.num_agents sets it), got {describe(scenario.params)}")
    roles = scenario.bots_by_role
    if not isinstance(roles, dict) or not all(
            isinstance(names, (list, tuple)) and names and all(isinstance(n, str) for n in names)
            for names in roles.values()):
        raise ValueError(f"scenario {scenario.name!r}: bots_by_role must be a dict {{team: (bot names, ...)}} with "
                         f"at least one name per team, got {describe(roles)}")
    if scenario.name in HELDOUT and not overwrite:
        raise ValueError(f"a held-out scenario named {scenario.name!r} is already registered; pass overwrite=True "
                         f"to replace it")
    if scenario.task not in list_envs():
        raise ValueError(f"scenario.task must be a registered task among {list_envs()}, got {scenario.task!r}")
    test = POPULATIONS[scenario.task]["test"] if scenario.task in POPULATIONS else ()
    strangers = sorted({n for names in scenario.bots_by_role.values() for n in names} - set(test))
    if strangers or not scenario.bots_by_role:
        raise ValueError(f"scenario {scenario.name!r}: bots_by_role must name bots of {scenario.task}'s test "
                         f"population {list(test)} (marl_render.bots.register_bot), got {strangers or 'none'}")
    with make_env(scenario.task, num_worlds=1, resolution=8, **scenario.env_kwargs()) as probe:
        agents, teams = probe.agent_names, dict(probe.groups)
    unknown = [name for name in scenario.focal if name not in agents]
    if not scenario.focal or unknown:
        raise ValueError(f"scenario {scenario.name!r}: focal must name agents among {agents}, got "
                         f"{list(scenario.focal)}")
    if set(scenario.bots_by_role) - set(teams):
        raise ValueError(f"scenario {scenario.name!r}: bots_by_role's roles must be teams among {list(teams)}, got "
                         f"{list(scenario.bots_by_role)}")
    # The registry keeps its own copy: the caller's lists and dicts may change later without changing it.
    scenario = dataclasses.replace(scenario, focal=tuple(scenario.focal), params=dict(scenario.params),
                                   bots_by_role={team: tuple(names) for team, names in scenario.bots_by_role.items()})
    try:  # the focal env itself: every slot focal or played by a bot, at least one of each, the bots made
        make_env(scenario.task, heldout=scenario, num_worlds=1, resolution=8).close()
    except (ValueError, TypeError) as error:
        raise ValueError(f"scenario {scenario.name!r} does not make a focal-only env: {error}") from None
    REGISTERED_SCENARIOS[:] = [*[s for s in REGISTERED_SCENARIOS if s.name != scenario.name], scenario]


def list_heldout(task: str | None = None) -> list:
    """Names of the held-out scenarios (of `task` only, if given), in registry order."""
    if task is not None and task not in POPULATIONS:
        raise ValueError(f"task must be one of the multi-agent tasks {sorted(POPULATIONS)}, got {task!r}")
    return [s.name for s in scenarios() if task is None or s.task == task]


