"""A custom two-agent scene in about 30 lines: two robots facing each other across a table."""
import math
import os

import torch
from PIL import Image

import marl_render as mr

worlds, agents = 4, 2
scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=(96, 128), effects=("lighting", "fog"))
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
renderer.update("balls", position=balls, scale=torch.full((worlds, 3, 3), 0.2), active=torch.ones(worlds, 3, dtype=torch.bool),
                color=torch.rand(worlds, 3, 3))
rgb = renderer.render().rgb  # [4, 2, 96, 128, 3] uint8
os.makedirs("out", exist_ok=True)
grid = torch.cat(tuple(torch.cat(tuple(rgb[w]), dim=1) for w in range(worlds)), dim=0)  # worlds down, agents across
Image.fromarray(grid.numpy()).save("out/custom_scene.png")
print("wrote out/custom_scene.png", tuple(rgb.shape))
renderer.close()
