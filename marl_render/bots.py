"""The bots of every multi-agent task as policies, and each task's training and test populations.

In the spirit of Melting Pot's puppets: each bot is the task's heuristic or a parameterised variant
of it (an interceptor predator that aims ahead, a permuted-code speaker, greedy and tagging
harvesters, ...). A task declares its bots in its own file, as data on its class (``bots``:
name -> ``envs.roster.Bot``, with a "train" or "test" population); this module turns them into
policies. Every bot reads the simulation state and plays any slot; which slots a held-out scenario
gives it is declared on the task too (``heldout``, read by marl_render/heldout.py).

    make_bot("tag", "interceptor")          # a Policy (marl_render/policies.py)
    POPULATIONS["tag"]["train"]             # names of the bots users may train with
    POPULATIONS["tag"]["test"]              # names held out for evaluation: none is in "train"

Each task's two populations share no bot: held-out scenarios use test bots only. A user's task
declares its bots on its class, or gets them with ``register_bot`` (docs/authoring.md): every
command line that takes bot names (``python -m marl_render.evaluate``, its cross-play roster) then
knows them, through ``--import MODULE`` of the module that registers them.
"""
from __future__ import annotations

from collections.abc import Mapping

import torch

from marl_render.envs import env_class, list_envs
from marl_render.envs import options as check
from marl_render.envs.arena import NOOP, wander  # noqa: F401  (wander: the shared script, importable from here)
from marl_render.envs.masking import sample_allowed
from marl_render.envs.roster import POPULATIONS as POPULATION_NAMES
from marl_render.envs.roster import Bot
from marl_render.validation import describe

from .policies import Policy, ScriptedPolicy, heuristic_policy


class Perturbed(Policy):
    """A bot that plays `base`, except that with probability `p` per (world, slot) and step it plays
    noop ("lazy") or a uniformly random action among those the action mask allows ("noisy")
    instead; its own seeded generator."""

    needs = frozenset({"sim"})

    def __init__(self, base: Policy, p: float, kind: str, seed: int = 0):
        self.base, self.p, self.kind = base, p, kind
        self.name = f"{kind}{p:g}"
        self.generator = torch.Generator().manual_seed(seed)

    def act(self, env, obs, worlds, slots):
        actions = self.base.act(env, obs, worlds, slots)
        swap = torch.rand(len(worlds), generator=self.generator) < self.p
        if self.kind == "lazy":
            other = torch.full_like(actions, NOOP)
        else:
            other = self._random(env, worlds, slots, actions.shape)
        return torch.where(swap.view(-1, *[1] * (actions.ndim - 1)), other, actions)

    def _random(self, env, worlds, slots, shape) -> torch.Tensor:
        """Uniformly random actions of the pairs: in [-1, 1] (continuous), else among the allowed.
        Drawn among all actions, then redrawn among the allowed where a draw is forbidden (uniform
        among the allowed all the same): where every action is allowed, the draws are the ones this
        bot made before it read the mask, and so are the results published with it."""
        if env.continuous:
            return torch.rand(shape, generator=self.generator) * 2 - 1
        drawn = torch.randint(env.num_actions, shape, generator=self.generator)
        mask = env.scenario.action_mask(env.sim, env.alive)[worlds, slots].cpu()  # [P, num_actions]
        forbidden = ~mask.gather(1, drawn[:, None])[:, 0]
        if not bool(forbidden.any()):
            return drawn
        return torch.where(forbidden, sample_allowed(mask[:, None], self.generator)[:, 0], drawn)


PERTURBED = {"noisy0.1": ("noisy", 0.1), "noisy0.2": ("noisy", 0.2), "noisy0.5": ("noisy", 0.5),
             "lazy0.5": ("lazy", 0.5)}  # heuristic variants register_bot takes by name: name -> (kind, probability)

_REGISTERED: dict = {}  # task -> {bot name: roster.Bot}: register_bot's, over the task class's own ``bots``


def roster(task: str) -> dict:
    """{bot name: roster.Bot} of `task`: the task class's ``bots`` (envs/roster.py), then those
    ``register_bot`` added (a registered name replaces the class's bot and moves to the end).
    The heuristic is not listed: it is every task's, in its train population."""
    registered = _REGISTERED.get(task, {})
    return {**{name: bot for name, bot in env_class(task).bots.items() if name not in registered}, **registered}


