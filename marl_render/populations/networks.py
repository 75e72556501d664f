"""The actor (pixels or state -> action logits) and MAPPO's centralised critic.

Inputs are per agent sample, flattened over worlds, agents and time: the actor sees one
agent's observation (uint8 [N, H, W, channels] pixels, or float [N, state_dim] state), that
agent's one-hot index among the world's agents (one network plays every trained agent) and its
action mask; the critic sees the state observations of all agents of the world, [N, A * state_dim].
A task's own vector observations (Scenario.vector_obs: matrix's inventory) enter both beside them:
the actor's `vector` [N, vector_dim] (that agent's vectors, standardised by ``vector_norm``, joined to
its encoder's features), the critic's input every agent's vectors after the states. A task without
any builds the very networks it built before (no new parameter or buffer, the same random draws).

Pixels are converted once (``Actor.prepare``: uint8 [N, H, W, C] -> [N, H, W, C] in [0, 1] in the
actor's compute dtype; the encoder reads them as [N, C, H, W] channels-last, the layout oneDNN's
convolutions prefer, and minibatches are gathered from whole rows) and the actor may compute in
bfloat16 (``precision``) with float32 weights, as torch's CPU autocast does; its logits are float32.
"""
from __future__ import annotations

import math

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


ENCODERS = {"conv": 8, "patch": 12}  # PixelEncoder's layouts and the fewest pixels per side each takes


