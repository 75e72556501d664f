"""Skinned walkers: agents whose legs, arms and lean follow their actions, seen egocentrically.

    python examples/skinned_walkers.py [--out out] [--worlds 16] [--agents 3] [--resolution 64] [--steps 40]

Every agent is a mr.skinned_character(). Its action each step is (speed in [0, 1], turn
in [-1, 1]); the walk moves it and sets its joints: hips and shoulders swing with a gait
phase that advances with the speed, knees and elbows bend, the body leans into turns.
All of it is batched torch: the joints of all worlds go to the renderer as one
[W, A, J, 4] tensor. Every agent sees the world (and the others' limbs) from its head.

Writes OUT/skinned_walkers.png: an overview of world 0 above its agents' own views. Then
times the same walk rendered with the skinned mesh and with the rigid bind-pose mesh
(same process, alternating blocks of steps) and prints both rates and their ratio.
"""
import argparse
import math
import os
import time

import numpy as np
import torch
from PIL import Image

import marl_render as mr

DT = 0.1  # seconds per step
ARENA = 4.0  # half-width of the walled floor, metres


def make_scene(worlds, agents, resolution, mesh, overview=False):
    """The arena with one walker per agent; the overview has one free camera instead of mounted ones."""
    scene = mr.Scene(num_worlds=worlds, agents_per_world=1 if overview else agents, resolution=resolution,
                     effects=("lighting", "fog"), fog=mr.Fog(density=0.03))
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[2 * ARENA + 1, 2 * ARENA + 1, 1],
                     color=[0.45, 0.6, 0.4])
    walls = [[ARENA + 0.5, 0, 0.4], [-ARENA - 0.5, 0, 0.4], [0, ARENA + 0.5, 0.4], [0, -ARENA - 0.5, 0.4]]
    sizes = [[0.2, 2 * ARENA + 1, 0.8]] * 2 + [[2 * ARENA + 1, 0.2, 0.8]] * 2
    scene.add_static("walls", "box", position=walls, scale=sizes, color=[0.65, 0.6, 0.55])
    scene.add_static("pillars", "cylinder", position=[[1.5, 1.5, 0.6], [-2.0, -1.0, 0.6], [2.5, -2.5, 0.6]],
                     scale=[0.4, 0.4, 1.2], color=[0.5, 0.5, 0.7])
    scene.add_group("walkers", mesh, capacity=agents)
    if not overview:  # eyes in front of the head, looking a little down
        scene.mount_cameras("walkers", list(range(agents)), offset=(0.0, 0.09, 0.93), pitch=-0.15)
    return scene


class Walk:
    """Batched walker state [W, A] and the joint pose that follows from each action."""

    def __init__(self, worlds, agents, mesh, seed):
        self.generator = torch.Generator().manual_seed(seed)
        self.position = torch.rand(worlds, agents, 3, generator=self.generator, dtype=torch.float64) * 3 - 1.5
        self.position[..., 2] = 0.0
        self.yaw = torch.rand(worlds, agents, generator=self.generator) * 2 * math.pi
        self.phase = torch.rand(worlds, agents, generator=self.generator) * 2 * math.pi
        self.action = torch.zeros(worlds, agents, 2)
        self.joint = {name: mesh.joint_index(name) for name in mesh.joint_names}
        self.num_joints = mesh.num_joints

    def random_actions(self):
        """Persistent random actions: each agent keeps its speed and turn for a while."""
        change = torch.rand(self.action.shape[:2], generator=self.generator) < 0.1
        fresh = torch.stack((torch.rand(self.action.shape[:2], generator=self.generator),
                             torch.rand(self.action.shape[:2], generator=self.generator) * 2 - 1), -1)
        return torch.where(change[..., None], fresh, self.action)

    def step(self, action):
        self.action = action
        speed, turn = action.unbind(-1)
        self.yaw = self.yaw + 1.5 * turn * DT
        heading = torch.stack((-torch.sin(self.yaw), torch.cos(self.yaw)), -1).to(torch.float64)  # +Y at yaw 0
        self.position[..., :2] = (self.position[..., :2] + 1.2 * speed[..., None] * heading * DT).clamp(
            -ARENA + 0.3, ARENA - 0.3)
        self.phase = self.phase + 2 * math.pi * 1.6 * speed * DT  # strides per second grow with speed

    def joints(self):
        """[W, A, J, 4] joint rotations: pitch about +X swings a hanging limb forward."""
        speed, turn = self.action.unbind(-1)
        swing = 0.6 * speed * torch.sin(self.phase)
        pitch = torch.zeros(*self.phase.shape, self.num_joints)
        roll = torch.zeros_like(pitch)
        j = self.joint
        pitch[..., j["left_hip"]], pitch[..., j["right_hip"]] = swing, -swing
        pitch[..., j["left_knee"]] = -1.1 * speed * torch.relu(-torch.sin(self.phase))  # bend while swinging back
        pitch[..., j["right_knee"]] = -1.1 * speed * torch.relu(torch.sin(self.phase))
        pitch[..., j["left_shoulder"]], pitch[..., j["right_shoulder"]] = -0.8 * swing, 0.8 * swing
        pitch[..., j["left_elbow"]] = pitch[..., j["right_elbow"]] = 0.3 + 0.5 * speed
        pitch[..., j["pelvis"]] = -0.12 * speed  # lean forward when fast
        roll[..., j["pelvis"]] = 0.25 * turn  # and into turns
        return mr.quat_from_yaw_pitch_roll(torch.zeros_like(pitch), pitch, roll)

    def instance_update(self, skinned=True):
        update = dict(position=self.position, rotation=mr.quat_from_yaw_pitch_roll(self.yaw))
        return dict(update, joints=self.joints()) if skinned else update


