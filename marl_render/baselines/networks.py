"""The actor (pixels or state -> action logits) and MAPPO's centralised critic.

Inputs are per agent sample, flattened over worlds, agents and time: the actor sees one
agent's observation (uint8 [N, H, W, channels] pixels, or float [N, state_dim] state), that
agent's one-hot index among the world's agents (one network plays every trained agent) and its
action mask; the critic sees the state observations of all agents of the world, [N, A * state_dim].
"""
from __future__ import annotations

import torch
from torch import nn

MASKED_LOGIT = -1e9  # logit of an action the mask forbids: probability 0, finite entropy terms


def merge_moments(count, mean, var, batch_count, batch_mean, batch_var):
    """Chan et al.'s merge of running moments with a batch's: (total count, the increment of the
    mean, the merged variance). Tensors or floats."""
    total = count + batch_count
    delta = batch_mean - mean
    return total, delta * batch_count / total, (var * count + batch_var * batch_count
                                               + delta ** 2 * count * batch_count / total) / total


class RunningNorm(nn.Module):
    """Standardises features with running mean and variance (updated by `update`, during
    collection only), clipped to +-5: state observations of very different scales (positions,
    counters) enter the networks on one scale."""

    def __init__(self, size: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(size))
        self.register_buffer("var", torch.ones(size))
        self.register_buffer("count", torch.tensor(1e-4))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.reshape(-1, x.shape[-1]).to(torch.float64)
        total, step, var = merge_moments(self.count, self.mean, self.var, x.shape[0], x.mean(0),
                                         x.var(0, unbiased=False))
        self.mean += step.to(self.mean.dtype)
        self.var.copy_(var)
        self.count.copy_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.mean) / torch.sqrt(self.var + 1e-8)).clamp(-5.0, 5.0)


class PixelEncoder(nn.Module):
    """uint8 [N, H, W, C] -> float [N, features]: two strided convolutions, small enough for
    two CPU cores; works from 8 pixels per side up."""

    def __init__(self, channels: int, resolution: int):
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(channels, 16, 4, stride=2), nn.ReLU(),
                                 nn.Conv2d(16, 32, 3, stride=2), nn.ReLU(), nn.Flatten())
        with torch.no_grad():
            self.features = self.net(torch.zeros(1, channels, resolution, resolution)).shape[-1]

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.net(pixels.permute(0, 3, 1, 2).to(torch.float32) / 255.0)


class Actor(nn.Module):
    """(observation, agent one-hot, action mask) -> masked logits [N, actions].

    With `state_dim` > 0 it also has ``state_head``, a linear map from the features of its last
    forward (``features``) to the agent's standardised state observation: an auxiliary loss
    for training only (the state is privileged information; acting needs only the pixels)."""

    def __init__(self, obs: str, obs_shape: tuple, agents: int, actions: int, hidden: int, state_dim: int = 0):
        super().__init__()
        self.obs = obs
        if obs == "pixels":
            height, width, channels = obs_shape
            self.encoder = PixelEncoder(channels, height)
            features = self.encoder.features
        else:
            self.encoder = RunningNorm(obs_shape[-1])
            features = obs_shape[-1]
        self.head = nn.Sequential(nn.Linear(features + agents, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                  nn.Linear(hidden, actions))
        nn.init.orthogonal_(self.head[-1].weight, 0.01)  # a near-uniform policy to start from
        nn.init.zeros_(self.head[-1].bias)
        self.state_head = nn.Linear(features, state_dim) if state_dim else None
        self.state_norm = RunningNorm(state_dim) if state_dim else None
        self.features = None

    def forward(self, observation, agent, mask):
        features = self.encoder(observation)
        if self.state_head is not None:
            self.features = features
        logits = self.head(torch.cat((features, agent), -1))
        return logits.masked_fill(~mask, MASKED_LOGIT)


class CentralCritic(nn.Module):
    """(all agents' states [N, A * state_dim], agent one-hot [N, A]) -> value [N, 1]."""

    def __init__(self, global_dim: int, agents: int, hidden: int):
        super().__init__()
        self.norm = RunningNorm(global_dim)
        self.net = nn.Sequential(nn.Linear(global_dim + agents, 2 * hidden), nn.Tanh(),
                                 nn.Linear(2 * hidden, 2 * hidden), nn.Tanh(), nn.Linear(2 * hidden, 1))

    def forward(self, global_state, agent):
        return self.net(torch.cat((self.norm(global_state), agent), -1))
