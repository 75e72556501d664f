"""Record an episode: every agent's view next to the top-down overview, as a GIF (or MP4).

    python examples/record_video.py --env tag --steps 80 --out out/tag.gif

Each frame has the agents' views (world 0) in a column, labelled with the agent's name
("(left)" once it has left the episode, e.g. a caught prey), beside the overview camera.
--scale enlarges the views (nearest neighbour) so that the labels stay readable.
An .mp4 output needs imageio's ffmpeg plugin (pip install imageio-ffmpeg).
"""
import argparse
import os

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageDraw, ImageFont

from marl_render.envs import list_envs, make_env
from marl_render.extras import command_needs_extra

with command_needs_extra("video", "examples/record_video.py"):
    import imageio.v3 as iio

FORMATS = (".gif", ".mp4")


def frame_image(pixels: torch.Tensor, overview: torch.Tensor, labels: list, scale: int, font) -> np.ndarray:
    """Agents' views [A, H, W, 3], enlarged `scale` times and labelled, in a column beside the
    overview [H2, W2, 3] (labelled "overview"): one uint8 image [A * H * scale, ..., 3]."""
    views = pixels.repeat_interleave(scale, dim=1).repeat_interleave(scale, dim=2)
    column = torch.cat(tuple(views), dim=0)  # stacked vertically
    height, tile = column.shape[0], views.shape[1]
    size = (height, height * overview.shape[1] // overview.shape[0])
    side = F.interpolate(overview.permute(2, 0, 1)[None].float(), size=size, mode="nearest")[0]
    image = Image.fromarray(torch.cat((column, side.permute(1, 2, 0).to(torch.uint8)), dim=1).numpy())
    width = views.shape[2]
    boxes = [(0, i * tile, width, (i + 1) * tile) for i in range(len(labels))] + [(width, 0, image.width, height)]
    for box, label in zip(boxes, list(labels) + ["overview"], strict=True):  # a few tiles per frame
        part = image.crop(box)  # drawn on its own, so a long label cannot spill into the next tile
        draw = ImageDraw.Draw(part)
        draw.rectangle((0, 0, part.width - 1, part.height - 1), outline=(25, 25, 25))
        draw.text((3, 2), label, font=font, fill="white", stroke_width=1, stroke_fill="black")
        image.paste(part, box[:2])
    return np.asarray(image)


def agent_labels(env) -> list:
    """Agent names of world 0, marked "(left)" for agents that left the episode."""
    alive = env.alive[0].tolist()
    return [name if up else f"{name} (left)" for name, up in zip(env.agent_names, alive, strict=True)]


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--env", default="spread", choices=list_envs(), help="environment")
    parser.add_argument("--steps", type=int, default=60, help="steps at most; the episode may end first "
                                                              "")
    parser.add_argument("--resolution", type=int, default=64, help="pixels per side of a view")
    parser.add_argument("--scale", type=int, default=2, help="enlargement of the views")
    parser.add_argument("--seed", type=int, default=0, help="reset seed")
    parser.add_argument("--out", default="out/episode.gif", help="output file, .gif or .mp4")
    args = parser.parse_args(argv)
    if os.path.splitext(args.out)[1].lower() not in FORMATS:
        parser.error(f"--out must end in one of {FORMATS}, got {args.out!r}")
    if args.scale < 1:
        parser.error(f"--scale must be an int >= 1, got {args.scale}")
    return args


def main(argv=None):
    args = parse_args(argv)
    env = make_env(args.env, num_worlds=1, resolution=args.resolution, seed=args.seed)
    font = ImageFont.load_default(size=max(9, env.resolution[0] * args.scale // 10))
    generator = torch.Generator().manual_seed(args.seed)
    obs = env.reset(seed=args.seed)
    frames = [frame_image(obs["pixels"][0], env.render_overview()[0], agent_labels(env), args.scale, font)]
    for _ in range(args.steps):
        obs, reward, terminated, truncated, info = env.step(env.random_actions(generator))
        frames.append(frame_image(obs["pixels"][0], env.render_overview()[0], agent_labels(env), args.scale, font))
        if bool((terminated | truncated).all()):
            break
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    iio.imwrite(args.out, np.stack(frames), duration=100, loop=0)
    print(f"wrote {args.out}: {len(frames)} frames of {frames[0].shape} ({env.num_agents} agents + overview)")
    env.close()


if __name__ == "__main__":
    main()
