"""Trained policies as objects: a run folder loaded as a policy that plays any slots of an env.

    policy = load_policy("docs/baselines/tag/seed0")      # a run folder of python -m marl_render.baselines
    actions = policy.act(env, obs, worlds, slots)         # [P] (or [P, action_dim]) for P pairs

What a policy is (``act``, ``needs``, ``reset``, batched over every pair it plays) is the one
protocol of envs/policy.py. The protocol and its adapters (``Policy``,
``as_policy``, ``RandomPolicy``, ``heuristic_policy``, ...) are the envs layer's (envs/policy.py),
importable from here as before; this module loads trained runs (``load_policy``, ``ActorPolicy``:
a self-play snapshot is one too). Task-specific bots are declared by the tasks (envs/roster.py).
"""
from __future__ import annotations

import json
import os
import pickle

import torch

from marl_render.envs import env_class, list_envs
from marl_render.envs.policy import (
    CallablePolicy,
    Policy,
    RandomPolicy,
    ScriptedPolicy,
    as_policy,
    heuristic_policy,
    joint_actions,
)
from marl_render.util.validation import describe

from .networks import Actor

# The protocol and its adapters are the envs layer's (envs/policy.py): this module's names too, as they were.
__all__ = ["ActorPolicy", "CallablePolicy", "Policy", "RandomPolicy", "ScriptedPolicy", "TRAINING_CONDITION",
           "as_policy", "heuristic_policy", "joint_actions", "load_policy", "required_env_kwargs"]

# Keys of a loaded run's env_kwargs that say where it trained, not what its actor needs: an
# evaluation chooses its own levels and looks (cross-play and held-out scenarios play the defaults).
TRAINING_CONDITION = ("levels", "appearance")


def required_env_kwargs(policy) -> dict:
    """The make_env keywords `policy`'s actor needs (resolution, grayscale, state_obs), without the
    levels and looks it trained on."""
    return {k: v for k, v in getattr(policy, "env_kwargs", {}).items() if k not in TRAINING_CONDITION}


class ActorPolicy(Policy):
    """A trained actor (marl_render/populations/networks.py) playing greedily, with the trainer's frame
    stack and action repeat kept per (world, slot). One network plays every slot it is given: its
    agent input is the slot's one-hot among the task's agents, as in training. `vector_keys`: the
    task's vector observations (Scenario.vector_obs) it reads beside `obs_key`, in the trainer's order."""

    def __init__(self, actor: Actor, *, name: str, obs_key: str, frames: int, action_repeat: int,
                 num_agents: int, env_kwargs: dict, task: str | None = None, num_actions: int | None = None,
                 vector_keys: tuple = ()):
        self.actor, self.name, self.obs_key = actor.eval(), name, obs_key
        self.frames, self.action_repeat, self.num_agents = frames, action_repeat, num_agents
        self.task, self.num_actions = task, num_actions  # what it was trained on (None: not recorded)
        self.vector_keys = tuple(vector_keys)
        self.needs = frozenset({obs_key, "action_mask", *self.vector_keys})
        self.env_kwargs = env_kwargs
        self.stack = self.held = self.fresh = None  # [W, A, ...] once the first call shows W and A

    def check_task(self, task: str) -> None:
        """ValueError naming both tasks unless this actor was trained on `task` (a registered name; a
        run that did not record its task passes): an actor plays the task it learnt, no other."""
        if self.task is None or task == self.task or _same_task(self.task, task):
            return
        raise ValueError(f"policy {self.name!r} was trained on {self.task!r} ({self.num_actions} actions); it cannot "
                         f"play {task!r}: use a run of {task!r}")

    def check_env(self, env) -> None:
        """ValueError naming both tasks unless `env` (a driver) is the task, agents and actions this
        actor was trained for."""
        trained = f"{self.task!r}" if self.task is not None else "its run's task"
        if env.continuous or (self.num_actions is not None and env.num_actions != self.num_actions):
            raise ValueError(f"policy {self.name!r} was trained on {trained} with {self.num_actions} discrete "
                             f"actions; env {env.name!r} has "
                             + ("continuous actions" if env.continuous else f"{env.num_actions} actions"))
        if self.task is not None and env.name != self.task and not _same_task(self.task, type(env.scenario)):
            raise ValueError(f"policy {self.name!r} was trained on {trained}; it cannot play env {env.name!r}")
        if env.num_agents != self.num_agents:
            raise ValueError(f"policy {self.name!r} was trained with {self.num_agents} agents; env {env.name!r} has "
                             f"{env.num_agents}")

    def reset(self, env, worlds):
        """Worlds (bool [W]) that start a new episode: their frame stacks and held actions start afresh."""
        if self.fresh is not None:
            self.fresh |= worlds.cpu()[:, None]

    @torch.inference_mode(False)
    @torch.no_grad()
    def act(self, env, obs, worlds, slots):
        """The actor's greedy actions of the pairs, deciding every action_repeat steps on its frame stack."""
        self.check_env(env)
        observation = obs[self.obs_key]
        if self.stack is None or self.stack.shape[0] != env.num_worlds:
            W, A = env.num_worlds, env.num_agents
            self.stack = observation.new_zeros((W, A, *observation.shape[1:-1], observation.shape[-1] * self.frames))
            self.held = torch.zeros(W, A, dtype=torch.int64)
            self.fresh = torch.ones(W, A, dtype=torch.bool)
        decide = env.step_count[worlds].cpu() % self.action_repeat == 0
        fresh = self.fresh[worlds, slots]
        pushed = torch.cat((self.stack[worlds, slots][..., observation.shape[-1]:], observation), -1)
        stack = torch.where(fresh.view(-1, *[1] * (observation.ndim - 1)),
                            torch.cat([observation] * self.frames, -1), pushed)
        self.stack[worlds, slots] = stack
        self.fresh[worlds, slots] = False
        agent = torch.eye(self.num_agents)[slots]
        # The trainer's Actor since issue 25 converts observations with prepare(); the earlier one took them as given.
        prepared = self.actor.prepare(stack) if hasattr(self.actor, "prepare") else stack
        vector = torch.cat([obs[key] for key in self.vector_keys], -1) if self.vector_keys else None
        logits = self.actor(prepared, agent, obs["action_mask"], *(() if vector is None else (vector,)))
        chosen = torch.where(decide | fresh, logits.argmax(-1), self.held[worlds, slots])
        self.held[worlds, slots] = chosen
        return chosen


