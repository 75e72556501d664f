"""Train MAPPO on a registered task for a step budget: the library entry point of the baselines.

    from marl_render.baselines import train
    from marl_render.envs.evaluation import evaluate

    run = train("spread", env_steps=200_000, seed=0)            # pixels, the task's hyperparameters
    print(run.env_steps, run.training_seconds, run.curve[-1]["episode_return"])
    print(evaluate("spread", run.policy(), episodes=32, seed=1000, resolution=run.hyperparameters.resolution))

Training stops on its budget in env steps (summed over worlds) or updates, never on the clock, so
the same call gives the same numbers on machines with the same software and the same CPU model (the
learner's float arithmetic follows the CPU's instruction set; ``max_seconds`` is an
opt-in safety cap; a run it stops is marked ``truncated``). Greedy evaluations at fixed env-step
checkpoints (``checkpoint_every``) record how stable the policy is over training; they never
choose which policy is returned: that is always the final one.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import math
import os
import time

import torch

from marl_render.envs.evaluation import evaluate

from .policy import GreedyPolicy
from .ppo import MAPPO
from .reproducible import mode as reproducible_mode
from .reproducible import settings_problem
from .selfplay import SelfPlay
from .settings import EVALUATION_SETS, Hyperparameters, step_budget, task_hyperparameters


@dataclasses.dataclass
class TrainingRun:
    """What ``train`` returns: the trainer (its env is closed), the per-update curve, the checkpoint
    evaluations, and the budget and clock of the run."""

    env: str
    obs: str
    trainer: MAPPO
    hyperparameters: Hyperparameters
    budget_env_steps: int
    budget_updates: int
    curve: list
    checkpoints: list
    updates: int
    training_seconds: float  # collecting and updating, checkpoint evaluations left out
    training_cpu_seconds: float  # CPU time of this process (all its threads, the renderer's too) in training
    checkpoint_seconds: float
    truncated: bool  # stopped by max_seconds before the budget
    # Env steps of the rollouts the updates so far learned from: with hp.overlap, env_steps also counts
    # the next rollout, collected while the last update ran.
    learned_env_steps: int = 0

    @property
    def env_steps(self) -> int:
        """Env steps collected, summed over worlds (with overlap, the last rollout's too; see learned_env_steps)."""
        return self.trainer.env_steps

    def policy(self) -> GreedyPolicy:
        """A fresh greedy policy of the final actor, as ``evaluate`` takes it (one per evaluation)."""
        hp = self.hyperparameters
        return GreedyPolicy(self.trainer.actor_net, self.trainer.evaluated, self.obs, hp.frames, hp.action_repeat,
                            self.trainer.vector_keys)


def updates_for(env_steps: int, hp: Hyperparameters) -> int:
    """Updates that make at least `env_steps` env steps: each steps every world rollout x action_repeat times."""
    return math.ceil(env_steps / (hp.worlds * hp.rollout * hp.action_repeat))


def train(env: str, *, obs: str = "pixels", env_steps: int | None = None, updates: int | None = None, seed: int = 0,
          hyperparameters: Hyperparameters | None = None, env_options: dict | None = None,
          train_options: dict | None = None, checkpoint_every: int = 0, checkpoint_episodes: int = 8,
          max_seconds: float | None = None, progress=None, self_play: SelfPlay | None = None,
          reproducible: bool = False) -> TrainingRun:
    """Train MAPPO on task `env` from `obs` for `env_steps` env steps (rounded up to whole updates) or
    `updates` updates (default: the task's step budget, settings.STEP_BUDGETS).

    `hyperparameters` default to the task's (``task_hyperparameters(env)``); `env_options` go to the
    training env and the checkpoint evaluations, `train_options` to the training env only (a shaped
    training reward). Every `checkpoint_every` env steps (0: never) the greedy policy is evaluated on
    `checkpoint_episodes` episodes of the development evaluation set. `progress(run, point)` is called
    after every update with the curve point just added. Torch runs on ``hp.torch_threads`` threads
    during the call (0: the cores this process may use; the run's hyperparameters say how many).

    With `self_play` (a ``SelfPlay``; the task needs two or more teams) every team is trained against
    a pool of frozen snapshots of the actor (selfplay.py): ``run.trainer.pool`` holds the snapshots and
    what each faced. The policy evaluated (``run.policy()``, the checkpoints) plays the task's usual
    trained team against random opponents, as without self-play.

    `reproducible` trains in the reproducible mode (reproducible.py): the same bits on machines of one
    CPU model (not across models: docs/training.md).
    It needs float32 precision, one torch thread, and a process started with
    ``reproducible.ENVIRONMENT`` (ValueError naming what is missing, before any work)."""
    if env_steps is not None and updates is not None:
        raise ValueError(f"give env_steps or updates, not both (got {env_steps} and {updates})")
    hp = hyperparameters if hyperparameters is not None else task_hyperparameters(env)
    if hp.torch_threads == 0:
        hp = dataclasses.replace(hp, torch_threads=len(os.sched_getaffinity(0)))
    if reproducible:
        problem = settings_problem(hp.precision, hp.torch_threads)
        if problem:
            raise ValueError(f"hyperparameters: {problem}")
    env_options, train_options = dict(env_options or {}), dict(train_options or {})
    if updates is None:
        updates = updates_for(step_budget(env, obs) if env_steps is None else env_steps, hp)
    budget_steps = env_steps if env_steps is not None else updates * hp.worlds * hp.rollout * hp.action_repeat
    threads = torch.get_num_threads()
    with reproducible_mode() if reproducible else contextlib.nullcontext():  # ValueError if not pinned
        torch.set_num_threads(hp.torch_threads)
        try:
            return _train(env, obs, hp, updates, budget_steps, seed, env_options, train_options, checkpoint_every,
                          checkpoint_episodes, max_seconds, progress, self_play)
        finally:
            torch.set_num_threads(threads)


def _train(env, obs, hp, updates, budget_steps, seed, env_options, train_options, checkpoint_every,
           checkpoint_episodes, max_seconds, progress, self_play) -> TrainingRun:
    trainer = MAPPO(env, hp, obs, seed, {**env_options, **train_options}, self_play)
    run = TrainingRun(env, obs, trainer, hp, budget_steps, updates, curve=[], checkpoints=[], updates=0,
                      training_seconds=0.0, training_cpu_seconds=0.0, checkpoint_seconds=0.0, truncated=False)
    development = EVALUATION_SETS["development"]
    next_checkpoint = checkpoint_every
    next_snapshot = self_play.snapshot_every if self_play is not None else None
    started, cpu_started, checkpoint_cpu = time.perf_counter(), time.process_time(), 0.0
    learner = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="mappo-update") if hp.overlap else None
    try:
        collected = None
        while run.updates < updates:
            samples, ended = collected or trainer.collect()
            collected = None
            learned = trainer.env_steps  # every rollout collected so far is in this update or an earlier one
            if learner is None:
                terms = trainer.update(samples)
            else:  # the next rollout (with the weights before this update) while the update runs
                update = learner.submit(trainer.update, samples)
                if run.updates + 1 < updates:
                    collected = trainer.collect()
                terms = update.result()
            trainer.publish()
            run.updates += 1
            run.learned_env_steps = learned
            if next_snapshot is not None and trainer.env_steps >= next_snapshot:
                trainer.pool.add(trainer.acting_actor, trainer.env_steps, run.updates)
                while next_snapshot <= trainer.env_steps:
                    next_snapshot += self_play.snapshot_every
            run.training_seconds = time.perf_counter() - started - run.checkpoint_seconds
            run.training_cpu_seconds = time.process_time() - cpu_started - checkpoint_cpu
            point = {"env_steps": trainer.env_steps, "seconds": run.training_seconds,
                     "episode_return": sum(ended) / len(ended) if ended else None, "episodes_ended": len(ended),
                     **terms}
            run.curve.append(point)
            if checkpoint_every and trainer.env_steps >= next_checkpoint:
                evaluated, evaluated_cpu = time.perf_counter(), time.process_time()
                score = evaluate(env, run.policy(), episodes=checkpoint_episodes, seed=development["seed"],
                                 resolution=hp.resolution, grayscale=hp.grayscale, state_obs=obs == "state",
                                 **env_options)
                run.checkpoint_seconds += time.perf_counter() - evaluated
                checkpoint_cpu += time.process_time() - evaluated_cpu
                run.checkpoints.append({"env_steps": trainer.env_steps, "updates": run.updates,
                                        "seconds": run.training_seconds, "evaluation_set": "development",
                                        **{k: score[k] for k in ("mean", "std", "min", "max", "episodes")},
                                        "per_episode": score["per_episode"]})
                while next_checkpoint <= trainer.env_steps:
                    next_checkpoint += checkpoint_every
            if progress is not None:
                progress(run, point)
            if max_seconds is not None and time.perf_counter() - started > max_seconds and run.updates < updates:
                run.truncated = True
                break
    finally:
        if learner is not None:
            learner.shutdown()
        trainer.close()
    return run
