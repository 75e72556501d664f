"""The learner's hyperparameters and their defaults per task.

Every task starts from ``Hyperparameters()``; ``TASK_DEFAULTS`` changes what a task needs
(cartpole's 0.01 s steps call for action repeat and stacked frames: between two single steps
the pole moves by less than a pixel). Command-line options override both.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from marl_render.envs import env_class, list_envs
from marl_render.envs.evaluation import SEALED_SEEDS

SEALED_SEEDS_BY_NAME = {name: seed for seed, name in SEALED_SEEDS.items()}


@dataclasses.dataclass(frozen=True)
class Hyperparameters:
    worlds: int = 32  # worlds stepped together while training
    resolution: int = 32  # pixels per side of each view
    grayscale: bool = False  # one-channel pixels (the renderer's luma)
    frames: int = 1  # decision frames stacked along the channels
    action_repeat: int = 1  # env steps each decision is held for
    rollout: int = 32  # decisions per world between updates
    # Passes over each rollout and minibatches per pass. From pixels the CNN updates take ~95% of a
    # run at 10 x 8 (spread: 18 s of 299 s stepping the env): 4 x 4 steps the env 2.5x as often.
    epochs: int = 4
    minibatches: int = 4
    lr: float = 5e-4  # Adam learning rate
    gamma: float = 0.99  # discount per decision
    gae_lambda: float = 0.95
    clip: float = 0.2  # PPO's clip range of the probability ratio
    entropy: float = 0.01  # entropy bonus weight
    critic_coef: float = 0.5  # value loss weight
    max_grad_norm: float = 0.5
    hidden: int = 128  # width of the actor's and the critic's hidden layers
    encoder: str = "patch"  # the actor's pixel encoder (networks.ENCODERS; "conv" until issue 25)
    init: str = "orthogonal"  # the actor's initial weights (networks.INITS; "torch" before issue 25's fix)
    precision: str = "bfloat16"  # the actor's compute: "bfloat16" autocast (float32 weights), or "float32"
    torch_threads: int = 1  # torch threads of the networks (the renderer has its own); 0: the cores available
    # Collect the next rollout while the update runs (a second thread): its actions come from the
    # weights one update behind, PPO's clipped ratio is taken against them (ppo.py).
    overlap: bool = True
    # Weight of an auxiliary loss (pixels only): the actor's pixel features predict the agent's own
    # state observation. Privileged information used in training only; the policy acts on pixels.
    aux_state: float = 0.0


class _TaskTraining(Mapping):
    """A read-only table over the registered tasks, read from each task's class: ``Scenario.training``
    (envs/roster.py) holds a task's Hyperparameters overrides and its step budget ("budget")."""

    def __init__(self, part: str):
        self.part = part  # "defaults": the overrides; "budget": {"pixels": N, "state": M}

    def __getitem__(self, task):
        if not isinstance(task, str) or task not in list_envs():
            raise KeyError(task)
        found = self._read(env_class(task).training)
        if not found:
            raise KeyError(task)
        return found

    def _read(self, training: dict) -> dict:
        if self.part == "budget":
            return dict(training.get("budget", {}))
        return {key: value for key, value in training.items() if key != "budget"}

    def __iter__(self):
        return iter([task for task in list_envs() if self._read(env_class(task).training)])

    def __len__(self):
        return len(list(iter(self)))


TASK_DEFAULTS = _TaskTraining("defaults")  # task -> what it changes of Hyperparameters() (its class's training)

FIELDS = tuple(field.name for field in dataclasses.fields(Hyperparameters))

# The step budget of a run when --env-steps and --updates are left out (env steps summed over worlds), per
# task and observation (its class's training["budget"]): what each reference run of docs/baselines.md trains
# for. Each is the env steps of the task's published run (the last ones budgeted on the wall-clock), so that
# a rerun on any machine trains as far. Half of them was tried with the faster learner
# (docs/baselines/notes.md, "Learning at half the budget"): too little for every task rerun so far.
STEP_BUDGETS = _TaskTraining("budget")
DEFAULT_STEP_BUDGET = 500_000  # a task without an entry above (e.g. one a user registered)

# Named sets of evaluation episodes: env seed (one episode per world of that env) and episode count.
# "development" scored every choice made so far (shaping, hyperparameters, tries); "publication" scored the
# published rows, and three choices followed its scores (docs/baselines/notes.md): a second development set;
# "final" is sealed: committed (issue 38) before anything was scored on it, refused by evaluate()
# without final=True (--final), for one scoring of the final runs. Its episodes: final_set.py.
EVALUATION_SETS: dict = {
    "development": {"seed": 1000, "episodes": 32},
    "publication": {"seed": 7_000_000, "episodes": 64},
    "final": {"seed": SEALED_SEEDS_BY_NAME["final"], "episodes": 256},
}


def step_budget(env: str, obs: str) -> int:
    """The default step budget of a run of `env` from `obs` ("pixels" or "state")."""
    return STEP_BUDGETS.get(env, {}).get(obs, DEFAULT_STEP_BUDGET)


def task_hyperparameters(env: str, **overrides) -> Hyperparameters:
    """Hyperparameters() with the task's defaults, then `overrides` (None values are ignored)."""
    unknown = sorted(set(overrides) - set(FIELDS))
    if unknown:
        raise TypeError(f"unknown hyperparameter(s) {unknown}; known: {list(FIELDS)}")
    values = {**TASK_DEFAULTS.get(env, {}), **{k: v for k, v in overrides.items() if v is not None}}
    return Hyperparameters(**values)
