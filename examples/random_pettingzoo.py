"""Random agents in a PettingZoo ParallelEnv of marl-render (one world, egocentric pixels).

    python examples/random_pettingzoo.py [--env spread] [--episodes 2] [--steps 50] [--resolution 64] [--out out]

Plays --episodes short episodes (at most --steps steps each) with random actions, prints
the observation / action spaces, each episode's return per agent and the steps per second,
and writes the tiled render of the last step (every agent's view + the overview) to
OUT/random_pettingzoo.png.
"""
import argparse
import os
import time

from PIL import Image

from marl_render.envs import list_envs
from marl_render.wrappers.pettingzoo import make_parallel_env


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--env", default="spread", choices=list_envs(), help="environment")
    parser.add_argument("--episodes", type=int, default=2, help="episodes to play")
    parser.add_argument("--steps", type=int, default=50, help="max_steps of an episode")
    parser.add_argument("--resolution", type=int, default=64, help="pixels per side of a view")
    parser.add_argument("--seed", type=int, default=0, help="episode i is reset with seed + i")
    parser.add_argument("--out", default="out", help="folder for random_pettingzoo.png")
    return parser.parse_args(argv)


def main(argv=None) -> None:
    args = parse_args(argv)
    env = make_parallel_env(args.env, resolution=args.resolution, max_steps=args.steps, render_mode="rgb_array")
    agent = env.possible_agents[0]
    print(f"{args.env}: agents {env.possible_agents}")
    print(f"  observation_space({agent!r}) = {env.observation_space(agent)}")
    print(f"  action_space({agent!r}) = {env.action_space(agent)}")
    for i, a in enumerate(env.possible_agents):  # reproducible random actions
        env.action_space(a).seed(args.seed + i)
    steps, start = 0, time.perf_counter()
    for episode in range(args.episodes):
        obs, infos = env.reset(seed=args.seed + episode)
        returns = dict.fromkeys(env.agents, 0.0)
        while env.agents:
            actions = {a: env.action_space(a).sample() for a in env.agents}
            obs, rewards, terminations, truncations, infos = env.step(actions)
            for a, r in rewards.items():
                returns[a] += r
            steps += 1
        shape = next(iter(obs.values())).shape
        print(f"episode {episode}: {steps} steps so far, obs {shape}, "
              f"returns {{{', '.join(f'{a}: {r:.2f}' for a, r in returns.items())}}}")
    elapsed = time.perf_counter() - start
    print(f"{steps / elapsed:.0f} env steps/s ({steps * len(env.possible_agents) / elapsed:.0f} agent views/s)")
    path = os.path.join(args.out, "random_pettingzoo.png")
    os.makedirs(args.out, exist_ok=True)
    Image.fromarray(env.render()).save(path)
    print(f"wrote {path}")
    env.close()


if __name__ == "__main__":
    main()
