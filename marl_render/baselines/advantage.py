"""Generalised advantage estimation (Schulman et al. 2016) over a time-major rollout, in plain torch.

One reverse scan over time, vectorised over everything else (worlds, agents). A step's `done` cuts the
advantage's recursion (the next step belongs to another episode, or the rollout was truncated); its
`terminated` also drops the bootstrap from `next_value` (the episode really ended, so nothing follows).
The arithmetic is TorchRL's `generalized_advantage_estimate`, in its order, so the two agree bit for bit
(tests/test_baselines.py compares them); it lives here so that the trainer does not import TorchRL.
"""
from __future__ import annotations

import torch


def generalized_advantage(gamma: float, lam: float, value: torch.Tensor, next_value: torch.Tensor,
                          reward: torch.Tensor, done: torch.Tensor, terminated: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """(advantage, value target = advantage + value), each shaped like `value`.

    All five tensors are [T, ...]: time first, any batch shape after. `value` is V(s_t), `next_value`
    V(s_{t+1}) (already the bootstrap value where a world was reset), `reward` r_t; `done` and
    `terminated` are bool.
    """
    shapes = {name: tuple(t.shape) for name, t in
              (("value", value), ("next_value", next_value), ("reward", reward), ("done", done),
               ("terminated", terminated))}
    if len(set(shapes.values())) != 1:
        raise ValueError(f"generalized_advantage needs value, next_value, reward, done and terminated of one "
                         f"shape [T, ...], got {shapes}")
    delta = reward + (gamma * (~terminated).int()) * next_value - value
    discount = lam * gamma * (~done).int()
    advantage = torch.empty_like(delta)
    running = torch.zeros_like(delta[0])
    for t in reversed(range(delta.shape[0])):  # a loop over time steps only; each step is one batched op
        running = advantage[t] = delta[t] + running * discount[t]
    return advantage, advantage + value
