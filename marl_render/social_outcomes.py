"""The social outcomes of mixed-motive tasks (envs/episodes.py) in the evaluation CLI's rows.

A mixed-motive task's env reports efficiency, equality, sustainability and peace in its info, for
the episode so far; ``EpisodeOutcomes`` keeps each world's values at the step its episode ended,
and ``fields`` gives their means over the episodes for a row of ``python -m marl_render.evaluate``.

    outcomes = EpisodeOutcomes(env)
    ... obs, reward, terminated, truncated, info = env.step(actions); outcomes.add(info, running)
    row.update(outcomes.fields())    # {"efficiency_mean": ..., "equality_mean": ..., ...}; {} for other tasks
"""
from __future__ import annotations

import torch

from marl_render.envs.episodes import SOCIAL_KEYS


class EpisodeOutcomes:
    """Each world's social outcomes at the end of its episode, collected step by step."""

    def __init__(self, env):
        self.keys = tuple(key for key in SOCIAL_KEYS if key in env.spec.info)
        self.values = {key: torch.full((env.num_worlds,), float("nan"), dtype=torch.float64) for key in self.keys}

    def add(self, info: dict, running: torch.Tensor) -> None:
        """Keep the values of the worlds whose episode ended at this step (done_worlds among `running`)."""
        ended = (info["done_worlds"] & running).cpu()
        for key in self.keys:
            self.values[key] = torch.where(ended, info[key].cpu().to(torch.float64), self.values[key])

    def fields(self) -> dict:
        """{"<outcome>_mean": mean over the episodes that ended}; {} for a task without social outcomes."""
        return {f"{key}_mean": float(values[~values.isnan()].mean()) for key, values in self.values.items()}