def load_policy(run_folder: str, name: str | None = None) -> ActorPolicy:
    """The greedy policy of a run folder that ``python -m marl_render.baselines`` wrote (its
    result.json and actor.pt); `name` defaults to the folder's path. ``policy.env_kwargs`` holds the
    resolution, grayscale and state_obs the actor needs, and the ``levels`` and ``appearance`` it
    trained with (where it did): build the env with them to play its training condition."""
    if not isinstance(run_folder, (str, os.PathLike)):
        raise TypeError(f"run_folder must be a path (str), got {describe(run_folder)}")
    paths = {f: os.path.join(run_folder, f) for f in ("result.json", "actor.pt")}
    missing = [f for f, path in paths.items() if not os.path.isfile(path)]
    if missing:
        raise FileNotFoundError(f"run_folder {str(run_folder)!r} must hold result.json and actor.pt (written by "
                                f"python -m marl_render.baselines); missing: {missing}")
    with open(paths["result.json"]) as f:
        try:
            result = json.load(f)
        except json.JSONDecodeError as error:
            raise ValueError(f"{paths['result.json']} is not valid JSON: {error}") from error
    hp, obs_key, resolution, grayscale, frames, action_repeat = _run_settings(result, paths["result.json"])
    weights = _actor_weights(paths["actor.pt"])
    vector_keys = _vector_keys(result, weights, paths["result.json"])
    try:
        actor, agents = _actor(weights, hp, obs_key, resolution, (1 if grayscale else 3) * frames)
    except (KeyError, ValueError, RuntimeError) as error:
        raise ValueError(f"{paths['actor.pt']} does not fit the actor that {paths['result.json']} describes: "
                         f"{type(error).__name__}: {str(error)[:300]}") from error
    env_kwargs = {"resolution": resolution, "grayscale": grayscale} if obs_key == "pixels" else {"state_obs": True}
    task = result.get("env")
    if task is not None and not isinstance(task, str):
        raise ValueError(f"{paths['result.json']}: env must be the name of the task the run trained on, got {task!r}")
    env_kwargs.update(_levels_and_looks(result, paths["result.json"]))
    return ActorPolicy(actor, name=name or str(run_folder), obs_key=obs_key, frames=frames,
                       action_repeat=action_repeat, num_agents=agents, env_kwargs=env_kwargs, task=task,
                       num_actions=int(weights["head.4.weight"].shape[0]), vector_keys=vector_keys)


def _vector_keys(result: dict, weights: dict, path: str) -> tuple:
    """The vector observations (obs keys) the run's actor reads: result.json's "vector_obs", which an
    actor with a ``vector_norm`` needs and one without must not have."""
    keys = result.get("vector_obs", [])
    if not isinstance(keys, list) or not all(isinstance(key, str) for key in keys):
        raise ValueError(f"{path}: vector_obs must be a list of obs keys, got {keys!r}")
    if bool(keys) != ("vector_norm.mean" in weights):
        raise ValueError(f"{path}: vector_obs {keys} does not fit the actor, which "
                         + ("reads vector observations" if keys == [] else "reads none"))
    return tuple(keys)


