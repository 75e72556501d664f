"""MAPPO on a BatchedEnv: rollouts of W worlds at once, TorchRL's GAE and ClipPPOLoss.

One actor plays every trained agent (the others, a task's ``opponents``, play uniformly random
valid actions, as in the reference evaluation); the critic is centralised (all agents' states).

Rollouts run the env without auto-reset: a decision holds its actions for ``action_repeat``
steps (rewards summed, a world that ends inside the block stops counting), then the worlds
whose episode ended are reset together (``reset_worlds``). A time-limit truncation is
bootstrapped from the value of the state the episode ended in; a terminated agent is not, and
its samples after termination (actions ignored, reward 0) are left out of the loss.
"""
from __future__ import annotations

import contextlib
import time

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value.functional import generalized_advantage_estimate

from marl_render.envs import make_env
from marl_render.envs.evaluation import opponent_mask, random_policy

from .networks import Actor, CentralCritic, merge_moments
from .settings import Hyperparameters


class StageClock:
    """Wall-clock seconds per stage of training, summed over the run: ``with clock("env"): ...``.
    Always on (two perf_counter calls per stage entry), so that result.json says where the time went."""

    STAGES = ("env", "observation", "policy_forward", "gae", "minibatch", "loss_forward_backward", "optimiser")

    def __init__(self):
        self.seconds = dict.fromkeys(self.STAGES, 0.0)

    @contextlib.contextmanager
    def __call__(self, stage: str):
        started = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - started


class FrameStack:
    """The last `frames` decision observations of every agent, stacked along the last axis."""

    def __init__(self, frames: int):
        self.frames = frames
        self.stack = None

    def reset(self, obs: torch.Tensor) -> torch.Tensor:
        self.stack = torch.cat([obs] * self.frames, -1)
        return self.stack

    def push(self, obs: torch.Tensor) -> torch.Tensor:
        """Add the frame [W, A, ...] of every world."""
        self.stack = torch.cat((self.stack[..., obs.shape[-1]:], obs), -1)
        return self.stack

    def restart(self, obs: torch.Tensor, worlds: torch.Tensor) -> torch.Tensor:
        """Worlds in `worlds` [W] (a new episode) start a new stack from their frame in `obs` alone."""
        self.stack[worlds] = torch.cat([obs[worlds]] * self.frames, -1)
        return self.stack


