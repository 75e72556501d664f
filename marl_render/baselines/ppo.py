"""MAPPO on a BatchedEnv: rollouts of W worlds at once, plain-torch GAE, the clipped PPO loss in plain torch.

One actor plays every trained agent (the others, a task's ``opponents``, play uniformly random
valid actions, as in the reference evaluation); the critic is centralised (all agents' states).

Rollouts run the env without auto-reset: a decision holds its actions for ``action_repeat``
steps (rewards summed, a world that ends inside the block stops counting), then the worlds
whose episode ended are reset together (``reset_worlds``). A time-limit truncation is
bootstrapped from the value of the state the episode ended in; a terminated agent is not, and
its samples after termination (actions ignored, reward 0) are left out of the loss.

The loss is TorchRL's ClipPPOLoss written out on plain tensors (``ppo_loss``; a test holds the two
equal): per-minibatch normalised advantages, the clipped probability-ratio objective, an entropy
bonus and a squared-error value loss. Without TensorDicts the small per-call costs are gone, and the
rollout's forward passes run under ``torch.inference_mode``. Random numbers (actions, opponents,
minibatches) come from the trainer's own generators, so a run depends on its seed alone.

Acting and learning use separate copies of the networks: rollouts run the acting copy (whose
running observation norms they update), an update loads those norms with its batch and trains the
learning copy, and ``publish()`` copies the learnt weights into the acting copy. Run one after the
other (collect, update, publish) this is plain PPO. With ``hp.overlap`` the training loop
(training.py) collects the next rollout while the update runs in a second thread, as Sample
Factory's APPO does: that rollout's actions come from the weights before the update, one update
behind, and PPO's ratio is taken against those behaviour log-probabilities (stored with the
samples) and clipped as usual.

A task's own vector observations (Scenario.vector_obs, e.g. matrix's inventory) go to both networks
(networks.py): the actor reads each agent's, the critic every agent's after the states. A task without
any trains exactly as before.

With ``self_play`` (selfplay.py) the actor plays every team: in each world the slots of one team
act with the learner and give the samples, the other teams' slots are played by frozen snapshots
of the actor from a pool. Without it nothing of the above changes (the same numbers for a seed).
"""
from __future__ import annotations

import contextlib
import copy
import math
import time

import torch
from torch import nn

from marl_render.envs import make_env
from marl_render.envs.evaluation import opponent_mask, random_policy
from marl_render.populations.networks import Actor, CentralCritic, merge_moments

from .advantage import generalized_advantage
from .selfplay import SelfPlay, SnapshotPool, team_index
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


def ppo_loss(actor: Actor, critic: CentralCritic, batch: dict, hp: Hyperparameters) -> dict:
    """ClipPPOLoss(clip_epsilon=hp.clip, entropy_coeff=hp.entropy, critic_coeff=hp.critic_coef,
    loss_critic_type="l2", normalize_advantage=True) on a minibatch of samples, in plain torch:
    {"loss_objective", "loss_entropy", "loss_critic", "entropy", "explained_variance"} (scalars).
    `batch` holds observation (prepared), agent, mask, global_state, action, sample_log_prob,
    advantage and value_target, each [N, ...], and vector where the task has vector observations."""
    logits = actor(batch["observation"], batch["agent"], batch["mask"], batch.get("vector"))
    log_probs = logits.log_softmax(-1)
    log_weight = log_probs.gather(-1, batch["action"][:, None]).squeeze(-1) - batch["sample_log_prob"]
    advantage = batch["advantage"]
    advantage = (advantage - advantage.mean()) / advantage.std().clamp_min(torch.finfo(torch.float32).resolution)
    gain = torch.minimum(log_weight.exp() * advantage,
                         log_weight.clamp(math.log1p(-hp.clip), math.log1p(hp.clip)).exp() * advantage)
    entropy = -(log_probs.exp() * log_probs).sum(-1)  # masked actions: probability 0, finite log-probability
    value = critic(batch["global_state"], batch["agent"]).squeeze(-1)
    target = batch["value_target"]
    with torch.no_grad():
        explained = 1.0 - (target - value).var(correction=0) / (target.var(correction=0) +
                                                                 torch.finfo(target.dtype).eps)
    return {"loss_objective": -gain.mean(), "loss_entropy": -hp.entropy * entropy.mean(),
            "loss_critic": hp.critic_coef * (value - target).pow(2).mean(), "entropy": entropy.detach().mean(),
            "explained_variance": explained}


