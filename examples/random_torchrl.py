"""Random agents in the batched TorchRL env of marl-render: many worlds stepped and rendered at once.

    python examples/random_torchrl.py [env_name]

Checks the specs, collects a rollout of 64 worlds x 60 steps with a random policy (TorchRL
resets the worlds whose episode ended, world by world) and prints shapes, the mean reward,
the number of finished episodes and frames per second.
"""
import sys
import time

import torch
from torchrl.envs.utils import check_env_specs

from marl_render.wrappers.torchrl import make_torchrl_env


def main(name: str = "spread") -> None:
    worlds, steps = 64, 60
    env = make_torchrl_env(name, num_worlds=worlds, resolution=32, max_steps=25, seed=0)
    print(env)
    print(f"groups: {env.group_map}")
    check_env_specs(env)
    env.rollout(2)  # warm-up
    start = time.perf_counter()
    td = env.rollout(steps, break_when_any_done=False)
    elapsed = time.perf_counter() - start
    for group in env.group_map:
        pixels = td["next", group, "pixels"]
        reward = td["next", group, "reward"]
        print(f"{group}: pixels {tuple(pixels.shape)} {pixels.dtype}, action {tuple(td[group, 'action'].shape)}, "
              f"mean reward {reward.mean().item():.3f}")
    episodes = int(td["next", "done"].sum())
    frames = worlds * steps
    views = frames * len(env.agent_names)
    print(f"{episodes} episodes finished; {frames / elapsed:.0f} world steps/s, {views / elapsed:.0f} agent views/s "
          f"({torch.get_num_threads()} torch threads)")
    print(f"overview: {tuple(env.render_overview().shape)}")
    env.close()


if __name__ == "__main__":
    main(*sys.argv[1:2])
