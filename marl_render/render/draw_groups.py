"""The GL side of the mesh groups: each group's node in every framebuffer, its buffer textures (the
packer's destinations, PandaTargets) and how many of its visible pairs each pass draws."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .panda_buffers import TextureMemory, int_input


@dataclass
class DrawGroup:
    """GL side of one group: its nodes (one per framebuffer), instance data and visible pairs.
    The renderer hands these to its other passes (the shadow pass draws the same nodes and
    instance textures); culling is the packer's, for every pass."""

    node: object  # the node drawn in the first framebuffer (the others are copies of it)
    count: int  # instances per world (static: in total)
    static: bool
    instances: object  # float32 buffer texture (packing.py writes it)
    pairs: object  # int32 buffer texture: visible view * count + instance
    pass_nodes: list | None = None  # [(NodePath, PTA_int pair offset, instance count drawn)] per pass
    plain_nodes: list | None = None  # the same for the variant without patterns (packing.py: plain_counts)


class PandaTargets:
    """The packer's destinations (packing.PackTargets): the RAM images of the buffer
    textures, each marked for upload when the packer asks for it (views made once:
    panda_buffers.TextureMemory says why)."""

    def __init__(self, groups: dict):
        self.groups = groups  # the renderer's draw groups by name, filled as they are built
        self.views_texture = None
        self.appearance_texture = None  # the "appearance" effect's rows, one per world
        self._memory: dict[tuple, TextureMemory] = {}

    def views(self) -> torch.Tensor:
        return self._view(("views",), self.views_texture, np.float32)

    def instances(self, group: str) -> torch.Tensor:
        return self._view(("instances", group), self.groups[group].instances, np.float32)

    def pairs(self, group: str) -> torch.Tensor:
        return self._view(("pairs", group), self.groups[group].pairs, np.int32)

    def appearance(self) -> torch.Tensor:
        return self._view(("appearance",), self.appearance_texture, np.float32)

    def _view(self, key: tuple, texture, dtype) -> torch.Tensor:
        view = self._memory.get(key)
        if view is None or view.texture is not texture:
            view = self._memory[key] = TextureMemory(texture, dtype)
        return view()

    def release(self) -> None:
        for view in self._memory.values():
            view.release()
        self._memory.clear()


def per_pass(node, passes: list, batch: int | None = None) -> list:
    """One copy of the node in every framebuffer (they share the geometry), each with its own pair
    offset and instance count: [[NodePath, PTA_int pair offset, pairs drawn, PTA_int pair count]] per
    pass. batch (impostor groups): each GL instance draws `batch` pairs (impostors.quad_node), the last
    one only up to the pair count (a shader input then)."""
    entries = []
    for index, render_pass in enumerate(passes):
        if index == 0:
            node.reparent_to(render_pass.root)
        copy = node if index == 0 else node.copy_to(render_pass.root)
        offset = int_input(0)  # updated in place (a new PTA would make a new render state)
        copy.set_shader_input("pair_offset", offset)
        pair_count = None
        if batch is not None:
            pair_count = int_input(0)
            copy.set_shader_input("pair_count", pair_count)
        entries.append([copy, offset, None, pair_count, batch or 1])
    return entries


def set_draw(entry: list, first: int, count: int) -> None:
    """Point a pass's node (entry of DrawGroup.pass_nodes) at `count` pairs from `first`."""
    node, offset, drawn, pair_count, batch = entry
    offset[0] = first
    if count == drawn:
        return
    if count == 0:  # Panda3D would draw an instance count of 0 once
        node.hide()
    else:
        if not drawn:
            node.show()
        if pair_count is not None:
            pair_count[0] = count
        node.set_instance_count(-(-count // batch))
    entry[2] = count