def minibatch_indices(order: torch.Tensor, minibatch: int) -> list:
    """`order` split into minibatches of `minibatch` samples, a last one of a single sample joined to the one
    before: its advantage has no standard deviation (NaN, which then reaches the weights). Samples of
    agents out of play are left out, so a task whose trained agents are removed (territory) makes such
    remainders; one whose samples split evenly gets the plain split."""
    chunks = list(order.split(minibatch))
    if len(chunks) > 1 and len(chunks[-1]) == 1:
        chunks[-2:] = [torch.cat(chunks[-2:])]
    return chunks


class MAPPO:
    """Trainer of one task: ``collect()`` a rollout, ``update(batch)``; ``actor_net`` is the policy
    network (masked logits), ``obs_key`` the observation it reads ("pixels" or "state")."""

    def __init__(self, env_name: str, hp: Hyperparameters, obs: str, seed: int, env_kwargs: dict,
                 self_play: SelfPlay | None = None):
        self.hp, self.obs_key = hp, obs
        torch.manual_seed(seed)  # the networks' initial weights
        self.env = make_env(env_name, num_worlds=hp.worlds, resolution=hp.resolution, grayscale=hp.grayscale,
                            state_obs=True, seed=seed, **env_kwargs)
        env = self.env
        if env.continuous:
            raise ValueError(f"the baselines learn discrete actions; {env_name!r} was built continuous")
        self.evaluated = ~opponent_mask(env)  # [A] bool: the agents a reference evaluation scores
        teams = team_index(env.groups) if self_play is not None else None  # ValueError for one team
        # [A] bool: the agents the actor plays (in self-play every one, each world's learning team learning)
        self.trained = self.evaluated if self_play is None else torch.ones(env.num_agents, dtype=torch.bool)
        self.agents = int(self.trained.sum())
        A = env.num_agents
        self.onehot = torch.eye(A)[self.trained]  # [At, A]
        self.vector_keys = tuple(env.vector_obs)  # the task's own vector observations, in declaration order
        vector_dim = sum(entry.width for entry in env.vector_obs.values())
        self.trained_index = self.trained.nonzero().squeeze(1)  # index_select: a fast copy of big observations
        self.generator = torch.Generator().manual_seed(seed + 1)  # the opponents' random actions
        self.sampler = torch.Generator().manual_seed(seed + 2)  # the actor's actions
        self.shuffler = torch.Generator().manual_seed(seed + 3)  # the minibatches (drawn in the update's thread)
        self.last_obs = env.reset(seed=seed)
        self.stack = FrameStack(hp.frames)
        self.stack.reset(self._observation(self.last_obs))
        self.alive = torch.ones(env.num_worlds, A, dtype=torch.bool)
        obs_shape = tuple(self.stack.stack.shape[2:])
        self.aux_state = hp.aux_state if obs == "pixels" else 0.0
        self.actor_net = Actor(obs, obs_shape, A, env.num_actions, hp.hidden,
                               state_dim=env.state_dim if self.aux_state else 0, encoder=hp.encoder,
                               precision=hp.precision, init=hp.init, vector_dim=vector_dim)
        self.critic_net = CentralCritic(A * (env.state_dim + vector_dim), A, hp.hidden)
        self.acting_actor, self.acting_critic = copy.deepcopy(self.actor_net), copy.deepcopy(self.critic_net)
        self.parameters = [*self.actor_net.parameters(), *self.critic_net.parameters()]
        self.optimizer = torch.optim.Adam(self.parameters, lr=hp.lr, eps=1e-5, fused=True)  # one kernel for all
        self.reward_scale = RewardScale((env.num_worlds, self.agents), hp.gamma)
        self.running_return = torch.zeros(env.num_worlds, dtype=torch.float64)
        self.env_steps = 0  # env steps summed over worlds
        self.clock = StageClock()
        self.pool = None
        if self_play is not None:  # the untrained actor is snapshot 0, every world's first opponent
            self.pool = SnapshotPool(self_play, teams, env.num_worlds, seed + 4)
            self.pool.add(self.acting_actor, 0, 0)
            self.pool.start()

    @property
    def seconds_stepping(self) -> float:
        """Seconds spent in the env (steps and resets of ended worlds) while training."""
        return self.clock.seconds["env"]

    def _observation(self, obs: dict) -> torch.Tensor:
        """The trained agents' observation [W, At, ...] of an obs dict."""
        return obs[self.obs_key].index_select(1, self.trained_index)

    def _vector(self, obs: dict) -> torch.Tensor | None:
        """The trained agents' vector observations [W, At, vector_dim] of an obs dict (None: the task has none)."""
        if not self.vector_keys:
            return None
        return torch.cat([obs[key] for key in self.vector_keys], -1).index_select(1, self.trained_index)

    def _global_state(self, obs: dict) -> torch.Tensor:
        state = obs["state"].flatten(-2)
        if self.vector_keys:  # every agent's vectors after the states
            state = torch.cat((state, *(obs[key].flatten(-2) for key in self.vector_keys)), -1)
        self.acting_critic.norm.update(state)
        return state

    def _values(self, global_state: torch.Tensor) -> torch.Tensor:
        """The critic's value [W, At] of every trained agent, from the worlds' states [W, A * state_dim]."""
        W, At = global_state.shape[0], self.agents
        with self.clock("policy_forward"), torch.inference_mode():
            agent = self.onehot.expand(W, -1, -1).reshape(W * At, -1)
            return self.acting_critic(global_state.repeat_interleave(At, 0), agent).reshape(W, At)

    def collect(self) -> tuple[dict, list]:
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
    def _collect(self) -> tuple[dict, list]:
        hp, env, clock = self.hp, self.env, self.clock
        T, W, At = hp.rollout, env.num_worlds, self.agents
        agent = self.onehot.expand(W, -1, -1).reshape(W * At, -1)
        steps = []
        ended = []
        for _ in range(T):
            observation = self.stack.stack
            if self.obs_key == "state":
                self.acting_actor.encoder.update(observation)
            global_state = self._global_state(self.last_obs)
            own_state = self.last_obs["state"][:, self.trained]
            if self.aux_state:
                self.acting_actor.state_norm.update(own_state)
            vector = self._vector(self.last_obs)
            if vector is not None:
                self.acting_actor.vector_norm.update(vector)
            mask = self.last_obs["action_mask"][:, self.trained]
            with clock("policy_forward"), torch.inference_mode():
                logits = self.acting_actor(self.acting_actor.prepare(observation.flatten(0, 1)), agent,
                                           mask.flatten(0, 1), None if vector is None else vector.flatten(0, 1))
                log_probs = logits.log_softmax(-1)
                action = torch.multinomial(log_probs.exp(), 1, generator=self.sampler)
                sample_log_prob = log_probs.gather(-1, action).reshape(W, At)
                action = action.reshape(W, At)
            value = self._values(global_state)
            actions = random_policy(env, self.last_obs, self.generator)
            actions[:, self.trained] = action
            alive = self.alive[:, self.trained].clone()
            learner = None
            if self.pool is not None:  # the opponents' slots: snapshots act, and give no samples
                learner = self.pool.learner_slots()
                with clock("policy_forward"), torch.inference_mode():
                    actions = self.pool.act(observation, self.onehot, self.last_obs["action_mask"], actions, vector)
                alive &= learner
            reward, done, terminated = self._act(actions)
            # An episode's return: the per-capita reward of the agents the actor plays (in self-play, of the
            # world's learning team).
            per_capita = reward.mean(-1) if learner is None else (reward * learner).sum(-1) / learner.sum(-1)
            bootstrap = torch.zeros(W, At)
            if bool(done.any()):  # the value of the state each ended episode stopped in
                bootstrap = self._values(self._global_state(self.last_obs))
                ending = reward[done].mean(-1) if learner is None else per_capita[done]
                ended += (self.running_return[done] + ending.double()).tolist()
                self._reset(done)
            self.running_return = torch.where(done, 0.0, self.running_return + per_capita.double())
            steps.append(dict(observation=observation, global_state=global_state, mask=mask, own_state=own_state,
                              action=action, sample_log_prob=sample_log_prob, value=value,
                              reward=self.reward_scale(reward.double(), done[:, None] | terminated).float(),
                              done=done[:, None] | terminated, terminated=terminated, bootstrap=bootstrap,
                              world_done=done[:, None].expand(W, At), valid=alive,
                              **({} if vector is None else {"vector": vector})))
        batch = {key: torch.stack([s[key] for s in steps]) for key in steps[0]}  # [T, W, ...]
        last_value = self._values(self._global_state(self.last_obs))[None]
        next_value = torch.cat((batch["value"][1:], last_value))
        next_value = torch.where(batch["world_done"], batch["bootstrap"], next_value)

        with clock("gae"):  # [T, W, At]
            advantage, value_target = generalized_advantage(
                hp.gamma, hp.gae_lambda, batch["value"], next_value, batch["reward"], batch["done"],
                batch["terminated"])

        valid = batch["valid"].reshape(-1)
        norms = {"actor": {k: v.clone() for k, v in self.acting_actor.named_buffers()},
                 "critic": {k: v.clone() for k, v in self.acting_critic.named_buffers()}}
        samples = {"observation": batch["observation"].flatten(0, 2),
                   "agent": self.onehot.expand(T, W, -1, -1).flatten(0, 2),
                   "mask": batch["mask"].flatten(0, 2),
                   "global_state": batch["global_state"][:, :, None].expand(T, W, At, -1).flatten(0, 2),
                   "own_state": batch["own_state"].flatten(0, 2),
                   "action": batch["action"].reshape(-1), "sample_log_prob": batch["sample_log_prob"].reshape(-1),
                   "advantage": advantage.reshape(-1), "value_target": value_target.reshape(-1)}
        if "vector" in batch:
            samples["vector"] = batch["vector"].flatten(0, 2)
        if not bool(valid.all()):
            index = valid.nonzero().squeeze(1)
            samples = {key: value.index_select(0, index) for key, value in samples.items()}
        return {**samples, "norms": norms}, ended

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
        if self.pool is not None:
            self.pool.count(self.hp.action_repeat, done)
        self.last_obs = obs
        self.stack.push(self._observation(obs))
        return reward, done, terminated

    def _reset(self, worlds: torch.Tensor) -> None:
        with self.clock("env"):
            self.last_obs = self.env.reset_worlds(worlds)
        self.alive |= worlds[:, None]
        self.stack.restart(self._observation(self.last_obs), worlds)
        if self.pool is not None:
            self.pool.redraw(worlds, self.env_steps)

    def update(self, samples: dict) -> dict:
        """hp.epochs passes of the PPO loss over `samples` in hp.minibatches minibatches; the mean
        of the loss terms of the last pass."""
        hp, clock = self.hp, self.clock
        norms = samples["norms"]  # the observation norms the samples were collected with
        for net, name in ((self.actor_net, "actor"), (self.critic_net, "critic")):
            for key, buffer in net.named_buffers():
                buffer.copy_(norms[name][key])
        with clock("minibatch"):  # the pixels converted once for every pass
            samples = {**{k: v for k, v in samples.items() if k != "norms"},
                       "observation": self.actor_net.prepare(samples["observation"])}
        size = len(samples["action"])
        minibatch = max(size // hp.minibatches, 1)
        for _ in range(hp.epochs):
            terms = []
            for index in minibatch_indices(torch.randperm(size, generator=self.shuffler), minibatch):
                with clock("minibatch"):
                    batch = {key: value.index_select(0, index) for key, value in samples.items()}
                with clock("loss_forward_backward"):
                    out = ppo_loss(self.actor_net, self.critic_net, batch, hp)
                    total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                    if self.aux_state:  # on the features of the forward the PPO loss just ran
                        target = self.actor_net.state_norm(batch["own_state"])
                        out["loss_aux_state"] = (self.actor_net.state_head(self.actor_net.features.float())
                                                 - target).pow(2).mean()
                        total = total + self.aux_state * out["loss_aux_state"]
                    total.backward()
                with clock("optimiser"):
                    nn.utils.clip_grad_norm_(self.parameters, hp.max_grad_norm, foreach=True)
                    self.optimizer.step()
                    self.optimizer.zero_grad()
                terms.append({k: float(v.detach()) for k, v in out.items()})
        return {k: sum(t[k] for t in terms) / len(terms) for k in terms[0]}

    @torch.no_grad()
    def publish(self) -> None:
        """The learnt weights into the acting networks (their observation norms stay theirs)."""
        for learnt, acting in ((self.actor_net, self.acting_actor), (self.critic_net, self.acting_critic)):
            for source, target in zip(learnt.parameters(), acting.parameters(), strict=True):
                target.copy_(source)

    def close(self) -> None:
        self.env.close()
