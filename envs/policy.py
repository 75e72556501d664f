"""The policy protocol: what plays a slot of an env, focal or background (one protocol for every
layer: a focal-only env's bots, the evaluations, the trainer's greedy actor, a loaded run).

A policy acts for any set of (world, slot) pairs of a driver (``marl_render.envs.make_env``) at
once: one call per step covers every pair it plays, in every world, so a population of bots costs
one batched call per distinct bot, never a loop over worlds.

    actions = policy.act(env, obs, worlds, slots)         # [P] (or [P, action_dim]) for P pairs
    policy = heuristic_policy()                           # the task's scripted heuristic
    policy = as_policy(function)                          # a function policy(env, obs, generator)

- ``env`` is the full driver (``BatchedEnv``): scripted bots read its simulation state
  (``env.sim``, ``env.alive``, ``env.step_count``), as Melting Pot's puppets read their cues.
- ``obs`` holds, for the keys in ``policy.needs``, the observations of exactly those pairs,
  ``[P, ...]``: a policy sees only what its own slots see.
- ``worlds``, ``slots``: int64 [P], the pairs it plays (slot = the agent's index in the task).
- ``reset(env, worlds)`` (bool [W]) is called when those worlds start a new episode: recurrent state
  (frame stacks, held actions) is kept per (world, slot) and cleared there.

``needs`` names the observation keys it reads ("pixels", "state", "action_mask"); "sim" means it
reads the driver's simulation state instead. A function ``policy(env, obs, generator) -> actions``
of every agent of every world is not a second protocol: ``as_policy`` adapts it. A task's bots
are envs/bots.py's; a trained run is ``marl_render.populations.policies.load_policy``'s.
"""
from __future__ import annotations

import torch

from marl_render.util.validation import describe

from .arena import NOOP
from .masking import sample_allowed


