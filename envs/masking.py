"""Action masks: advice by default, a rule of the step with ``enforce_action_mask=True``.

A discrete task's ``action_mask(state, alive)`` says which actions each agent may take now; the
driver hands it out as ``obs["action_mask"]`` (TorchRL's action spec carries it too, PettingZoo
and gymnasium give it with ``action_mask=True``). By default it is advice: a step takes every
action in ``[0, num_actions)``, allowed or not, and the task's rules decide what it does (an agent
allowed only noop still moves on forward). ``EnvOptions(enforce_action_mask=True)`` (the keyword
``enforce_action_mask=True`` of make_env and of every front end) makes the driver refuse them:

* a step whose actions the mask of the current state forbids raises ValueError naming the worlds,
  agents and actions and what was allowed, before anything changes (state, counters and random
  generator stay as they were: the caller may correct the actions and step again);
* only the agents the step acts for are checked: agents that left the episode, and worlds a
  ``"next_step"`` autoreset restarts in this step, have their actions ignored anyway;
* ``random_actions()`` samples among the allowed actions, so ``env.step(env.random_actions())``
  always passes. ``sample_allowed`` is the one such sampler (the random policy, the noisy bots and
  the evaluation's random opponents use it too); an agent whose mask allows nothing, which only an
  agent out of the episode may have, gets action 0 (``with_fallback``).

Refusing was chosen over replacing a forbidden action by noop: a policy that picks forbidden
actions has a bug (or reads the mask of another step), and a silent replacement would train it
on actions it did not take.
"""
from __future__ import annotations

import torch
from torch import Tensor

SHOWN = 4  # refused (world, agent) pairs the error lists; it counts the rest


def forbidden(mask: Tensor, actions: Tensor, acting: Tensor) -> Tensor:
    """[W, A] bool: acting agents whose action (int64 [W, A]) mask [W, A, n] does not allow."""
    allowed = mask.gather(-1, actions[..., None])[..., 0]
    return acting & ~allowed


def refusal(refused: Tensor, mask: Tensor, actions: Tensor, agent_names: list, meanings) -> ValueError:
    """The ValueError of a refused step: the first SHOWN refused agents, their actions and the allowed."""
    worlds, agents = refused.nonzero(as_tuple=True)
    count = len(worlds)

    def named(action: int) -> str:
        return f"{action} ({meanings[action]!r})" if meanings else str(action)

    cases = []
    for w, a in zip(worlds[:SHOWN].tolist(), agents[:SHOWN].tolist(), strict=True):
        allowed = [named(i) for i in mask[w, a].nonzero()[:, 0].tolist()]
        cases.append(f"world {w} agent {agent_names[a]!r} took {named(int(actions[w, a]))}, "
                     f"allowed: [{', '.join(allowed)}]")
    more = f"; and {count - SHOWN} more" if count > SHOWN else ""
    return ValueError(f"actions must be allowed by the action mask (enforce_action_mask=True; the mask is "
                      f"obs['action_mask'] of the current state), got {count} forbidden: "
                      f"{'; '.join(cases)}{more}")


def with_fallback(mask: Tensor) -> Tensor:
    """A copy of mask [..., n] in which a row that allows nothing allows action 0 (noop in every
    built-in task). Only an agent out of the episode can have such a row (the driver refuses one for
    an agent in it), and it must still be given a valid value, which the step ignores: 0, what
    gymnasium's ``Discrete.sample(mask=...)`` gives for an all-zero mask and what the PettingZoo
    front end fills in for agents that left."""
    nothing = ~mask.any(-1, keepdim=True)
    return torch.cat((mask[..., :1] | nothing, mask[..., 1:]), -1)


def sample_allowed(mask: Tensor, generator: torch.Generator | None) -> Tensor:
    """int64 [W, A] on the CPU (as random_actions gives them): uniformly random actions among those
    mask [W, A, n] allows; 0 where a row allows nothing (``with_fallback``). The one sampler of
    random allowed actions: the driver's random_actions, the random policy and bots, and
    ``envs.evaluation.random_policy`` use it."""
    W, A, n = mask.shape
    weights = with_fallback(mask).reshape(W * A, n).to("cpu", torch.float32)
    return torch.multinomial(weights, 1, generator=generator).reshape(W, A)
