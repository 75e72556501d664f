"""The bots of every multi-agent task as policies, and each task's training and test populations.

In the spirit of Melting Pot's puppets: each bot is the task's heuristic or a parameterised variant
of it (an interceptor predator that aims ahead, a permuted-code speaker, greedy and tagging
harvesters, ...). A task declares its bots in its own file, as data on its class (``bots``:
name -> ``envs.roster.Bot``, with a "train" or "test" population); envs/bots.py turns them into
policies (this module's names too), and this one adds a user's with ``register_bot``. Every bot
reads the simulation state and plays any slot; which slots a held-out scenario gives it is declared
on the task too (``heldout``, marl_render/populations/heldout.py).

    make_bot("tag", "interceptor")          # a Policy (envs/policy.py)
    POPULATIONS["tag"]["train"]             # names of the bots users may train with
    POPULATIONS["tag"]["test"]              # names held out for evaluation: none is in "train"

Each task's two populations share no bot: held-out scenarios use test bots only. A user's task
declares its bots on its class, or gets them with ``register_bot`` (docs/authoring.md): every
command line that takes bot names (``python -m marl_render.evaluate``, its cross-play roster) then
knows them, through ``--import MODULE`` of the module that registers them.
"""
from __future__ import annotations

from marl_render.envs import list_envs
from marl_render.envs.arena import wander
from marl_render.envs.bots import POPULATIONS, REGISTERED_BOTS, bot_names, has_bots, make_bot, populations, roster
from marl_render.envs.policy import Perturbed
from marl_render.envs.roster import Bot
from marl_render.util.validation import describe

# The run-time half lives with the tasks' declarations (envs/bots.py), so that make_env(heldout=...)
# needs no layer above the envs; these names are this module's too, as they always were.
__all__ = ["PERTURBED", "POPULATIONS", "REGISTERED_BOTS", "Perturbed", "bot_names", "describe_bot", "has_bots",
           "make_bot", "populations", "register_bot", "roster", "wander"]


PERTURBED = {"noisy0.1": ("noisy", 0.1), "noisy0.2": ("noisy", 0.2), "noisy0.5": ("noisy", 0.5),
             "lazy0.5": ("lazy", 0.5)}  # heuristic variants register_bot takes by name: name -> (kind, probability)

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
    REGISTERED_BOTS[task] = {**{k: v for k, v in REGISTERED_BOTS.get(task, {}).items() if k != name}, name: bot}


def describe_bot(task: str, name: str) -> str:
    """The bot's one line (its roster.Bot's description)."""
    return "the task's scripted heuristic" if name == "heuristic" else roster(task)[name].description