class RewardScale:
    """Divides rewards by a running standard deviation of the discounted return, so that the
    critic learns on a similar scale whatever the task's reward (cartpole's 1 per step, spread's
    distances, sparse goals)."""

    def __init__(self, shape: tuple, gamma: float):
        self.gamma = gamma
        self.ret = torch.zeros(shape, dtype=torch.float64)
        self.count, self.mean, self.var = 1e-4, 0.0, 1.0

    def __call__(self, reward: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        self.ret = self.ret * self.gamma + reward
        x = self.ret.flatten()
        self.count, step, self.var = merge_moments(self.count, self.mean, self.var, x.numel(), float(x.mean()),
                                                   float(x.var(unbiased=False)))
        self.mean += step
        self.ret = torch.where(done, 0.0, self.ret)
        return reward / (self.var ** 0.5 + 1e-8)


class MAPPO:
    """Trainer of one task: ``collect()`` a rollout, ``update(batch)``; ``actor`` is the policy
    network (masked logits), ``obs_key`` the observation it reads ("pixels" or "state")."""

    def __init__(self, env_name: str, hp: Hyperparameters, obs: str, seed: int, env_kwargs: dict):
        self.hp, self.obs_key = hp, obs
        torch.manual_seed(seed)
        self.env = make_env(env_name, num_worlds=hp.worlds, resolution=hp.resolution, grayscale=hp.grayscale,
                            state_obs=True, seed=seed, **env_kwargs)
        env = self.env
        if env.continuous:
            raise ValueError(f"the baselines learn discrete actions; {env_name!r} was built continuous")
        self.trained = ~opponent_mask(env)  # [A] bool: the agents the actor plays
        self.agents = int(self.trained.sum())
        A = env.num_agents
        self.onehot = torch.eye(A)[self.trained]  # [At, A]
        self.generator = torch.Generator().manual_seed(seed + 1)  # the opponents' random actions
        self.last_obs = env.reset(seed=seed)
        self.stack = FrameStack(hp.frames)
        self.stack.reset(self._observation(self.last_obs))
        self.alive = torch.ones(env.num_worlds, A, dtype=torch.bool)
        obs_shape = tuple(self.stack.stack.shape[2:])
        self.aux_state = hp.aux_state if obs == "pixels" else 0.0
        self.actor_net = Actor(obs, obs_shape, A, env.num_actions, hp.hidden,
                               state_dim=env.state_dim if self.aux_state else 0)
        self.critic_net = CentralCritic(A * env.state_dim, A, hp.hidden)
        self.actor = ProbabilisticActor(
            TensorDictModule(self.actor_net, in_keys=["observation", "agent", "mask"], out_keys=["logits"]),
            in_keys=["logits"], out_keys=["action"], distribution_class=torch.distributions.Categorical,
            return_log_prob=True, log_prob_key="sample_log_prob")
        self.critic = TensorDictModule(self.critic_net, in_keys=["global_state", "agent"], out_keys=["state_value"])
        self.loss = ClipPPOLoss(self.actor, self.critic, clip_epsilon=hp.clip, entropy_coeff=hp.entropy,
                                critic_coeff=hp.critic_coef, loss_critic_type="l2", normalize_advantage=True)
        self.loss.set_keys(sample_log_prob="sample_log_prob")
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=hp.lr, eps=1e-5)
        self.reward_scale = RewardScale((env.num_worlds, self.agents), hp.gamma)
        self.running_return = torch.zeros(env.num_worlds, dtype=torch.float64)
        self.env_steps = 0  # env steps summed over worlds
        self.clock = StageClock()

    @property
    def seconds_stepping(self) -> float:
        """Seconds spent in the env (steps and resets of ended worlds) while training."""
        return self.clock.seconds["env"]

    def _observation(self, obs: dict) -> torch.Tensor:
        """The trained agents' observation [W, At, ...] of an obs dict."""
        return obs[self.obs_key][:, self.trained]

    def _inputs(self, observation, global_state, mask) -> TensorDict:
        """Network inputs of [..., At] samples, flattened."""
        lead = observation.shape[:-len(self.stack.stack.shape[2:])]
        n = lead.numel()
        return TensorDict(observation=observation.reshape(n, *observation.shape[len(lead):]),
                          agent=self.onehot.expand(*lead[:-1], -1, -1).reshape(n, -1),
                          mask=mask.reshape(n, -1),
                          global_state=global_state.reshape(n, -1),
                          batch_size=[n])

    def _global_state(self, obs: dict) -> torch.Tensor:
        state = obs["state"].flatten(-2)
        self.critic_net.norm.update(state)
        return state

    def collect(self) -> tuple[TensorDict, list]:
        """One rollout of hp.rollout decisions in every world: (the samples of the trained agents
        that were alive, flattened, with advantage and value_target; the returns of the episodes
        that ended, each the sum of the trained agents' rewards averaged over them)."""
        started = time.perf_counter()
        inner = sum(self.clock.seconds[k] for k in ("env", "policy_forward", "gae"))
        out = self._collect()
        # Observation handling is what the rollout spent outside the env, the networks and GAE.
        self.clock.seconds["observation"] += (time.perf_counter() - started
                                              - (sum(self.clock.seconds[k] for k in ("env", "policy_forward", "gae"))
                                                 - inner))
        return out

    @torch.no_grad()
    def _collect(self) -> tuple[TensorDict, list]:
        hp, env, clock = self.hp, self.env, self.clock
        T, W, At = hp.rollout, env.num_worlds, self.agents
        steps = []
        ended = []
        for _ in range(T):
            observation = self.stack.stack
            if self.obs_key == "state":
                self.actor_net.encoder.update(observation)
            global_state = self._global_state(self.last_obs)
            self.last_obs_state = self.last_obs["state"][:, self.trained]
            if self.aux_state:
                self.actor_net.state_norm.update(self.last_obs_state)
            mask = self.last_obs["action_mask"][:, self.trained]
            td = self._inputs(observation, global_state[:, None].expand(W, At, -1), mask)
            with clock("policy_forward"), set_exploration_type(ExplorationType.RANDOM):
                self.actor(td)
                self.critic(td)
            actions = random_policy(env, self.last_obs, self.generator)
            actions[:, self.trained] = td["action"].reshape(W, At)
            alive = self.alive[:, self.trained].clone()
            reward, done, terminated = self._act(actions)
            bootstrap = torch.zeros(W, At)
            if bool(done.any()):  # the value of the state each ended episode stopped in
                final = self._inputs(self.stack.stack, self._global_state(self.last_obs)[:, None].expand(W, At, -1),
                                     mask)
                with clock("policy_forward"):
                    bootstrap = self.critic(final)["state_value"].reshape(W, At)
                ended += (self.running_return[done] + reward[done].mean(-1).double()).tolist()
                self._reset(done)
            self.running_return = torch.where(done, 0.0, self.running_return + reward.mean(-1).double())
            own_state = self.last_obs_state
            steps.append(dict(observation=observation, global_state=global_state, mask=mask, own_state=own_state,
                              action=td["action"].reshape(W, At), sample_log_prob=td["sample_log_prob"].reshape(W, At),
                              value=td["state_value"].reshape(W, At),
                              reward=self.reward_scale(reward.double(), done[:, None] | terminated).float(),
                              done=done[:, None] | terminated, terminated=terminated, bootstrap=bootstrap,
                              world_done=done[:, None].expand(W, At), valid=alive))
        batch = {key: torch.stack([s[key] for s in steps]) for key in steps[0]}  # [T, W, ...]
        final = self._inputs(self.stack.stack, self._global_state(self.last_obs)[:, None].expand(W, At, -1),
                             self.last_obs["action_mask"][:, self.trained])
        with clock("policy_forward"):
            last_value = self.critic(final)["state_value"].reshape(1, W, At)
        next_value = torch.cat((batch["value"][1:], last_value))
        next_value = torch.where(batch["world_done"], batch["bootstrap"], next_value)

        def by_time(x):  # [T, W, At] -> [W * At, T, 1]: GAE's layout
            return x.permute(1, 2, 0).reshape(W * At, T, 1)

        with clock("gae"):
            advantage, value_target = generalized_advantage_estimate(
                hp.gamma, hp.gae_lambda, by_time(batch["value"]), by_time(next_value), by_time(batch["reward"]),
                by_time(batch["done"]), by_time(batch["terminated"]))

        def back(x):  # [W * At, T, 1] -> [T, W, At, 1]
            return x.reshape(W, At, T, 1).permute(2, 0, 1, 3)

        samples = self._inputs(batch["observation"], batch["global_state"][:, :, None].expand(T, W, At, -1),
                               batch["mask"])
        samples.update(action=batch["action"].reshape(-1), sample_log_prob=batch["sample_log_prob"].reshape(-1),
                       advantage=back(advantage).reshape(-1, 1), value_target=back(value_target).reshape(-1, 1),
                       own_state=batch["own_state"].flatten(0, 2))
        return samples[batch["valid"].reshape(-1)], ended

    def _act(self, actions: torch.Tensor):
        """Hold `actions` for action_repeat steps: (reward [W, At] summed until each world's episode
        ended, world done [W], newly terminated trained agents [W, At])."""
        W = self.env.num_worlds
        reward = torch.zeros(W, self.agents)
        done = torch.zeros(W, dtype=torch.bool)
        terminated = torch.zeros(W, self.agents, dtype=torch.bool)
        for _ in range(self.hp.action_repeat):
            with self.clock("env"):
                obs, r, term, _, info = self.env.step(actions)
            reward += r[:, self.trained] * ~done[:, None]
            terminated |= term[:, self.trained] & self.alive[:, self.trained] & ~done[:, None]
            self.alive &= ~term
            done |= info["done_worlds"]
            self.env_steps += W
        self.last_obs = obs
        self.stack.push(self._observation(obs))
        return reward, done, terminated

    def _reset(self, worlds: torch.Tensor) -> None:
        with self.clock("env"):
            self.last_obs = self.env.reset_worlds(worlds)
        self.alive |= worlds[:, None]
        self.stack.restart(self._observation(self.last_obs), worlds)

    def update(self, samples: TensorDict) -> dict:
        """hp.epochs passes of ClipPPOLoss over `samples` in hp.minibatches minibatches; the mean
        of the loss terms of the last pass."""
        hp, clock = self.hp, self.clock
        size = len(samples)
        minibatch = max(size // hp.minibatches, 1)
        for _ in range(hp.epochs):
            terms = []
            for index in torch.randperm(size).split(minibatch):
                with clock("minibatch"):
                    minibatch_samples = samples[index]
                with clock("loss_forward_backward"):
                    out = self.loss(minibatch_samples)
                    total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                    if self.aux_state:  # on the features of the forward the PPO loss just ran
                        target = self.actor_net.state_norm(minibatch_samples["own_state"])
                        out["loss_aux_state"] = (self.actor_net.state_head(self.actor_net.features)
                                                 - target).pow(2).mean()
                        total = total + self.aux_state * out["loss_aux_state"]
                    self.optimizer.zero_grad()
                    total.backward()
                with clock("optimiser"):
                    nn.utils.clip_grad_norm_(self.loss.parameters(), hp.max_grad_norm)
                    self.optimizer.step()
                terms.append({k: float(out[k].detach().mean()) for k in ("loss_objective", "loss_critic", "entropy",
                                                                         "explained_variance", "loss_aux_state")
                              if k in out.keys()})
        return {k: sum(t[k] for t in terms) / len(terms) for k in terms[0]}

    def close(self) -> None:
        self.env.close()
