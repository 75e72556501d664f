"""The main demo: several worlds, several agents, every agent's own camera.

    python examples/demo.py [--out out] [--worlds 8] [--agents 4] [--resolution 96]
                            [--bench-worlds 256] [--steps 20]

Renders --worlds x --agents views of an arena, writes a PNG grid of all of them to
OUT/demo.png (a row per world, a column per agent), then measures the throughput of
--bench-worlds x --agents views at 64x64 over --steps frames and prints views/s together
with the OpenGL renderer in use (--steps 0 skips the measurement).
"""
import argparse
import math
import os
import time

import numpy as np
import torch
from PIL import Image

import marl_render as mr
from marl_render import backend


def arena(worlds, agents, resolution):
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=resolution,
                     effects=("lighting", "fog"), fog=mr.Fog(density=0.04))
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[12, 12, 1], color=[0.35, 0.55, 0.35])
    walls = [[6, 0, 0.5], [-6, 0, 0.5], [0, 6, 0.5], [0, -6, 0.5]]
    scale = [[0.2, 12, 1], [0.2, 12, 1], [12, 0.2, 1], [12, 0.2, 1]]
    scene.add_static("walls", "box", position=walls, scale=scale, color=[0.6, 0.6, 0.65])
    scene.add_group("agents", mr.capsule(0.3, 1.0, segments=10, rings=3), capacity=agents)
    scene.add_group("crates", "box", capacity=6)
    scene.mount_cameras("agents", list(range(agents)), offset=(0.0, 0.0, 0.3), pitch=-0.1)
    return scene


def random_poses(renderer, scene, generator):
    W = scene.num_worlds
    for name, group in scene.groups.items():
        C = group.capacity
        position = torch.rand(W, C, 3, generator=generator) * 9 - 4.5
        position[..., 2] = 0.5
        yaw = torch.rand(W, C, generator=generator) * 2 * math.pi
        hue = torch.arange(C, dtype=torch.float32) / C
        color = torch.stack((0.5 + 0.5 * torch.cos(2 * math.pi * hue),
                             0.5 + 0.5 * torch.cos(2 * math.pi * (hue - 1 / 3)),
                             0.5 + 0.5 * torch.cos(2 * math.pi * (hue - 2 / 3))), -1).expand(W, C, 3)
        renderer.update(name, position=position, rotation=mr.quat_from_yaw_pitch_roll(yaw),
                        active=torch.ones(W, C, dtype=torch.bool), color=color)


def save_grid(rgb: torch.Tensor, path: str, scale: int = 2) -> None:
    """[W, A, H, Wpx, 3] -> one image: a row per world, a column per agent, 2 px gaps."""
    worlds, agents, h, w, _ = rgb.shape
    canvas = np.full((worlds * (h + 2), agents * (w + 2), 3), 255, dtype=np.uint8)
    for world in range(worlds):  # a handful of tiles for a picture, not a hot path
        for agent in range(agents):
            top, left = world * (h + 2), agent * (w + 2)
            canvas[top: top + h, left: left + w] = rgb[world, agent].numpy()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    Image.fromarray(canvas).resize((canvas.shape[1] * scale, canvas.shape[0] * scale), Image.NEAREST).save(path)


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--out", default="out", help="folder for demo.png")
    parser.add_argument("--worlds", type=int, default=8, help="worlds in the picture")
    parser.add_argument("--agents", type=int, default=4, help="agents (views) per world")
    parser.add_argument("--resolution", type=int, default=96, help="pixels per side of a view in the picture "
                                                                   "")
    parser.add_argument("--bench-worlds", type=int, default=256, help="worlds in the throughput measurement, "
                                                                      "64x64 views")
    parser.add_argument("--steps", type=int, default=20, help="timed frames of the throughput measurement; "
                                                              "0 skips it")
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    generator = torch.Generator().manual_seed(0)
    scene = arena(args.worlds, args.agents, args.resolution)
    with mr.BatchRenderer(scene) as renderer:
        random_poses(renderer, scene, generator)
        frame = renderer.render()
    path = os.path.join(args.out, "demo.png")
    save_grid(frame.rgb, path)
    print(f"wrote {path}: {scene.num_worlds} worlds x {scene.agents_per_world} agents, "
          f"{scene.resolution[0]}x{scene.resolution[1]} each")
    if args.steps <= 0:
        return

    scene = arena(args.bench_worlds, args.agents, 64)
    with mr.BatchRenderer(scene) as renderer:
        for _ in range(3):  # warm-up: shader compile, first upload
            random_poses(renderer, scene, generator)
            renderer.render()
        start = time.perf_counter()
        for _ in range(args.steps):
            random_poses(renderer, scene, generator)
            renderer.render()
        seconds = (time.perf_counter() - start) / args.steps
    info = backend.gl_info()
    print(f"throughput: {scene.num_views / seconds:,.0f} views/s ({scene.num_views} views of 64x64 per frame, "
          f"{seconds * 1e3:.1f} ms per frame incl. pose upload and readback)")
    print(f"GL renderer: {info.renderer} | {info.gl_version}")


if __name__ == "__main__":
    main()
