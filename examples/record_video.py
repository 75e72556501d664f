"""Record an episode: every agent's view next to the top-down overview, as a GIF (or MP4).

    python examples/record_video.py --env tag --steps 80 --out out/tag.gif
An .mp4 output needs imageio's ffmpeg plugin (pip install imageio-ffmpeg).
"""
import argparse
import os

import imageio.v3 as iio
import torch
import torch.nn.functional as F

from marl_render.envs import make_env


def frame_image(pixels: torch.Tensor, overview: torch.Tensor) -> torch.Tensor:
    """Agents' views [A, H, W, 3] in a column beside the overview [H2, W2, 3], one uint8 image."""
    views = torch.cat(tuple(pixels), dim=0)  # stacked vertically
    height = views.shape[0]
    scaled = F.interpolate(overview.permute(2, 0, 1)[None].float(), size=(height, height * overview.shape[1] // overview.shape[0]),
                           mode="nearest")[0].permute(1, 2, 0).to(torch.uint8)
    return torch.cat((views, scaled), dim=1)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="spread")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="out/episode.gif")
    args = parser.parse_args()

    env = make_env(args.env, num_worlds=1, resolution=args.resolution, seed=args.seed)
    generator = torch.Generator().manual_seed(args.seed)
    obs = env.reset(seed=args.seed)
    frames = [frame_image(obs["pixels"][0], env.render_overview()[0])]
    for step in range(args.steps):
        obs, reward, terminated, truncated, info = env.step(env.random_actions(generator))
        frames.append(frame_image(obs["pixels"][0], env.render_overview()[0]))
        if bool((terminated | truncated).all()):
            break
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    iio.imwrite(args.out, torch.stack(frames).numpy(), duration=100, loop=0)
    print(f"wrote {args.out}: {len(frames)} frames of {tuple(frames[0].shape)} ({env.num_agents} agents + overview)")
    env.close()


if __name__ == "__main__":
    main()