def overview_picture(walk, colors, views, path):
    """World 0 from above and behind its walkers, over its agents' egocentric views."""
    scene = make_scene(1, walk.position.shape[1], (360, 640), mr.skinned_character(), overview=True)
    with mr.BatchRenderer(scene) as renderer:
        centre = walk.position[0].mean(0)
        spread = (walk.position[0] - centre).norm(dim=-1).max().item()
        eye = centre + torch.tensor([0.5, -1.8, 0.9], dtype=torch.float64) * (0.45 * spread + 0.8)
        renderer.set_cameras(position=eye.view(1, 1, 3), look_at=(centre + torch.tensor([0, 0, 0.4])).view(1, 1, 3))
        state = {key: value[:1] for key, value in walk.instance_update().items()}
        renderer.update("walkers", active=torch.ones(1, colors.shape[1], dtype=torch.bool), color=colors[:1], **state)
        overview = renderer.render().rgb[0, 0].numpy()
    agents, h = views.shape[1], views.shape[2]
    gap = np.full((h, 2, 3), 255, np.uint8)  # white lines between the agents' views
    row = np.concatenate([part for a in range(agents) for part in (gap, views[0, a].numpy())][1:], axis=1)
    row = np.asarray(Image.fromarray(row).resize((640, round(640 * h / row.shape[1])), Image.NEAREST))
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    Image.fromarray(np.concatenate((overview, row), axis=0)).save(path)


def views_per_s(renderer, walk, skinned, steps):
    start = time.perf_counter()
    for _ in range(steps):
        walk.step(walk.random_actions())
        renderer.update("walkers", **walk.instance_update(skinned))
        renderer.render()
    return renderer.num_views * steps / (time.perf_counter() - start)


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--out", default="out", help="output folder")
    parser.add_argument("--worlds", type=int, default=16, help="worlds")
    parser.add_argument("--agents", type=int, default=3, help="walkers per world, each with a camera")
    parser.add_argument("--resolution", type=int, default=64, help="view size in pixels")
    parser.add_argument("--steps", type=int, default=40, help="steps per renderer in the timing")
    parser.add_argument("--seed", type=int, default=0, help="seed of the walks")
    args = parser.parse_args()

    # The walk is a few dozen ops on tiny tensors: on one thread they leave the cores to the
    # rasteriser (with torch's default pool they met its threads and ran 100x slower here).
    torch.set_num_threads(1)
    character = mr.skinned_character()
    W, A = args.worlds, args.agents
    hue = torch.arange(A) / A * 2 * math.pi
    colors = torch.stack((0.55 + 0.4 * torch.cos(hue), 0.55 + 0.4 * torch.cos(hue - 2.1),
                          0.55 + 0.4 * torch.cos(hue + 2.1)), -1)
    colors = colors.expand(W, A, 3)
    skinned = mr.BatchRenderer(make_scene(W, A, args.resolution, character))
    rigid = mr.BatchRenderer(make_scene(W, A, args.resolution, character.rigid()))
    for renderer in (skinned, rigid):
        renderer.update("walkers", active=torch.ones(W, A, dtype=torch.bool), color=colors)

    walk = Walk(W, A, character, args.seed)
    for _ in range(8):  # get everyone moving
        walk.step(walk.random_actions())
    skinned.update("walkers", **walk.instance_update())
    views = skinned.render().rgb  # [W, A, H, W, 3]
    path = os.path.join(args.out, "skinned_walkers.png")
    overview_picture(walk, colors, views, path)
    print("wrote", path, tuple(views.shape))

    if args.steps > 0:
        rates = {"skinned": [], "rigid": []}
        block = max(args.steps // 8, 1)
        for renderer, name in ((skinned, "skinned"), (rigid, "rigid")):
            views_per_s(renderer, walk, name == "skinned", 2)  # warm-up: shaders compile on the first draw
        for _ in range(args.steps // block):  # alternate, so that both see the same machine load
            for renderer, name in ((skinned, "skinned"), (rigid, "rigid")):
                rates[name].append(views_per_s(renderer, walk, name == "skinned", block))
        skinned_rate, rigid_rate = (float(np.median(rates[k])) for k in ("skinned", "rigid"))
        # per block pair: both renderers ran one block each in every round
        ratio = float(np.median([s / r for s, r in zip(rates["skinned"], rates["rigid"], strict=True)]))
        print(f"throughput ({W * A} views of {args.resolution}x{args.resolution}, walk + pack + render; medians of "
              f"{len(rates['rigid'])} alternating blocks): skinned {skinned_rate:,.0f} views/s, "
              f"rigid {rigid_rate:,.0f} views/s, skinned / rigid = {ratio:.2f}")
    skinned.close()
    rigid.close()


if __name__ == "__main__":
    main()
