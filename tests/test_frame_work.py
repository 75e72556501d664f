"""A frame does only the work whose inputs changed, and skipping it never changes a pixel."""
import torch

import marl_render as mr
from marl_render.packing import CULL_RECHECK

BACKGROUND = (0.2, 0.4, 0.6)
BACKGROUND_U8 = torch.tensor([round(c * 255) for c in BACKGROUND], dtype=torch.uint8)
RED, GREEN = torch.tensor([255, 0, 0], dtype=torch.uint8), torch.tensor([0, 255, 0], dtype=torch.uint8)


def two_boxes(mounted=False):
    """1 world, 2 agents, boxes 'a' (2, in front of the cameras) and 'b' (1); 32x32, unlit."""
    scene = mr.Scene(num_worlds=1, agents_per_world=2, resolution=32, effects=(), background=BACKGROUND)
    scene.add_group("a", "box", capacity=2)
    scene.add_group("b", "box", capacity=1)
    if mounted:
        scene.mount_cameras("b", [0, 0])
    renderer = mr.BatchRenderer(scene)
    if not mounted:
        renderer.set_cameras(position=torch.zeros(1, 2, 3), rotation=torch.tensor([1.0, 0, 0, 0]).repeat(1, 2, 1))
    renderer.update("a", position=[[[-0.6, 3.0, 0.0], [0.6, 3.0, 0.0]]], color=[[[1.0, 0, 0], [0, 1.0, 0]]],
                    active=[[True, True]])
    renderer.update("b", position=[[[0.0, -3.0, 0.0]]], active=[[True]])
    return renderer


def stamps(renderer):
    textures = {"views": renderer.views_texture}
    textures.update({f"pairs:{name}": draw.pairs for name, draw in renderer._groups.items()})
    textures.update({f"instances:{name}": draw.instances for name, draw in renderer._groups.items()})
    return {name: texture.get_image_modified() for name, texture in textures.items()}


def changed(before, after):
    return sorted(name for name in before if before[name] != after[name])


def test_a_frame_with_nothing_changed_packs_and_culls_nothing():
    with two_boxes() as renderer:
        first = renderer.render().rgb
        before = stamps(renderer)
        second = renderer.render().rgb
        assert changed(before, stamps(renderer)) == []
        assert torch.equal(first, second)


def test_free_cameras_are_packed_only_when_set():
    with two_boxes() as renderer:
        renderer.render()
        before = stamps(renderer)
        renderer.update("a", position=[[[-0.6, 3.0, 0.2], [0.6, 3.0, 0.2]]])
        renderer.render()
        # Only the moved group is packed and culled again; the views stay as they were.
        assert changed(before, stamps(renderer)) == ["instances:a", "pairs:a"]
        before = stamps(renderer)
        renderer.set_cameras(position=torch.tensor([[[0.0, 0.5, 0.0], [0.0, 0.5, 0.0]]]))
        renderer.render()
        assert "views" in changed(before, stamps(renderer))


def test_mounted_cameras_are_packed_when_their_bodies_move():
    with two_boxes(mounted=True) as renderer:
        renderer.render()
        before = stamps(renderer)
        renderer.update("a", color=[[[0.0, 0, 1.0], [0, 1.0, 0]]])
        renderer.render()
        assert "views" not in changed(before, stamps(renderer))
        renderer.update("b", position=[[[0.0, -1.0, 0.0]]])
        renderer.render()
        assert "views" in changed(before, stamps(renderer))


def test_culling_pauses_where_it_removes_nothing_and_masks_still_apply():
    with two_boxes() as renderer:
        renderer.update("b", position=[[[0.0, 3.0, 0.8]]], scale=[[[0.3, 0.3, 0.3]]])
        renderer.render()
        # Everything is in view: the next frames draw the candidate pairs without frustum tests.
        assert renderer.packer.groups["a"].frustum_pause == CULL_RECHECK
        renderer.update("a", position=[[[-0.6, 3.0, 0.0], [0.6, 3.0, 0.0]]])
        image = renderer.render().rgb[0, 0]
        assert renderer.packer.groups["a"].frustum_pause == CULL_RECHECK - 1
        assert torch.equal(image[16, 8], RED) and torch.equal(image[16, 23], GREEN)
        # Deactivating an instance while paused takes effect in the same frame ...
        renderer.update("a", active=[[True, False]])
        image = renderer.render().rgb[0, 0]
        assert torch.equal(image[16, 8], RED) and torch.equal(image[16, 23], BACKGROUND_U8)
        assert renderer.packer.groups["a"].pass_ranges == [(0, 2)]  # one pair per view
        # ... and so does an owner: agent 1's own box is hidden from agent 1 only.
        renderer.update("a", active=[[True, True]], owner=[[-1, 1]])
        frame = renderer.render().rgb[0]
        assert torch.equal(frame[0, 16, 23], GREEN) and torch.equal(frame[1, 16, 23], BACKGROUND_U8)
        assert renderer.packer.groups["a"].pass_ranges == [(0, 3)]


def test_culling_removes_what_no_view_can_see():
    with two_boxes() as renderer:
        renderer.render()
        # Box b sits behind both cameras: it is culled from both views, and culling stays on.
        assert renderer.packer.groups["b"].pass_ranges == [(0, 0)]
        assert renderer.packer.groups["b"].frustum_pause == 0
        renderer.update("b", position=[[[0.0, -3.5, 0.0]]])
        renderer.render()
        assert renderer.packer.groups["b"].pass_ranges == [(0, 0)]
