"""Self-play: the learner against a pool of frozen snapshots of itself, every team of a task trained.

ML-Agents' ghost trainer is the model. One actor (its agent one-hot tells the slots apart) learns
every team's slots; in each world one team is the *learning team* (its slots act with the learner
and give the samples) and every other team is played by a *snapshot*, a frozen copy of the actor
taken every ``snapshot_every`` env steps. Which snapshot a world faces is drawn from the pool:
the latest with probability ``play_latest``, else uniformly among the last ``window`` snapshots
(the latest included). Every ``swap_every`` env steps the assignment is due again: each world
draws a new snapshot, and its learning team moves on to the next team, at its next reset, so that
no episode changes opponent half-way and every advantage is taken within one assignment. Worlds
draw independently, so one batch faces several snapshots; each distinct snapshot acts once per
step over all the slots it plays (a loop over the snapshots in play, none over worlds).

Opponent snapshots sample their actions (as the ghost trainer's opponents do), from the pool's
own generator: a run depends on its seed alone.
"""
from __future__ import annotations

import copy
import dataclasses
import math

import torch

from marl_render.populations.networks import Actor

# Defaults, for a budget of 0.5-1 million env steps summed over 32 worlds (the competitive tasks' budgets):
# a snapshot every ~49 updates of 32 x 32 decisions gives 11-19 snapshots per run, of which the last 10 (the
# ghost trainer's default window) stay in play: old enough opponents to keep what was learnt against them,
# recent enough to be worth beating. Half the episodes face the latest snapshot (the ghost trainer's
# default ratio), the rest older ones. A new draw is due every 10,000 env steps, about 3 episodes of push
# and capture_flag (200 steps) per world and 3 of tag (100 steps, x 32 worlds): long enough for the critic
# to see an opponent over whole episodes, short enough that each update mixes several.
SNAPSHOT_EVERY, WINDOW, PLAY_LATEST, SWAP_EVERY = 50_000, 10, 0.5, 10_000


@dataclasses.dataclass(frozen=True)
class SelfPlay:
    """The pool's settings; each is checked on construction (ValueError naming the field)."""

    snapshot_every: int = SNAPSHOT_EVERY  # env steps (summed over worlds) between snapshots of the learner
    window: int = WINDOW  # the last `window` snapshots are in play
    play_latest: float = PLAY_LATEST  # chance that a draw is the latest snapshot
    swap_every: int = SWAP_EVERY  # env steps between draws of each world's opponent and learning team

    def __post_init__(self):
        for field in dataclasses.fields(self):
            problem = setting_problem(field.name, getattr(self, field.name))
            if problem:
                raise ValueError(f"self-play {field.name} {problem}")


def setting_problem(name: str, value) -> str | None:
    """What is wrong with `value` for the SelfPlay field `name` ("must be ..., got ..."), or None."""
    if name == "play_latest":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                math.isfinite(value) and 0.0 <= value <= 1.0):
            return f"must be a probability in [0, 1], got {value!r}"
    elif isinstance(value, bool) or not isinstance(value, int) or value < 1:
        return f"must be an int >= 1, got {value!r}"
    return None


def team_index(groups: dict) -> torch.Tensor:
    """int64 [A]: each agent's team (its group's index), from an env's ``groups``; ValueError for fewer than 2."""
    if len(groups) < 2:
        raise ValueError(f"self-play needs a task with two or more teams; this one has {len(groups)}: "
                         f"{list(groups)}")
    return torch.tensor([t for t, names in enumerate(groups.values()) for _ in names])