def _same_task(name: str, other) -> bool:
    """Whether the task `name` (a run's) is `other` (a registered name, or a Scenario class) under
    another name: a task registered twice, or named module:Class (compared by name when this process
    has not registered it: a name read from a result.json is never imported)."""
    try:
        target = env_class(other)
    except (ValueError, TypeError, KeyError, ImportError, AttributeError):
        return False
    if name in list_envs():
        return env_class(name) is target
    return name == f"{target.__module__}:{target.__qualname__}"


def _levels_and_looks(result: dict, path: str) -> dict:
    """The levels (``--levels``: train_options) and looks (``--appearance``: env_options) the run
    trained with, as make_env keywords; none where it trained on the env's default resets."""
    found = {}
    for section, key in (("train_options", "levels"), ("env_options", "appearance")):
        options = result.get(section) or {}
        if not isinstance(options, dict):
            raise ValueError(f"{path}: {section} must be a JSON object, got {options!r}")
        if options.get(key) is not None:
            found[key] = options[key]
    return found


def _actor(weights: dict, hp: dict, obs_key: str, resolution: int, channels: int) -> tuple:
    """(the Actor holding `weights`, the number of agents it was trained for: its one-hot agent ids)."""
    if obs_key == "pixels":
        shape = (resolution, resolution, channels)
    else:
        shape = (int(weights["encoder.mean"].shape[0]),)
    state_dim = int(weights["state_head.weight"].shape[0]) if "state_head.weight" in weights else 0
    num_actions, inputs = int(weights["head.4.weight"].shape[0]), int(weights["head.0.weight"].shape[1])
    # The "conv" encoder and float32 compute were the only ones before the trainer recorded them (and
    # its Actor took no such arguments): only other choices are passed on.
    choices = {key: hp[key] for key, old in (("encoder", "conv"), ("precision", "float32")) if hp.get(key, old) != old}
    vector_dim = int(weights["vector_norm.mean"].shape[0]) if "vector_norm.mean" in weights else 0
    probe = Actor(obs_key, shape, 0, num_actions, hp["hidden"], **choices)
    features = (probe.encoder.features if obs_key == "pixels" else shape[0]) + vector_dim
    if inputs < features:
        raise ValueError(f"head.0.weight takes {inputs} inputs, fewer than the encoder's features and the vectors "
                         f"({features})")
    actor = Actor(obs_key, shape, inputs - features, num_actions, hp["hidden"], state_dim=state_dim,
                  vector_dim=vector_dim, **choices)
    actor.load_state_dict(weights)
    return actor, inputs - features


def _run_settings(result, path: str) -> tuple:
    """(hyperparameters, obs key, resolution, grayscale, frames, action_repeat) of a run's result.json,
    each checked: a hostile or hand-edited file is a ValueError naming the file and the entry."""
    try:
        hp, obs_key = result["hyperparameters"], result["obs"]
        resolution, grayscale = hp["resolution"], hp.get("grayscale", False)
        frames, action_repeat, hidden = hp.get("frames", 1), hp.get("action_repeat", 1), hp["hidden"]
    except (KeyError, TypeError, AttributeError) as error:
        raise ValueError(f"{path} lacks the run's settings (obs, hyperparameters with resolution and hidden): "
                         f"{error!r}") from error
    for key, value, high in (("resolution", resolution, 16384), ("frames", frames, 64),
                             ("action_repeat", action_repeat, 1024), ("hidden", hidden, 65536)):
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= high:
            raise ValueError(f"{path}: hyperparameters[{key!r}] must be an int in [1, {high}], got {value!r}")
    if obs_key not in ("pixels", "state") or not isinstance(grayscale, bool):
        raise ValueError(f"{path}: obs must be 'pixels' or 'state' and grayscale a bool, got {obs_key!r} and "
                         f"{grayscale!r}")
    return hp, obs_key, resolution, grayscale, frames, action_repeat


def _actor_weights(path: str) -> dict:
    """actor.pt's state_dict of finite tensors (torch.load with weights_only: no code runs)."""
    try:
        weights = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, OSError, ValueError, pickle.UnpicklingError) as error:
        raise ValueError(f"{path} is not a state_dict that torch.save wrote (truncated, or another kind of file): "
                         f"{type(error).__name__}: {str(error)[:200]}") from error
    if (not isinstance(weights, dict) or "head.0.weight" not in weights or "head.4.weight" not in weights
            or not all(isinstance(value, torch.Tensor) for value in weights.values())):
        raise ValueError(f"{path} is not an actor's state_dict (marl_render/baselines/networks.py)")
    broken = [key for key, value in weights.items() if value.is_floating_point() and not bool(value.isfinite().all())]
    if broken:
        raise ValueError(f"{path} holds NaN or Inf weights in {broken[:5]}: the actor's actions would be meaningless")
    return weights
