"""Scripted bots of every multi-agent task, and each task's training and test populations.

In the spirit of Melting Pot's puppets: each bot is the task's heuristic or a parameterised variant
of it (an interceptor predator that aims ahead, a permuted-code speaker, greedy and tagging
harvesters, ...). Every bot reads the simulation state and plays any slot; which slots a held-out
scenario gives it is in marl_render/heldout.py.

    make_bot("tag", "interceptor")          # a Policy (marl_render/policies.py)
    POPULATIONS["tag"]["train"]             # names of the bots users may train with
    POPULATIONS["tag"]["test"]              # names held out for evaluation: none is in "train"

Each task's two populations share no bot: held-out scenarios use test bots only. A user's task
(or a built-in one) gets bots with ``register_bot`` (docs/authoring.md): every command line that
takes bot names (``python -m marl_render.evaluate``, its cross-play roster) then knows them,
through ``--import MODULE`` of the module that registers them.
"""
from __future__ import annotations

import math

import torch

from marl_render.envs import list_envs
from marl_render.envs import options as check
from marl_render.envs.masking import sample_allowed
from marl_render.validation import describe

from .policies import Policy, ScriptedPolicy, heuristic_policy

NOOP = 0  # the egocentric tasks' action 0 (envs/egomotion.py)


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


# ---------------------------------------------------------------- scripts: env -> actions [W, A]
def wander(env) -> torch.Tensor:
    """Each agent drives round a circle of its own phase (half the arena's extent): covers the
    arena without looking at anything."""
    s = env.scenario
    hx, hy = s.arena_half_extent
    phase = torch.arange(env.num_agents) * (2 * math.pi / env.num_agents) + env.step_count[:, None].cpu() * 0.03
    target = torch.stack((0.5 * hx * torch.cos(phase), 0.5 * hy * torch.sin(phase)), -1).to(env.device)
    return s.steer_to(env.sim, target)


def tag_interceptor(env) -> torch.Tensor:
    """Predators aim where the nearest live prey will be in half a second; prey as the heuristic."""
    s, state, alive = env.scenario, env.sim, env.alive
    N = env.num_agents
    pos, vel = state.pos[:, :N], state.vel[:, :N]
    dist = torch.where(s.is_prey & alive[:, None, :], torch.cdist(pos, pos), math.inf)
    prey = dist.argmin(-1)[..., None].expand(-1, -1, 2)
    ahead = pos.gather(1, prey) + 0.5 * vel.gather(1, prey)
    chase = s.steer_to(state, ahead)
    return torch.where(s.is_predator, chase, s.heuristic(state, alive))


def tag_lazy_predator(env) -> torch.Tensor:
    """Predators chase only prey within 1 m, else wait; prey as the heuristic."""
    s, state, alive = env.scenario, env.sim, env.alive
    N = env.num_agents
    pos = state.pos[:, :N]
    near = (torch.where(s.is_prey & alive[:, None, :], torch.cdist(pos, pos), math.inf).amin(-1) < 1.0)
    actions = s.heuristic(state, alive)
    return torch.where(s.is_predator & ~near, NOOP, actions)


def tag_wandering_prey(env) -> torch.Tensor:
    """Prey wander round the arena, ignoring predators; predators as the heuristic."""
    s = env.scenario
    return torch.where(s.is_prey, wander(env), s.heuristic(env.sim, env.alive))


def tag_corner_prey(env) -> torch.Tensor:
    """Prey hide in the corner nearest to where they are; predators as the heuristic."""
    s, state = env.scenario, env.sim
    hx, hy = s.arena_half_extent
    pos = state.pos[:, :env.num_agents]
    corner = torch.stack((torch.sign(pos[..., 0]) * 0.85 * hx, torch.sign(pos[..., 1]) * 0.85 * hy), -1)
    return torch.where(s.is_prey, s.steer_to(state, corner), s.heuristic(state, env.alive))


def spread_nearest(env) -> torch.Tensor:
    """Each agent drives to its nearest landmark, whoever else takes it."""
    s, state = env.scenario, env.sim
    dist = torch.cdist(state.pos[:, :env.num_agents], state.landmarks)
    target = state.landmarks.gather(1, dist.argmin(-1)[..., None].expand(-1, -1, 2))
    return s.steer_to(state, target)


def speaker_permuted(env) -> torch.Tensor:
    """The speaker shows the colour after the goal's (a permuted code); the listener as the heuristic."""
    s, state = env.scenario, env.sim
    actions = s.heuristic(state, env.alive).clone()
    actions[:, 0] = 5 + (state.goal + 1) % s.num_targets
    return actions