class PixelEncoder(nn.Module):
    """Prepared pixels [N, H, W, C] -> float [N, features], two convolutions small enough for two
    CPU cores.

    - ``"conv"``: 4x4 stride 2 (16 channels), 3x3 stride 2 (32): the first reference runs' encoder;
      from 8 pixels per side up.
    - ``"patch"``: each 4x4 patch of the view seen once (16 channels: a 4x4 stride-4 convolution,
      computed as one matrix product over the patches), then 3x3 stride 1 (32); from 12 pixels up.
      Sized for 32-48 px: about the features of "conv" (1152 against 1568 at 32 px) from a quarter
      of the first layer's activations, which dominate the cost of a CPU update. Its ``prepare``
      lays the pixels out as patches once ([N, H/4, W/4, 16 C], values 0-255 in the compute dtype:
      exact in bfloat16), and the first layer's weights carry the 1/255 (the same function as a
      layer on pixels in [0, 1]): no pass over the pixels but the one conversion. On this CPU
      memory traffic, not arithmetic, bounds an update."""

    def __init__(self, channels: int, resolution: int, kind: str = "conv"):
        super().__init__()
        if kind not in ENCODERS:
            raise ValueError(f"encoder must be one of {list(ENCODERS)}, got {kind!r}")
        self.kind = kind
        smallest = ENCODERS[kind]  # the first layer must leave 3x3 for the second
        if resolution < smallest:
            raise ValueError(f"the {kind!r} encoder needs at least {smallest} pixels per side, got {resolution}")
        if kind == "conv":
            self.net = nn.Sequential(nn.Conv2d(channels, 16, 4, stride=2), nn.ReLU(),
                                     nn.Conv2d(16, 32, 3, stride=2), nn.ReLU(), nn.Flatten())
        else:
            self.patch = nn.Linear(16 * channels, 16)  # the same parameters and initial scale as Conv2d(C, 16, 4, 4)
            self.conv = nn.Conv2d(16, 32, 3)
        with torch.no_grad():
            zeros = torch.zeros(1, resolution, resolution, channels, dtype=torch.uint8)
            self.features = self(self.prepare(zeros, torch.float32)).shape[-1]

    def prepare(self, pixels: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """uint8 [N, H, W, C] -> the input of `forward` in `dtype`: "conv" [N, H, W, C] in [0, 1];
        "patch" [N, H/4, W/4, 16 C] in 0-255."""
        if self.kind == "conv":
            return pixels.to(dtype) / 255.0
        n, height, width, channels = pixels.shape
        rows, columns = height // 4, width // 4
        pixels = pixels[:, :4 * rows, :4 * columns].contiguous()
        # A patch row is 4 C bytes: moved as C int32 words, the bytes before they are widened to dtype.
        words = pixels.view(n, 4 * rows, 4 * columns * channels).view(torch.int32)
        patches = words.reshape(n, rows, 4, columns, channels).transpose(2, 3).contiguous().view(torch.uint8)
        return patches.reshape(n, rows, columns, 16 * channels).to(dtype)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        if self.kind == "conv":
            return self.net(pixels.permute(0, 3, 1, 2))  # channels-last [N, C, H, W], no copy
        first = torch.relu(nn.functional.linear(pixels, self.patch.weight / 255.0, self.patch.bias))
        # Channels-last in and out of the convolution; flattened in that order, without a copy.
        return torch.relu(self.conv(first.permute(0, 3, 1, 2))).permute(0, 2, 3, 1).flatten(1)


PRECISIONS = {"float32": torch.float32, "bfloat16": torch.bfloat16}
INITS = ("orthogonal", "torch")  # the actor's initial weights (Actor's docstring says why)


class Actor(nn.Module):
    """(prepared observation, agent one-hot, action mask) -> masked float32 logits [N, actions].

    ``prepare`` turns observations as the env gives them into the network's input (done once per
    rollout step, and once per update for the whole batch). `precision` "bfloat16" runs the actor
    under CPU autocast (float32 weights and gradients, bfloat16 convolutions and matmuls).

    With `state_dim` > 0 it also has ``state_head``, a linear map from the features of its last
    forward (``features``) to the agent's standardised state observation: an auxiliary loss
    for training only (the state is privileged information; acting needs only the pixels).

    `init` "orthogonal" draws the encoder's and the hidden layers' weights orthogonal with ReLU's gain
    sqrt(2) and zero biases, as CleanRL's and Stable-Baselines3's PPO do; "torch" keeps torch's
    default (uniform, +-1/sqrt(fan in)), which shrinks each layer's output: at 32 px the view moved
    the first hidden layer by 0.003 (standard deviation over views) against biases of +-0.03, so
    the policy learnt from its biases first and could settle on a view-blind action mix
    (docs/baselines/notes.md). The output layer starts near uniform either way.

    With `vector_dim` > 0 it also reads ``vector`` [N, vector_dim] (the agent's vector observations of
    this step, not stacked: Scenario.vector_obs), standardised by ``vector_norm`` (a RunningNorm the
    trainer updates as the state encoder's) and joined to the encoder's features before the one-hot."""

    def __init__(self, obs: str, obs_shape: tuple, agents: int, actions: int, hidden: int, state_dim: int = 0,
                 encoder: str = "conv", precision: str = "float32", init: str = "torch", vector_dim: int = 0):
        super().__init__()
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {list(PRECISIONS)}, got {precision!r}")
        if init not in INITS:
            raise ValueError(f"init must be one of {list(INITS)}, got {init!r}")
        if isinstance(vector_dim, bool) or not isinstance(vector_dim, int) or vector_dim < 0:
            raise ValueError(f"vector_dim must be an int >= 0, got {vector_dim!r}")
        self.obs = obs
        self.dtype = PRECISIONS[precision]
        if obs == "pixels":
            height, width, channels = obs_shape
            self.encoder = PixelEncoder(channels, height, encoder)
            features = self.encoder.features
        else:
            self.encoder = RunningNorm(obs_shape[-1])
            features = obs_shape[-1]
        self.head = nn.Sequential(nn.Linear(features + vector_dim + agents, hidden), nn.ReLU(),
                                  nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, actions))
        if init == "orthogonal":
            for layer in (*self.encoder.modules(), *self.head[:-1]):
                if isinstance(layer, (nn.Linear, nn.Conv2d)):
                    nn.init.orthogonal_(layer.weight, math.sqrt(2))
                    nn.init.zeros_(layer.bias)
        nn.init.orthogonal_(self.head[-1].weight, 0.01)  # a near-uniform policy to start from
        nn.init.zeros_(self.head[-1].bias)
        self.state_head = nn.Linear(features, state_dim) if state_dim else None
        self.state_norm = RunningNorm(state_dim) if state_dim else None
        # Built last and drawing no random numbers: a task without vectors gets the weights it got before.
        self.vector_dim = vector_dim
        self.vector_norm = RunningNorm(vector_dim) if vector_dim else None
        self.features = None

    def prepare(self, observation: torch.Tensor) -> torch.Tensor:
        """Observations [N, ...] as the env gives them -> the network's input (pixels: converted once)."""
        if self.obs == "pixels":
            return self.encoder.prepare(observation, self.dtype)
        return observation.to(torch.float32)

    def forward(self, observation, agent, mask, vector=None):
        if (vector is None) != (self.vector_norm is None) or (vector is not None
                                                               and vector.shape[-1] != self.vector_dim):
            given = None if vector is None else f"[..., {vector.shape[-1]}]"
            raise ValueError(f"vector must be the agent's vector observations [N, {self.vector_dim}] (None when the "
                             f"actor has none), got {given}")
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.dtype == torch.bfloat16):
            features = self.encoder(observation)
            if self.state_head is not None:
                self.features = features
            joined = (features,) if vector is None else (features, self.vector_norm(vector.float()).to(features.dtype))
            logits = self.head(torch.cat((*joined, agent.to(features.dtype)), -1))
        return logits.float().masked_fill(~mask, MASKED_LOGIT)


class CentralCritic(nn.Module):
    """(all agents' states [N, A * state_dim], then all agents' vector observations where the task has
    any, agent one-hot [N, A]) -> value [N, 1]."""

    def __init__(self, global_dim: int, agents: int, hidden: int):
        super().__init__()
        self.norm = RunningNorm(global_dim)
        self.net = nn.Sequential(nn.Linear(global_dim + agents, 2 * hidden), nn.Tanh(),
                                 nn.Linear(2 * hidden, 2 * hidden), nn.Tanh(), nn.Linear(2 * hidden, 1))

    def forward(self, global_state, agent):
        return self.net(torch.cat((self.norm(global_state), agent), -1))
