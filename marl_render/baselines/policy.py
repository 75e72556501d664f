"""The learned policy during training, as ``marl_render.envs.evaluation.evaluate`` takes it: greedy
actions. A function policy ``policy(env, obs, generator)``, which ``as_policy`` adapts to the one
policy protocol (envs/policy.py); a saved run is ``load_policy``'s ``ActorPolicy``
(marl_render/populations/policies.py).

``evaluate`` calls ``policy(env, obs, generator)`` once per step from a fresh reset; the policy
decides every ``action_repeat`` steps on its stack of decision frames, as in training, and
holds its actions in between. One GreedyPolicy plays one evaluation (it keeps the frame stack).
"""
from __future__ import annotations

import torch

from marl_render.populations.networks import Actor

from .ppo import FrameStack


class GreedyPolicy:
    """`vector_keys`: the task's vector observations (Scenario.vector_obs) the actor reads beside
    `obs_key`, in the trainer's order; none for a task without any."""

    def __init__(self, actor: Actor, trained: torch.Tensor, obs_key: str, frames: int, action_repeat: int,
                 vector_keys: tuple = ()):
        self.actor, self.trained, self.obs_key, self.vector_keys = actor, trained, obs_key, tuple(vector_keys)
        self.needs = frozenset({obs_key, "action_mask", *self.vector_keys})  # the keys as_policy hands it
        self.action_repeat = action_repeat
        self.onehot = torch.eye(len(trained))[trained]
        self.stack = FrameStack(frames)
        self.calls = 0
        self.actions = None

    @torch.inference_mode()
    def __call__(self, env, obs: dict, generator: torch.Generator) -> torch.Tensor:
        decide = self.calls % self.action_repeat == 0
        self.calls += 1
        if not decide:
            return self.actions
        observation = obs[self.obs_key][:, self.trained]
        stack = self.stack.reset(observation) if self.stack.stack is None else self.stack.push(observation)
        W, At = stack.shape[:2]
        vector = None
        if self.vector_keys:
            vector = torch.cat([obs[key][:, self.trained] for key in self.vector_keys], -1).flatten(0, 1)
        logits = self.actor(self.actor.prepare(stack.flatten(0, 1)), self.onehot.repeat(W, 1),
                            obs["action_mask"][:, self.trained].flatten(0, 1), vector)
        # The opponents' actions are replaced by random ones in evaluate; 0 is only a placeholder.
        actions = torch.zeros(W, len(self.trained), dtype=torch.int64)
        actions[:, self.trained] = self.choose(logits, generator).reshape(W, At)
        self.actions = actions
        return actions

    def choose(self, logits: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """The action of each row of `logits` [N, actions]: the most likely one."""
        return logits.argmax(-1)