def populations(task: str) -> dict:
    """{"train": bot names users may train with (the heuristic first), "test": bot names of the
    held-out scenarios} of `task`; the two share no bot."""
    bots = roster(task)
    return {population: (*(("heuristic",) if population == "train" else ()),
                         *[name for name, bot in bots.items() if bot.population == population])
            for population in POPULATION_NAMES}


def has_bots(task) -> bool:
    """Whether `task` (any value) is a registered task with bots of its own or registered ones."""
    if not isinstance(task, str) or task not in list_envs():
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
        return iter([task for task in list_envs() if has_bots(task)])

    def __len__(self):
        return len(list(iter(self)))


POPULATIONS = Populations()


def register_bot(task: str, name: str, script=None, *, factory=None, description: str = "",
                 population: str = "test", overwrite: bool = False) -> None:
    """Make bot `name` of registered task `task` known to make_bot, bot_names, held-out scenarios
    (``register_heldout``) and every command line that takes bot names. A task of your own can
    declare its bots on its class instead (``bots = {name: roster.Bot(...)}``, docs/authoring.md).

    Give one of: `script`, a function ``script(env) -> actions`` of every agent of every world
    ([W, A] or [W, A, action_dim]) that reads ``env.sim`` (a scripted bot, as the built-in ones);
    `factory`, a function ``factory(seed) -> Policy`` (an object with ``act``, ``needs`` and
    ``reset``: a bot with its own state or generator); or neither, for a heuristic variant of
    ``PERTURBED`` ("noisy0.5", "lazy0.5", ...). `population`: "test" (held-out scenarios use these
    only) or "train" (bots a user may train with); the two stay disjoint. A task's first bot gives it
    the populations, with its scripted heuristic (``Scenario.heuristic``) in "train"."""
    if not isinstance(task, str) or task not in list_envs():
        raise ValueError(f"task must be a registered task (register_env first) among {list_envs()}, got {task!r}")
    if not isinstance(name, str) or not name:
        raise TypeError(f"name must be a non-empty str, got {describe(name)}")
    if population not in ("train", "test"):
        raise ValueError(f"population must be 'train' or 'test', got {population!r}")
    if not isinstance(description, str):
        raise TypeError(f"description of bot {name!r} must be a str (one line), got {describe(description)}")
    if not isinstance(overwrite, bool):  # a truthy "no" would replace a registered bot
        raise TypeError(f"overwrite must be a bool, got {describe(overwrite)}")
    if script is not None and factory is not None:
        raise ValueError(f"bot {name!r}: give script or factory, not both")
    for label, value in (("script", script), ("factory", factory)):
        if value is not None and not callable(value):
            raise TypeError(f"{label} of bot {name!r} must be callable, got {describe(value)}")
    if script is None and factory is None and name not in PERTURBED:
        raise ValueError(f"bot {name!r} needs a script or a factory (only the heuristic variants {list(PERTURBED)} "
                         f"need neither)")
    if name == "heuristic":
        raise ValueError("bot 'heuristic' is the task's own Scenario.heuristic, in every task's train population: "
                         "choose another name")
    current = populations(task)
    other = "train" if population == "test" else "test"
    if name in current[other]:
        raise ValueError(f"bot {name!r} is in {task}'s {other} population: the train and test populations share "
                         f"no bot")
    if name in current[population] and not overwrite:
        raise ValueError(f"bot {name!r} of {task} is already registered; pass overwrite=True to replace it")
    if script is not None:
        bot = Bot(description or (script.__doc__ or "").strip() or name, script=script, population=population)
    elif factory is not None:
        bot = Bot(description or name, factory=factory, population=population)
    else:
        kind, p = PERTURBED[name]
        bot = (Bot.lazy if kind == "lazy" else Bot.noisy)(p, population=population)
    # A new dict, never an edit of the old one; the name moves to the end of its population.
    _REGISTERED[task] = {**{k: v for k, v in _REGISTERED.get(task, {}).items() if k != name}, name: bot}


def bot_names(task: str) -> list:
    """Every bot of `task` (its populations' union)."""
    if not has_bots(task):
        raise ValueError(f"task must be one of the multi-agent tasks {sorted(POPULATIONS)}, got {task!r}")
    current = populations(task)
    return [*current["train"], *current["test"]]


def describe_bot(task: str, name: str) -> str:
    """The bot's one line (its roster.Bot's description)."""
    return "the task's scripted heuristic" if name == "heuristic" else roster(task)[name].description


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