class Policy:
    """The interface: ``act(env, obs, worlds, slots)`` and ``reset(env, worlds)``; see the module docstring."""

    name: str = "policy"
    needs: frozenset = frozenset()
    env_kwargs: dict = {}  # make_env keywords this policy requires of the env it plays (resolution, ...)

    def reset(self, env, worlds: torch.Tensor) -> None:
        """Worlds (bool [W]) that start a new episode: forget what was kept for them. Stateless: nothing."""

    def act(self, env, obs: dict, worlds: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
        """Actions of the (world, slot) pairs `worlds`, `slots` (int64 [P]): [P] (or [P, action_dim]),
        from `obs`, the observations of exactly those pairs ([P, ...] for the keys in ``needs``)."""
        raise NotImplementedError

    def __repr__(self):
        return f"{type(self).__name__}({self.name!r})"


class CallablePolicy(Policy):
    """A policy given as a function ``policy(env, obs, generator) -> actions`` of every agent of every
    world ([W, A] or [W, A, action_dim]): the protocol of ``marl_render.envs.evaluation`` (its
    ``random_policy`` and ``heuristic_policy``, the trainer's ``GreedyPolicy``) as a Policy. The
    function is handed the observations of every agent, its own pairs' in their places (zeros
    elsewhere, every action allowed), and `generator`; of its actions, its pairs' are taken. A function
    with a ``needs`` attribute (the trainer's GreedyPolicy: a task's vector observations) is handed those
    keys too."""

    needs = frozenset({"pixels", "depth", "state", "lidar", "agent_id", "action_mask"})

    def __init__(self, function, generator: torch.Generator | None = None, name: str | None = None):
        self.needs = CallablePolicy.needs | frozenset(getattr(function, "needs", ()))
        self.function = function
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.name = name or getattr(function, "__name__", type(function).__name__)

    def act(self, env, obs, worlds, slots):
        """The function's actions of the pairs `worlds`, `slots` (it sees every agent, theirs in place)."""
        full = {}
        for key, value in obs.items():
            # Every action allowed where the function sees no pair of its own: a random draw there stays valid.
            fill = value.new_ones if key == "action_mask" else value.new_zeros
            full[key] = fill((env.num_worlds, env.num_agents, *value.shape[1:]))
            full[key][worlds, slots] = value
        return self.function(env, full, self.generator)[worlds, slots]


def as_policy(policy, generator: torch.Generator | None = None) -> Policy:
    """Whatever plays an env, as a Policy: an object with ``act`` (a Policy: ``load_policy``'s
    actor, ``heuristic_policy()``, ``RandomPolicy``, a bot) as it is, a function ``policy(env, obs,
    generator)`` (``marl_render.envs.evaluation.random_policy`` and ``heuristic_policy``, the
    trainer's greedy policy) as a CallablePolicy drawing from `generator`. Every evaluation
    (``marl_render.envs.evaluation.evaluate``, ``marl_render.evaluate.evaluate``, cross-play,
    ``marl_render.generalise``) takes its policies through this one adapter."""
    if callable(getattr(policy, "act", None)):
        return policy
    if callable(policy) and not isinstance(policy, (str, type)):
        return CallablePolicy(policy, generator)
    raise TypeError(f"policy must be an object with act(env, obs, worlds, slots) (a Policy, e.g. load_policy's) or a "
                    f"function policy(env, obs, generator) -> actions, got {describe(policy)}")


def joint_actions(policy: Policy, env, obs: dict) -> torch.Tensor:
    """`policy`'s actions for every agent of every world of the driver `env` ([W, A] or [W, A,
    action_dim]) from its observations `obs` ([W, A, ...] each): one ``act`` call for all pairs."""
    W, A = env.num_worlds, env.num_agents
    worlds, slots = torch.arange(W).repeat_interleave(A), torch.arange(A).repeat(W)
    seen = {key: value.flatten(0, 1) for key, value in obs.items() if key in policy.needs}
    return policy.act(env, seen, worlds, slots).reshape(W, A, *env.spec.action.shape)


class RandomPolicy(Policy):
    """Uniformly random valid actions (among those the action mask allows), from its own generator."""

    needs = frozenset({"action_mask"})

    def __init__(self, seed: int = 0, name: str = "random"):
        self.name, self.generator = name, torch.Generator().manual_seed(seed)

    def act(self, env, obs, worlds, slots):
        """A uniformly random valid action per pair (uniform in [-1, 1] per dimension for continuous actions)."""
        if env.continuous:
            return torch.rand(len(worlds), env.action_dim, generator=self.generator) * 2 - 1
        if not len(worlds):
            return torch.zeros(0, dtype=torch.int64)
        return sample_allowed(obs["action_mask"][:, None], self.generator)[:, 0]


class ScriptedPolicy(Policy):
    """A bot that reads the simulation state: ``script(env)`` returns actions for every agent of every
    world ([W, A] or [W, A, action_dim]), of which the pairs played are taken."""

    needs = frozenset({"sim"})

    def __init__(self, name: str, script, description: str = ""):
        self.name, self.script, self.description = name, script, description

    def act(self, env, obs, worlds, slots):
        """The script's actions for every agent of every world, taken at the pairs `worlds`, `slots`."""
        return self.script(env)[worlds, slots]


def heuristic_policy(env=None, obs=None, generator=None):
    """The task's own scripted heuristic (``Scenario.heuristic``), the 1 of the normalised score.

    ``heuristic_policy()``: a fresh ScriptedPolicy of it. Passed itself where a function policy is
    taken (``evaluate("spread", heuristic_policy)``), it is that function: ``heuristic_policy(env,
    obs, generator)`` gives the driver's checked heuristic actions of every agent, [W, A]."""
    if env is None:
        return ScriptedPolicy("heuristic", lambda env: env.scenario.heuristic(env.sim, env.alive),
                              "the task's scripted heuristic")
    return env.heuristic_actions()


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
