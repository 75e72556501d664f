"""Random agents in a PettingZoo ParallelEnv of marl-render (one world, egocentric pixels).

    python examples/random_pettingzoo.py [env_name]

Plays two short episodes of `spread` (or the env named on the command line) with random
actions, prints the observation / action spaces, each episode's return per agent and the
steps per second, and writes the tiled render (every agent's view + overview) to
out/random_pettingzoo.png.
"""
import os
import sys
import time

from PIL import Image

from marl_render.wrappers.pettingzoo import make_parallel_env


def main(name: str = "spread") -> None:
    env = make_parallel_env(name, resolution=64, max_steps=50, render_mode="rgb_array")
    agent = env.possible_agents[0]
    print(f"{env.metadata['name']}: agents {env.possible_agents}")
    print(f"  observation_space({agent!r}) = {env.observation_space(agent)}")
    print(f"  action_space({agent!r}) = {env.action_space(agent)}")
    steps, start = 0, time.perf_counter()
    for episode in range(2):
        obs, infos = env.reset(seed=episode)
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
    os.makedirs("out", exist_ok=True)
    Image.fromarray(env.render()).save("out/random_pettingzoo.png")
    print("wrote out/random_pettingzoo.png")
    env.close()


if __name__ == "__main__":
    main(*sys.argv[1:2])
