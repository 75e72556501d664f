"""The bots and held-out scenarios that the tasks declare (envs/roster.py), at run time: a declared
bot as a Policy (envs/policy.py), a held-out scenario as the population of a focal-only env
(envs/focal.py), for ``make_env(task, heldout=NAME)``.

    make_bot("tag", "interceptor", seed=0)            # a Policy
    heldout_scenario("tag/prey_vs_interceptors")      # a HeldOutScenario; .population(seed), .env_kwargs()

A task's own bots and scenarios are data on its class. ``register_bot`` and ``register_heldout``
(the populations layer, marl_render/populations/) check a user's additions and store them here
(REGISTERED_BOTS, REGISTERED_SCENARIOS), so this layer resolves every name without importing the
layers above it.
"""
from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping

from marl_render.util.validation import describe

from . import options as check
from . import registry  # the module: registry.make_env reads this one's heldout_scenario
from .focal import Population
from .policy import Perturbed, Policy, ScriptedPolicy, heuristic_policy
from .roster import POPULATIONS as POPULATION_NAMES

REGISTERED_BOTS: dict = {}  # task -> {bot name: roster.Bot}: register_bot's, over the task class's own ``bots``


def roster(task: str) -> dict:
    """{bot name: roster.Bot} of `task`: the task class's ``bots`` (envs/roster.py), then those
    ``register_bot`` added (a registered name replaces the class's bot and moves to the end).
    The heuristic is not listed: it is every task's, in its train population."""
    registered = REGISTERED_BOTS.get(task, {})
    own = registry.env_class(task).bots
    return {**{name: bot for name, bot in own.items() if name not in registered}, **registered}


def populations(task: str) -> dict:
    """{"train": bot names users may train with (the heuristic first), "test": bot names of the
    held-out scenarios} of `task`; the two share no bot."""
    bots = roster(task)
    return {population: (*(("heuristic",) if population == "train" else ()),
                         *[name for name, bot in bots.items() if bot.population == population])
            for population in POPULATION_NAMES}


def has_bots(task) -> bool:
    """Whether `task` (any value) is a registered task with bots of its own or registered ones."""
    if not isinstance(task, str) or task not in registry.list_envs():
        return False
    return bool(roster(task))


class Populations(Mapping):
    """The read-only table ``POPULATIONS[task]`` = populations(task), over the registered tasks that
    have bots (their classes' ``bots`` or ``register_bot``'s), in ``list_envs`` order. Each task
    keeps its bots in its own class (envs/roster.py); nothing is stored here."""

    def __getitem__(self, task):
        if not has_bots(task):
            raise KeyError(task)
        return populations(task)

    def __iter__(self):
        return iter([task for task in registry.list_envs() if has_bots(task)])

    def __len__(self):
        return len(list(iter(self)))


POPULATIONS = Populations()


def bot_names(task: str) -> list:
    """Every bot of `task` (its populations' union)."""
    if not has_bots(task):
        raise ValueError(f"task must be one of the multi-agent tasks {sorted(POPULATIONS)}, got {task!r}")
    current = populations(task)
    return [*current["train"], *current["test"]]


def make_bot(task: str, name: str, seed: int = 0) -> Policy:
    """A fresh bot of `task` by name (see bot_names); `seed` seeds the randomised variants."""
    if name not in bot_names(task):
        raise ValueError(f"bot must be one of {task}'s bots {bot_names(task)}, got {name!r}")
    if check.seed("seed", seed) is None:  # a generator seed as the envs take it, [0, 2**63)
        raise TypeError("seed must be an int in [0, 2**63), got None")
    seed = int(seed)
    if name == "heuristic":
        return heuristic_policy()
    bot = roster(task)[name]
    if bot.factory is not None:
        made = bot.factory(seed)
        if not callable(getattr(made, "act", None)):
            raise TypeError(f"the factory of bot {name!r} of {task} must return a Policy (an object with act), got "
                            f"{describe(made)}")
        return made
    if bot.script is None:
        kind, p = bot.variant
        return Perturbed(heuristic_policy(), p, kind, seed)
    return ScriptedPolicy(name, bot.script, bot.description)


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


REGISTERED_SCENARIOS: list = []  # register_heldout's scenarios, in registration order


def declared(task: str) -> list:
    """The HeldOutScenarios that task `task`'s class declares (``heldout``: envs.roster.HeldOut),
    named "<task>/<name>"."""
    return _declared(task, registry.env_class(task))


@functools.cache
def _declared(task: str, scenario_class: type) -> list:
    # One object per scenario and class (a task registered again under its name is read afresh).
    return [HeldOutScenario(f"{task}/{held.name}", task, held.description, held.num_agents, tuple(held.focal),
                            {team: tuple(names) for team, names in held.bots_by_role.items()}, dict(held.params))
            for held in scenario_class.heldout]


def scenarios() -> list:
    """Every held-out scenario: the tasks' own (in list_envs order), then register_heldout's (one
    registered under a task's scenario's name replaces it)."""
    registered = {scenario.name for scenario in REGISTERED_SCENARIOS}
    own = [scenario for task in registry.list_envs() for scenario in declared(task)
           if scenario.name not in registered]
    return [*own, *REGISTERED_SCENARIOS]


class HeldOutTable(Mapping):
    """The read-only table ``HELDOUT[name]`` -> HeldOutScenario, in list_heldout order. Each task
    keeps its scenarios on its own class (envs/roster.py); only register_heldout's are stored here."""

    def __getitem__(self, name):
        for scenario in scenarios():
            if scenario.name == name:
                return scenario
        raise KeyError(name)

    def __iter__(self):
        return iter([scenario.name for scenario in scenarios()])

    def __len__(self):
        return len(scenarios())


HELDOUT = HeldOutTable()


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
