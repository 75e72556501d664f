"""Schelling diagrams of mixed-motive tasks: is the task really a dilemma?

For a task of A agents that declares ``schelling = (cooperator bot, defector bot)`` (envs/roster.py
bots), the diagram gives, for n = 0 .. A-1 other cooperators, the mean return of a cooperator
(among n other cooperators and A-1-n defectors) and of a defector (among n cooperators). It is a
dilemma where defecting pays the individual (defector(n) > cooperator(n) for every n) while
cooperating pays the group (all cooperating earns each more than all defecting).

    python -m marl_render.baselines.schelling --env matrix --episodes 8 --out out/schelling_matrix

writes OUT.json and OUT.png. All A + 1 mixes of k = 0 .. A cooperators play at once, `episodes`
worlds each, in one batched env (fixed ends at max_steps, so every mix plays as long).
"""
from __future__ import annotations

import argparse
import json

import torch

from marl_render.envs import env_class, make_env


def schelling(task: str, *, episodes: int = 8, seed: int = 0, resolution: int = 8, max_steps: int | None = None,
              **task_kwargs) -> dict:
    """{"cooperator": [A floats], "defector": [A floats], ...}: index n is the mean return of a
    cooperator / a defector with n other cooperators; see the module docstring."""
    cls = env_class(task)
    if len(cls.schelling) != 2 or not set(cls.schelling) <= set(cls.bots):
        raise ValueError(f"{cls.name} declares no schelling = (cooperator bot, defector bot) among its bots "
                         f"{sorted(cls.bots)}; got {cls.schelling!r}")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be an int >= 1, got {episodes!r}")
    cooperator, defector = (cls.bots[name] for name in cls.schelling)
    probe = make_env(task, num_worlds=1, resolution=resolution, **task_kwargs)
    A = probe.num_agents
    probe.close()
    mixes = torch.arange(A + 1).repeat_interleave(episodes)  # [W]: cooperators in each world
    cooperates = torch.arange(A)[None, :] < mixes[:, None]  # [W, A]: the first k agents cooperate
    with make_env(task, num_worlds=len(mixes), resolution=resolution, seed=seed, max_steps=max_steps,
                  episode_end=False, **task_kwargs) as env:
        env.reset()
        returns = torch.zeros(len(mixes), A, dtype=torch.float64)
        shape = (-1, A) + (1,) * (env.random_actions().ndim - 2)
        for _ in range(env.max_steps):
            actions = torch.where(cooperates.view(shape), cooperator.script(env), defector.script(env))
            returns += env.step(actions)[1].to(torch.float64)
    # A cooperator with n others: the cooperators' mean in the worlds of k = n + 1; a defector with n: k = n.
    counts = torch.zeros(A + 1, 2, dtype=torch.float64).index_add_(
        0, mixes, torch.stack((cooperates.sum(1), (~cooperates).sum(1)), 1).to(torch.float64))
    sums = torch.zeros(A + 1, 2, dtype=torch.float64).index_add_(
        0, mixes, torch.stack(((returns * cooperates).sum(1), (returns * ~cooperates).sum(1)), 1))
    mean = sums / counts.clamp_min(1)
    coop, defect = mean[1:, 0].tolist(), mean[:A, 1].tolist()
    return {"task": cls.name, "num_agents": A, "episodes_per_mix": episodes, "seed": seed, "max_steps": env.max_steps,
            "bots": list(cls.schelling), "params": {k: repr(v) for k, v in task_kwargs.items()},
            "others_cooperating": list(range(A)), "cooperator": coop, "defector": defect,
            "defecting_pays_the_individual": all(d > c for c, d in zip(coop, defect, strict=True)),
            "cooperating_pays_the_group": coop[-1] > defect[0]}


def plot(result: dict, path: str) -> None:
    import matplotlib  # lazily: only the picture needs it
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(5, 3.5))
    n = result["others_cooperating"]
    axes.plot(n, result["cooperator"], "o-", color="tab:green", label=f"cooperator ({result['bots'][0]})")
    axes.plot(n, result["defector"], "s-", color="tab:red", label=f"defector ({result['bots'][1]})")
    axes.set_xlabel("other cooperators")
    axes.set_ylabel("mean return per episode")
    axes.set_title(f"Schelling diagram: {result['task']} ({result['num_agents']} agents)")
    axes.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.baselines.schelling", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", required=True, help="a task that declares schelling = (cooperator, defector)")
    parser.add_argument("--episodes", type=int, default=8, help="episodes (worlds) per mix of cooperators")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", type=int, default=8, help="pixels per side (the bots read the state)")
    parser.add_argument("--max-steps", type=int, default=None, help="episode length (default: the task's)")
    parser.add_argument("--out", default=None, help="write OUT.json and OUT.png (default: print the JSON)")
    args = parser.parse_args(argv)
    try:
        result = schelling(args.env, episodes=args.episodes, seed=args.seed, resolution=args.resolution,
                           max_steps=args.max_steps)
    except ValueError as error:
        parser.error(str(error))
    if args.out is None:
        print(json.dumps(result, indent=1))
        return 0
    with open(args.out + ".json", "w") as handle:
        json.dump(result, handle, indent=1)
    plot(result, args.out + ".png")
    print(f"wrote {args.out}.json and {args.out}.png", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
