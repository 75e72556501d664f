"""A custom two-agent scene in about 30 lines: two robots facing each other across a table.
Writes OUT/custom_scene.png: a row per world, robot 0's view left of robot 1's."""
import argparse
import math
import os

import torch
from PIL import Image

import marl_render as mr


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
parser.add_argument("--out", default="out", help="output folder")
parser.add_argument("--worlds", type=int, default=4, help="worlds, each with its own balls")
parser.add_argument("--resolution", type=int, nargs=2, default=(96, 128), metavar=("H", "W"), help="view size")
args = parser.parse_args()

worlds, agents, path = args.worlds, 2, os.path.join(args.out, "custom_scene.png")
scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=args.resolution, effects=("lighting", "fog"))
scene.add_static("floor", "plane", position=[0, 0, 0], scale=[8, 8, 1], color=[0.8, 0.8, 0.75])
scene.add_static("table", "box", position=[0, 0, 0.4], scale=[1.2, 0.8, 0.8], color=[0.55, 0.35, 0.2])
scene.add_group("robots", mr.capsule(0.25, 1.4), capacity=agents)
scene.add_group("balls", mr.sphere(), capacity=3)
scene.mount_cameras("robots", instance=[0, 1], offset=(0.0, 0.1, 0.5), pitch=-0.35)

renderer = mr.BatchRenderer(scene)
yaw = torch.tensor([[-math.pi / 2, math.pi / 2]]).repeat(worlds, 1)  # robot 0 looks along +x, robot 1 along -x
renderer.update("robots", position=torch.tensor([[-1.5, 0, 0.7], [1.5, 0, 0.7]]).repeat(worlds, 1, 1),
                rotation=mr.quat_from_yaw_pitch_roll(yaw), active=torch.ones(worlds, agents, dtype=torch.bool),
                color=torch.tensor([[0.9, 0.2, 0.2], [0.2, 0.3, 0.9]]).repeat(worlds, 1, 1))
balls = torch.rand(worlds, 3, 3) * torch.tensor([1.0, 0.6, 0.0]) - torch.tensor([0.5, 0.3, -0.95])
renderer.update("balls", position=balls, scale=torch.full((worlds, 3, 3), 0.2),
                active=torch.ones(worlds, 3, dtype=torch.bool), color=torch.rand(worlds, 3, 3))
rgb = renderer.render().rgb  # [worlds, 2, H, W, 3] uint8
grid = rgb.permute(0, 2, 1, 3, 4).reshape(worlds * rgb.shape[2], agents * rgb.shape[3], 3)  # worlds down, agents across
os.makedirs(args.out, exist_ok=True)
Image.fromarray(grid.numpy()).save(path)
print("wrote", path, tuple(rgb.shape))
renderer.close()