def listener_first_target(env) -> torch.Tensor:
    """The listener drives to the first target whatever the lamp shows; the speaker as the heuristic."""
    s, state = env.scenario, env.sim
    actions = s.heuristic(state, env.alive).clone()
    actions[:, 1] = s.steer_to(state, state.targets[:, :1].expand(-1, 2, 2))[:, 1]
    return actions


def commons_greedy(env) -> torch.Tensor:
    """Each harvester drives to the nearest present apple, ripe or not (it strips patches bare)."""
    s, state = env.scenario, env.sim
    W, N = env.num_worlds, env.num_agents
    dist = torch.cdist(state.pos[:, :N], s.apples.expand(W, -1, -1))
    dist = torch.where(state.present[:, None, :], dist, math.inf)
    target = torch.where(torch.isinf(dist.amin(-1))[..., None], state.pos[:, :N], s.apples[dist.argmin(-1)])
    return torch.where(state.timeout > 0, NOOP, s.steer_to(state, target))


def commons_tagger(env) -> torch.Tensor:
    """A greedy harvester that zaps (action 5) every fourth step."""
    zap = (env.step_count[:, None] % 4 == 0) & (env.sim.timeout == 0)
    return torch.where(zap, 5, commons_greedy(env))


def push_ball_chaser(env) -> torch.Tensor:
    """Every agent drives straight at the ball."""
    state = env.sim
    return env.scenario.steer_to(state, state.pos[:, -1:].expand(-1, env.num_agents, 2))


def push_goalkeeper(env) -> torch.Tensor:
    """Every agent stands on its own goal line, level with the ball."""
    s, state = env.scenario, env.sim
    own_goal_y = -s.side * 0.85 * s.arena_half_extent[1]  # [N]
    ball_x = state.pos[:, -1:, 0].expand(-1, env.num_agents)
    return s.steer_to(state, torch.stack((ball_x, own_goal_y.expand_as(ball_x)), -1))


def flag_all_attack(env) -> torch.Tensor:
    """Every agent fetches the enemy flag and carries it home (or goes home while a teammate has it)."""
    s, state = env.scenario, env.sim
    enemy = 1 - s.team
    carried = (state.carrier[:, enemy] >= 0)[..., None]
    target = torch.where(carried, s.base[s.team].expand(env.num_worlds, -1, -1), s.flag_position(state)[:, enemy])
    return s.steer_to(state, target)


def flag_all_defend(env) -> torch.Tensor:
    """Every agent guards the point 1 m in front of its own flag."""
    s, state = env.scenario, env.sim
    guard = s.base[s.team] - s.side[:, None] * torch.tensor([0.0, 1.0], device=env.device)
    return s.steer_to(state, guard.expand(env.num_worlds, -1, -1))


SCRIPTS: dict = {  # task -> bot name -> (script, one line)
    "tag": {"interceptor": (tag_interceptor, "predators aim half a second ahead of the prey"),
            "lazy_predator": (tag_lazy_predator, "predators chase only prey within 1 m"),
            "wandering_prey": (tag_wandering_prey, "prey wander round the arena, ignoring predators"),
            "corner_prey": (tag_corner_prey, "prey hide in their nearest corner")},
    "spread": {"nearest_landmark": (spread_nearest, "drives to its nearest landmark, whoever else takes it"),
               "wanderer": (wander, "drives round a circle, ignoring landmarks")},
    "speaker_listener": {"permuted_speaker": (speaker_permuted, "the speaker shows the next colour (a permuted code)"),
                         "first_target_listener": (listener_first_target, "the listener ignores the lamp")},
    "commons": {"greedy": (commons_greedy, "harvests the nearest apple, ripe or not"),
                "tagger": (commons_tagger, "greedy, and zaps every fourth step")},
    "push": {"ball_chaser": (push_ball_chaser, "drives straight at the ball"),
             "goalkeeper": (push_goalkeeper, "stands on its goal line, level with the ball")},
    "capture_flag": {"all_attack": (flag_all_attack, "fetches the enemy flag, never defends"),
                     "all_defend": (flag_all_defend, "guards its own flag, never attacks")},
    "forage": {"wanderer": (wander, "drives round a circle, ignoring items")},
    "rooms": {"wanderer": (wander, "drives round a circle, ignoring doors and the goal")},
}
PERTURBED = {"noisy0.1": ("noisy", 0.1), "noisy0.2": ("noisy", 0.2), "noisy0.5": ("noisy", 0.5),
             "lazy0.5": ("lazy", 0.5)}  # heuristic variants: name -> (kind, probability)

