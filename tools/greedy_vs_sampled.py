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

from marl_render.baselines.ablate import AblatedPolicy
from marl_render.baselines.policy import GreedyPolicy
from marl_render.baselines.published import evaluation_kwargs
from marl_render.baselines.settings import EVALUATION_SETS
from marl_render.envs.evaluation import evaluate
from marl_render.populations.policies import load_policy


class SampledPolicy(GreedyPolicy):
    def choose(self, logits: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        return torch.multinomial(logits.softmax(-1), 1, generator=generator).squeeze(-1)


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
        hp = result["hyperparameters"]
        means = {name: evaluate(result["env"], AblatedPolicy(loaded.actor, hp.get("frames", 1),
                                                             hp.get("action_repeat", 1), "none", loaded.vector_keys,
                                                             obs_key=result["obs"], kind=kind), **kwargs)["mean"]
                 for name, kind in (("greedy", GreedyPolicy), ("sampled", SampledPolicy))}
        print(json.dumps({"run": run, "seed": args.seed, "episodes": args.episodes, **means}), flush=True)


if __name__ == "__main__":
    main()
