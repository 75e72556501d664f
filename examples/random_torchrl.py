"""Random agents in the batched TorchRL env of marl-render: many worlds stepped and rendered at once.

    python examples/random_torchrl.py [--env spread] [--worlds 64] [--steps 60] [--max-steps 25]
                                      [--resolution 32] [--out out]

Checks the specs, collects a rollout of --worlds worlds x --steps steps with a random
policy (TorchRL resets the worlds whose episode ended, world by world) and prints shapes,
the mean reward, the number of finished episodes and frames per second. Writes the
overview camera of the first (up to 8) worlds at the end of the rollout, side by side, to
OUT/random_torchrl.png.
"""
import argparse
import os
import time

import torch
from PIL import Image
from torchrl.envs.utils import check_env_specs

from marl_render.envs import list_envs
from marl_render.wrappers.torchrl import make_torchrl_env


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--env", default="spread", choices=list_envs(), help="environment")
    parser.add_argument("--worlds", type=int, default=64, help="worlds stepped together")
    parser.add_argument("--steps", type=int, default=60, help="rollout length")
    parser.add_argument("--max-steps", type=int, default=25, help="episode length limit")
    parser.add_argument("--resolution", type=int, default=32, help="pixels per side of a view")
    parser.add_argument("--seed", type=int, default=0, help="reset seed")
    parser.add_argument("--out", default="out", help="folder for random_torchrl.png")
    return parser.parse_args(argv)


def main(argv=None) -> None:
    args = parse_args(argv)
    env = make_torchrl_env(args.env, num_worlds=args.worlds, resolution=args.resolution, max_steps=args.max_steps,
                           seed=args.seed)
    print(env)
    print(f"groups: {env.group_map}")
    check_env_specs(env)
    env.rollout(2)  # warm-up
    start = time.perf_counter()
    td = env.rollout(args.steps, break_when_any_done=False)
    elapsed = time.perf_counter() - start
    for group in env.group_map:
        pixels = td["next", group, "pixels"]
        reward = td["next", group, "reward"]
        print(f"{group}: pixels {tuple(pixels.shape)} {pixels.dtype}, action {tuple(td[group, 'action'].shape)}, "
              f"mean reward {reward.mean().item():.3f}")
    episodes = int(td["next", "done"].sum())
    frames = args.worlds * args.steps
    views = frames * len(env.agent_names)
    print(f"{episodes} episodes finished; {frames / elapsed:.0f} world steps/s, {views / elapsed:.0f} agent views/s "
          f"({torch.get_num_threads()} torch threads)")
    overview = env.render_overview()[:8]  # [worlds, H, W, 3] uint8
    path = os.path.join(args.out, "random_torchrl.png")
    os.makedirs(args.out, exist_ok=True)
    Image.fromarray(torch.cat(tuple(overview), dim=1).numpy()).save(path)
    print(f"wrote {path}: overview of {len(overview)} worlds, {tuple(overview.shape[1:3])} each")
    env.close()


if __name__ == "__main__":
    main()
