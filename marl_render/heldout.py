"""Held-out scenarios in Melting Pot's sense: a task, its parameters, which slots are focal, and the
background bots by role, all drawn from the task's test population (marl_render/bots.py). Each task
declares its own on its class (``heldout``: envs.roster.HeldOut, named "<task>/<name>" here).

    list_heldout()                       # every scenario's name, e.g. "tag/prey_vs_interceptors"
    HELDOUT["tag/prey_vs_interceptors"]  # its HeldOutScenario
    make_env("tag", heldout="tag/prey_vs_interceptors", num_worlds=32)   # its focal-only env

Tags: "resident" when the focal agents are the majority of the slots, else "visitor".

A user's task gets scenarios with ``register_heldout(HeldOutScenario(...))`` once its test bots
are registered (``marl_render.bots.register_bot``; docs/authoring.md).
"""
from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping

from marl_render.envs.focal import Population
from marl_render.envs.registry import env_class, list_envs, make_env
from marl_render.validation import describe

from .bots import POPULATIONS, make_bot


@dataclasses.dataclass(frozen=True)
class HeldOutScenario:
    """A task with focal slots and test bots on the others (named so as not to be taken for the
    task class ``Scenario``). `focal`: agent names; `bots_by_role`: team -> test bot names;
    `params`: the task's keywords (make_env's); `num_agents`: the slot count it is defined for."""

    name: str
    task: str
    description: str
    num_agents: int
    focal: tuple
    bots_by_role: dict
    params: dict = dataclasses.field(default_factory=dict)

    @property
    def tags(self) -> tuple:
        """("resident",) when the focal agents hold most of the slots, else ("visitor",)."""
        return ("resident",) if 2 * len(self.focal) > self.num_agents else ("visitor",)

    def population(self, seed: int = 0) -> Population:
        """A fresh population of this scenario's bots (seeded: the randomised variants' generators)."""
        return Population({team: [make_bot(self.task, name, seed + 1000 * i + j) for j, name in enumerate(names)]
                           for i, (team, names) in enumerate(self.bots_by_role.items())}, focal=self.focal)

    def env_kwargs(self) -> dict:
        """make_env keywords of the scenario's task: its slot count and parameters."""
        return {"num_agents": self.num_agents, **self.params}


_REGISTERED: list = []  # register_heldout's scenarios, in registration order


def declared(task: str) -> list:
    """The HeldOutScenarios that task `task`'s class declares (``heldout``: envs.roster.HeldOut),
    named "<task>/<name>"."""
    return _declared(task, env_class(task))


@functools.cache
def _declared(task: str, scenario_class: type) -> list:
    # One object per scenario and class (a task registered again under its name is read afresh).
    return [HeldOutScenario(f"{task}/{held.name}", task, held.description, held.num_agents, tuple(held.focal),
                            {team: tuple(names) for team, names in held.bots_by_role.items()}, dict(held.params))
            for held in scenario_class.heldout]


def _scenarios() -> list:
    """Every held-out scenario: the tasks' own (in list_envs order), then register_heldout's (one
    registered under a task's scenario's name replaces it)."""
    registered = {scenario.name for scenario in _REGISTERED}
    own = [scenario for task in list_envs() for scenario in declared(task)
           if scenario.name not in registered]
    return [*own, *_REGISTERED]


class HeldOutTable(Mapping):
    """The read-only table ``HELDOUT[name]`` -> HeldOutScenario, in list_heldout order. Each task
    keeps its scenarios on its own class (envs/roster.py); only register_heldout's are stored here."""

    def __getitem__(self, name):
        for scenario in _scenarios():
            if scenario.name == name:
                return scenario
        raise KeyError(name)

    def __iter__(self):
        return iter([scenario.name for scenario in _scenarios()])

    def __len__(self):
        return len(_scenarios())


HELDOUT = HeldOutTable()


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
    _REGISTERED[:] = [*[s for s in _REGISTERED if s.name != scenario.name], scenario]


def list_heldout(task: str | None = None) -> list:
    """Names of the held-out scenarios (of `task` only, if given), in registry order."""
    if task is not None and task not in POPULATIONS:
        raise ValueError(f"task must be one of the multi-agent tasks {sorted(POPULATIONS)}, got {task!r}")
    return [s.name for s in _scenarios() if task is None or s.task == task]


def heldout_scenario(name) -> HeldOutScenario:
    """The HeldOutScenario registered as `name` (see list_heldout); a HeldOutScenario is returned as
    it is. ValueError listing the registered names for any other value."""
    if isinstance(name, HeldOutScenario):
        return name
    if not isinstance(name, str):
        raise TypeError(f"heldout must be a str (one of the held-out scenarios {list(HELDOUT)}) or a HeldOutScenario, "
                        f"got {describe(name)}")
    if name not in HELDOUT:
        raise ValueError(f"heldout must be one of the held-out scenarios {list(HELDOUT)} (or a HeldOutScenario), "
                         f"got {name!r}")
    return HELDOUT[name]