POPULATIONS: dict = {  # task -> {"train": bots users may train with, "test": bots of held-out scenarios}
    "tag": {"train": ("heuristic", "noisy0.2"), "test": ("interceptor", "lazy_predator", "wandering_prey",
                                                          "corner_prey")},
    "spread": {"train": ("heuristic", "noisy0.2"), "test": ("nearest_landmark", "wanderer", "lazy0.5")},
    "speaker_listener": {"train": ("heuristic", "noisy0.1"), "test": ("permuted_speaker", "first_target_listener",
                                                                       "noisy0.5")},
    "commons": {"train": ("heuristic", "noisy0.1"), "test": ("greedy", "tagger", "lazy0.5")},
    "push": {"train": ("heuristic", "noisy0.2"), "test": ("ball_chaser", "goalkeeper", "lazy0.5")},
    "capture_flag": {"train": ("heuristic", "noisy0.2"), "test": ("all_attack", "all_defend", "lazy0.5")},
    "forage": {"train": ("heuristic", "noisy0.2"), "test": ("wanderer", "lazy0.5", "noisy0.5")},
    "rooms": {"train": ("heuristic", "noisy0.2"), "test": ("wanderer", "lazy0.5", "noisy0.5")},
}


FACTORIES: dict = {}  # task -> bot name -> (factory(seed) -> Policy, one line): register_bot's factory bots


def register_bot(task: str, name: str, script=None, *, factory=None, description: str = "",
                 population: str = "test", overwrite: bool = False) -> None:
    """Make bot `name` of registered task `task` known to make_bot, bot_names, held-out scenarios
    (``register_heldout``) and every command line that takes bot names.

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
    populations = POPULATIONS.get(task, {"train": ("heuristic",), "test": ()})
    other = "train" if population == "test" else "test"
    if name in populations[other]:
        raise ValueError(f"bot {name!r} is in {task}'s {other} population: the train and test populations share "
                         f"no bot")
    if name in populations[population] and not overwrite:
        raise ValueError(f"bot {name!r} of {task} is already registered; pass overwrite=True to replace it")
    # New entries, never edits of the tables' own dicts (which the built-in tasks share).
    POPULATIONS[task] = {**populations, population: (*[n for n in populations[population] if n != name], name)}
    SCRIPTS[task] = {k: v for k, v in SCRIPTS.get(task, {}).items() if k != name}
    FACTORIES[task] = {k: v for k, v in FACTORIES.get(task, {}).items() if k != name}
    if script is not None:
        SCRIPTS[task][name] = (script, description or (script.__doc__ or "").strip() or name)
    if factory is not None:
        FACTORIES[task][name] = (factory, description or name)


def bot_names(task: str) -> list:
    """Every bot of `task` (its populations' union)."""
    if task not in POPULATIONS:
        raise ValueError(f"task must be one of the multi-agent tasks {sorted(POPULATIONS)}, got {task!r}")
    return [*POPULATIONS[task]["train"], *POPULATIONS[task]["test"]]


def describe_bot(task: str, name: str) -> str:
    if name == "heuristic":
        return "the task's scripted heuristic"
    if name in FACTORIES.get(task, {}):
        return FACTORIES[task][name][1]
    if name in PERTURBED and name not in SCRIPTS.get(task, {}):
        kind, p = PERTURBED[name]
        return f"the heuristic, playing {'noop' if kind == 'lazy' else 'a random action'} with probability {p:g}"
    return SCRIPTS[task][name][1]


def make_bot(task: str, name: str, seed: int = 0) -> Policy:
    """A fresh bot of `task` by name (see bot_names); `seed` seeds the randomised variants."""
    if name not in bot_names(task):
        raise ValueError(f"bot must be one of {task}'s bots {bot_names(task)}, got {name!r}")
    if check.seed("seed", seed) is None:  # a generator seed as the envs take it, [0, 2**63)
        raise TypeError("seed must be an int in [0, 2**63), got None")
    seed = int(seed)
    if name == "heuristic":
        return heuristic_policy()
    if name in FACTORIES.get(task, {}):
        bot = FACTORIES[task][name][0](seed)
        if not callable(getattr(bot, "act", None)):
            raise TypeError(f"the factory of bot {name!r} of {task} must return a Policy (an object with act), got "
                            f"{describe(bot)}")
        return bot
    if name in PERTURBED and name not in SCRIPTS.get(task, {}):
        kind, p = PERTURBED[name]
        return Perturbed(heuristic_policy(), p, kind, seed)
    script, description = SCRIPTS[task][name]
    return ScriptedPolicy(name, script, description)
