"""What a task declares besides its rules: its scripted bots, held-out scenarios, sides, card text
and training defaults, as data on the ``Scenario`` class (Melting Pot keeps rosters as data; VMAS
keeps the heuristic in the task file). Nothing here runs a policy: the populations layer
(``marl_render.populations.bots``, ``marl_render.populations.heldout``) turns these declarations
into bots and scenarios, so that adding a task touches one file.

    class Tag(ArenaScenario):
        sides = ("predator", "prey")
        bots = {"interceptor": Bot("aims where the nearest prey will be", script=interceptor),
                "noisy0.2": Bot.noisy(0.2, population="train")}
        heldout = (HeldOut("prey_vs_interceptors", "one focal prey against interceptors", num_agents=4,
                           focal=("prey_0",), bots_by_role={"predator": ("interceptor",)}),)
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable

POPULATIONS = ("train", "test")  # users may train with "train" bots; held-out scenarios use "test" bots only
VARIANTS = ("noisy", "lazy")  # the heuristic, playing a random action / noop with some probability


@dataclasses.dataclass(frozen=True)
class Bot:
    """A scripted bot of a task. `script(env) -> actions` of every agent of every world ([W, A] or
    [W, A, action_dim]) reads the driver's state (``env.sim``, ``env.alive``, ``env.step_count``,
    ``env.scenario``); or, with no script, `variant` = (kind, p): the task's heuristic, playing a
    random allowed action ("noisy") or noop ("lazy") with probability p per slot and step; or
    `factory(seed) -> Policy` (an object with ``act``, ``needs`` and ``reset``): a bot with its own
    state or generator."""

    description: str
    script: Callable | None = None
    population: str = "test"
    variant: tuple | None = None
    factory: Callable | None = None

    @classmethod
    def noisy(cls, p: float, population: str = "test") -> Bot:
        return cls(f"the heuristic, playing a random action with probability {p:g}", population=population,
                   variant=("noisy", p))

    @classmethod
    def lazy(cls, p: float, population: str = "test") -> Bot:
        return cls(f"the heuristic, playing noop with probability {p:g}", population=population,
                   variant=("lazy", p))


@dataclasses.dataclass(frozen=True)
class HeldOut:
    """A held-out scenario of the task that declares it (named "task/name"): `focal` agent names, the
    other slots played by test bots by team (`bots_by_role`: team -> bot names; each episode draws one
    per background slot of the team, envs/focal.py), for `num_agents` slots and the task keywords `params`."""

    name: str
    description: str
    num_agents: int
    focal: tuple
    bots_by_role: dict
    params: dict = dataclasses.field(default_factory=dict)
