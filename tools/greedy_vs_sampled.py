"""A saved pixel or state run's actor played greedily and with actions drawn from its distribution,
on the same development worlds: a diagnostic for a greedy policy that gets stuck where sampling moves on.

    python tools/greedy_vs_sampled.py docs/final/rooms/seed0 docs/final/rooms/seed1 --episodes 64

The development worlds (seed 1000) by default; the sealed final set is refused (evaluate's guard).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from marl_render.baselines.policy import GreedyPolicy
from marl_render.baselines.published import evaluation_kwargs
from marl_render.baselines.settings import EVALUATION_SETS
from marl_render.envs.evaluation import evaluate, opponent_mask
from marl_render.populations.policies import load_policy


class SampledPolicy(GreedyPolicy):
    def choose(self, logits: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        return torch.multinomial(logits.softmax(-1), 1, generator=generator).squeeze(-1)


class Deferred:
    """Builds the policy at the first call, when the env shows which agents are evaluated (as ablate's)."""

    def __init__(self, kind, loaded, obs_key: str, hp: dict):  # obs_key: "pixels" or "state", the run's obs
        self.kind, self.loaded, self.obs_key, self.hp, self.policy = kind, loaded, obs_key, hp, None
        self.needs = frozenset({obs_key, "action_mask", *loaded.vector_keys})

    def __call__(self, env, obs, generator):
        if self.policy is None:
            self.policy = self.kind(self.loaded.actor, ~opponent_mask(env), self.obs_key, self.hp.get("frames", 1),
                                    self.hp.get("action_repeat", 1), self.loaded.vector_keys)
        return self.policy(env, obs, generator)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run folders (result.json and actor.pt)")
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--seed", type=int, default=EVALUATION_SETS["development"]["seed"])
    args = parser.parse_args(argv)
    for run in args.runs:
        result = json.loads((Path(run) / "result.json").read_text())
        kwargs = {**evaluation_kwargs(result), "seed": args.seed, "episodes": args.episodes}
        loaded = load_policy(run)
        means = {name: evaluate(result["env"], Deferred(kind, loaded, result["obs"], result["hyperparameters"]),
                                **kwargs)["mean"] for name, kind in (("greedy", GreedyPolicy),
                                                                     ("sampled", SampledPolicy))}
        print(json.dumps({"run": run, "seed": args.seed, "episodes": args.episodes, **means}), flush=True)


if __name__ == "__main__":
    main()
