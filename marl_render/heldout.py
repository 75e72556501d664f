"""Held-out scenarios in Melting Pot's sense: a task, its parameters, which slots are focal, and the
background bots by role, all drawn from the task's test population (marl_render/bots.py).

    list_heldout()                       # every scenario's name, e.g. "tag/prey_vs_interceptors"
    HELDOUT["tag/prey_vs_interceptors"]  # its HeldOutScenario
    make_env("tag", heldout="tag/prey_vs_interceptors", num_worlds=32)   # its focal-only env

Tags: "resident" when the focal agents are the majority of the slots, else "visitor".

A user's task gets scenarios with ``register_heldout(HeldOutScenario(...))`` once its test bots
are registered (``marl_render.bots.register_bot``; docs/authoring.md).
"""
from __future__ import annotations

import dataclasses

from marl_render.envs.focal import Population
from marl_render.envs.registry import list_envs, make_env
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


def _names(prefix: str, indices) -> tuple:
    return tuple(f"{prefix}_{i}" for i in indices)


_SCENARIOS = [
    HeldOutScenario("tag/prey_vs_interceptors", "tag", "one focal prey against predators that aim ahead or wait",
                    4, _names("prey", [0]), {"predator": ("interceptor", "lazy_predator")}),
    HeldOutScenario("tag/predators_vs_wanderers", "tag", "focal predators hunt prey that wander or hide in corners",
                    4, _names("predator", range(3)), {"prey": ("wandering_prey", "corner_prey")}),
    HeldOutScenario("tag/pair_with_interceptor", "tag",
                    "two focal predators with an interceptor teammate, against a wandering or hiding prey",
                    4, _names("predator", range(2)), {"predator": ("interceptor",),
                                                      "prey": ("wandering_prey", "corner_prey")}),
    HeldOutScenario("spread/two_with_nearest", "spread",
                    "two focal agents with one partner that takes its nearest landmark or idles half the time",
                    3, _names("agent", range(2)), {"agents": ("nearest_landmark", "lazy0.5")}),
    HeldOutScenario("spread/one_among_nearest", "spread",
                    "one focal agent among two partners that take their nearest landmark",
                    3, _names("agent", [0]), {"agents": ("nearest_landmark",)}),
    HeldOutScenario("spread/two_with_wanderer", "spread", "two focal agents with one partner that wanders",
                    3, _names("agent", range(2)), {"agents": ("wanderer",)}),
    HeldOutScenario("speaker_listener/permuted_speaker", "speaker_listener",
                    "a focal listener with a speaker whose lamp code is permuted (convention following)",
                    2, ("listener_0",), {"speaker": ("permuted_speaker",)}),
    HeldOutScenario("speaker_listener/noisy_speaker", "speaker_listener",
                    "a focal listener with a speaker that shows a random colour half the time",
                    2, ("listener_0",), {"speaker": ("noisy0.5",)}),
    HeldOutScenario("speaker_listener/deaf_listener", "speaker_listener",
                    "a focal speaker with a listener that ignores the lamp", 2, ("speaker_0",),
                    {"listener": ("first_target_listener",)}),
    HeldOutScenario("commons/resident_with_greedy", "commons",
                    "four focal harvesters with one greedy or tagging visitor", 5, _names("agent", range(4)),
                    {"agents": ("greedy", "tagger")}),
    HeldOutScenario("commons/visitor_among_taggers", "commons",
                    "one focal harvester among four greedy harvesters that zap", 5, _names("agent", [0]),
                    {"agents": ("tagger", "greedy")}),
    HeldOutScenario("commons/resident_with_lazy", "commons", "three focal harvesters with two that idle half the time",
                    5, _names("agent", range(3)), {"agents": ("lazy0.5",)}),
    HeldOutScenario("push/red_vs_chasers", "push", "focal red team against ball chasers or goalkeepers",
                    4, _names("red", range(2)), {"blue": ("ball_chaser", "goalkeeper")}),
    HeldOutScenario("push/blue_vs_chasers", "push", "focal blue team against ball chasers or goalkeepers",
                    4, _names("blue", range(2)), {"red": ("ball_chaser", "goalkeeper")}),
    HeldOutScenario("push/with_lazy_teammate", "push",
                    "one focal red player with an idle-half-the-time teammate, against ball chasers",
                    4, ("red_0",), {"red": ("lazy0.5",), "blue": ("ball_chaser",)}),
    HeldOutScenario("capture_flag/red_vs_attackers", "capture_flag",
                    "focal red team against a team that only attacks or only defends", 16, _names("red", range(8)),
                    {"blue": ("all_attack", "all_defend")}),
    HeldOutScenario("capture_flag/blue_vs_defenders", "capture_flag",
                    "focal blue team against a team that only defends or idles half the time",
                    16, _names("blue", range(8)), {"red": ("all_defend", "lazy0.5")}),
    HeldOutScenario("capture_flag/resident_red", "capture_flag",
                    "focal red team and half of blue, with four blue attackers", 16,
                    _names("red", range(8)) + _names("blue", range(4)), {"blue": ("all_attack",)}),
    # The same opponents at the reference trainer's 2 v 2 (docs/baselines): its runs' agent one-hot fixes
    # their team size, so without these capture_flag's trained actors would play no scenario.
    HeldOutScenario("capture_flag/duel_red_vs_attackers", "capture_flag",
                    "a focal red pair against a pair that only attacks or only defends", 4, _names("red", range(2)),
                    {"blue": ("all_attack", "all_defend")}),
    HeldOutScenario("capture_flag/duel_blue_vs_defenders", "capture_flag",
                    "a focal blue pair against a pair that only defends or idles half the time",
                    4, _names("blue", range(2)), {"red": ("all_defend", "lazy0.5")}),
    HeldOutScenario("capture_flag/duel_red_with_lazy_teammate", "capture_flag",
                    "one focal red player with a teammate that idles half the time, against attackers",
                    4, ("red_0",), {"red": ("lazy0.5",), "blue": ("all_attack",)}),
    HeldOutScenario("forage/two_with_wanderer", "forage", "two focal foragers with one that wanders",
                    3, _names("agent", range(2)), {"agents": ("wanderer",)}),
    HeldOutScenario("forage/one_among_noisy", "forage", "one focal forager among two that act at random half the time",
                    3, _names("agent", [0]), {"agents": ("noisy0.5", "lazy0.5")}),
    HeldOutScenario("forage/two_with_lazy", "forage", "two focal foragers with one that idles half the time",
                    3, _names("agent", range(2)), {"agents": ("lazy0.5",)}),
    HeldOutScenario("rooms/with_wanderer", "rooms", "a focal explorer with a partner that wanders",
                    2, ("agent_0",), {"agents": ("wanderer",)}),
    HeldOutScenario("rooms/with_lazy", "rooms", "a focal explorer with a partner that idles half the time",
                    2, ("agent_0",), {"agents": ("lazy0.5",)}),
    HeldOutScenario("rooms/with_noisy", "rooms", "a focal explorer with a partner that acts at random half the time",
                    2, ("agent_0",), {"agents": ("noisy0.5",)}),
]
HELDOUT: dict = {s.name: s for s in _SCENARIOS}


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
    test = POPULATIONS.get(scenario.task, {}).get("test", ())
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
    if scenario.name in HELDOUT:
        _SCENARIOS.remove(HELDOUT[scenario.name])
    _SCENARIOS.append(scenario)
    HELDOUT[scenario.name] = scenario


def list_heldout(task: str | None = None) -> list:
    """Names of the held-out scenarios (of `task` only, if given), in registry order."""
    if task is not None and task not in POPULATIONS:
        raise ValueError(f"task must be one of the multi-agent tasks {sorted(POPULATIONS)}, got {task!r}")
    return [s.name for s in _SCENARIOS if task is None or s.task == task]


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