class SnapshotPool:
    """Frozen snapshots of the actor and which one each world faces.

    ``snapshots``: one record per snapshot ({id, env_steps, updates, episodes_faced, env_steps_faced}),
    ``actors``: the frozen actors (kept, small: a world may still face one that left the window),
    ``opponent`` [W] and ``learning_team`` [W]: each world's current draw."""

    def __init__(self, settings: SelfPlay, teams: torch.Tensor, worlds: int, seed: int):
        self.settings, self.teams = settings, teams
        self.num_teams = int(teams.max()) + 1
        self.draws = torch.Generator().manual_seed(seed)  # which snapshot each world faces
        self.sampler = torch.Generator().manual_seed(seed + 1)  # the snapshots' actions
        self.snapshots: list = []
        self.actors: list = []
        self.opponent = torch.zeros(worlds, dtype=torch.int64)
        self.learning_team = torch.arange(worlds) % self.num_teams
        self.epoch = torch.zeros(worlds, dtype=torch.int64)  # the swap period of each world's draw

    def add(self, actor: Actor, env_steps: int, updates: int) -> None:
        """A frozen copy of `actor` joins the pool (the oldest leaves the window)."""
        frozen = copy.deepcopy(actor).eval().requires_grad_(False)
        index = len(self.snapshots)
        self.snapshots.append({"id": index, "env_steps": env_steps, "updates": updates, "episodes_faced": 0,
                               "env_steps_faced": 0})
        self.actors.append(frozen)

    def draw(self, count: int) -> torch.Tensor:
        """`count` snapshot ids: the latest with probability play_latest, else uniform over the window."""
        latest = len(self.snapshots) - 1
        in_window = min(self.settings.window, len(self.snapshots))
        older = latest - in_window + 1 + torch.randint(in_window, (count,), generator=self.draws)
        chosen = torch.rand(count, generator=self.draws) < self.settings.play_latest
        return torch.where(chosen, latest, older)

    def start(self) -> None:
        """Every world's first draw (after the first snapshot is taken)."""
        self.opponent = self.draw(len(self.opponent))

    def redraw(self, worlds: torch.Tensor, env_steps: int) -> None:
        """Worlds (bool [W]) that start an episode: those whose draw is older than the current swap
        period draw a new snapshot, and their learning team moves on to the next team."""
        epoch = env_steps // self.settings.swap_every
        due = worlds & (self.epoch < epoch)
        count = int(due.sum())
        if count:
            self.opponent[due] = self.draw(count)
            self.learning_team[due] = (self.learning_team[due] + 1) % self.num_teams
            self.epoch[due] = epoch

    def learner_slots(self) -> torch.Tensor:
        """bool [W, A]: the slots the learner plays in each world (its learning team's)."""
        return self.teams[None, :] == self.learning_team[:, None]

    def count(self, env_steps_per_world: int, ended: torch.Tensor | None = None) -> None:
        """Tally what each snapshot faced: `env_steps_per_world` steps of every world, the episodes of
        the worlds in `ended` (bool [W])."""
        faced = torch.bincount(self.opponent, minlength=len(self.snapshots)).tolist()
        for record, worlds in zip(self.snapshots, faced, strict=True):
            record["env_steps_faced"] += worlds * env_steps_per_world
        if ended is not None:
            episodes = torch.bincount(self.opponent[ended], minlength=len(self.snapshots)).tolist()
            for record, n in zip(self.snapshots, episodes, strict=True):
                record["episodes_faced"] += n

    def act(self, observation: torch.Tensor, onehot: torch.Tensor, mask: torch.Tensor,
            actions: torch.Tensor, vector: torch.Tensor | None = None) -> torch.Tensor:
        """`actions` [W, A] with every opponent slot's action sampled by the snapshot its world faces;
        one batched forward per distinct snapshot in play. `observation` [W, A, ...] prepared by the
        caller's actor layout (raw, as the env gives it), `onehot` [A, A], `mask` [W, A, actions],
        `vector` [W, A, vector_dim] the task's vector observations (None: it has none)."""
        opponents = ~self.learner_slots()
        for snapshot in torch.unique(self.opponent).tolist():
            worlds, slots = (opponents & (self.opponent == snapshot)[:, None]).nonzero(as_tuple=True)
            if not len(worlds):
                continue
            actor = self.actors[snapshot]
            logits = actor(actor.prepare(observation[worlds, slots]), onehot[slots], mask[worlds, slots],
                           None if vector is None else vector[worlds, slots])
            actions[worlds, slots] = torch.multinomial(logits.softmax(-1), 1, generator=self.sampler)[:, 0]
        return actions

    def record(self) -> dict:
        """What result.json keeps: the settings, the teams and every snapshot's record."""
        return {**dataclasses.asdict(self.settings), "snapshots": [dict(s) for s in self.snapshots]}
