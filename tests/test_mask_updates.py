"""The packer lists a group's candidate pairs again only when its active or owner mask changed
(envs pass both every step); the frame follows every change."""
import torch

import marl_render as mr

RED = (0.9, 0.1, 0.1, 1.0)


def _renderer():
    scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=16, effects=("lighting", "segmentation"))
    scene.add_group("boxes", "box", capacity=2)
    renderer = mr.BatchRenderer(scene)
    renderer.update("boxes", position=torch.tensor([[(-0.6, 0.0, 1.0), (0.6, 0.0, 1.0)]] * 2, dtype=torch.float64),
                    color=torch.tensor(RED).expand(2, 2, 4), active=torch.ones(2, 2, dtype=torch.bool))
    renderer.set_cameras(position=torch.tensor([[(0.0, -4.0, 1.0)]] * 2, dtype=torch.float64),
                         look_at=torch.tensor([[(0.0, 0.0, 1.0)]] * 2, dtype=torch.float64))
    return renderer, scene.groups["boxes"].segment_base


def test_unchanged_masks_keep_the_candidates_and_changed_ones_redraw():
    renderer, base = _renderer()
    try:
        both = renderer.render().segmentation.clone()
        assert set(both[0, 0].unique().tolist()) >= {base, base + 1}
        renderer.update("boxes", active=torch.ones(2, 2, dtype=torch.bool), owner=torch.full((2, 2), -1))
        assert "boxes" not in renderer.packer._mask_dirty  # the same masks again: nothing to list again
        assert torch.equal(renderer.render().segmentation, both)
        renderer.update("boxes", active=torch.tensor([[True, False], [True, True]]))
        assert "boxes" in renderer.packer._mask_dirty
        frame = renderer.render().segmentation
        assert base + 1 not in frame[0, 0].unique().tolist() and torch.equal(frame[1], both[1])
        renderer.update("boxes", owner=torch.tensor([[-1, -1], [0, -1]]))  # world 1's viewer owns box 0
        assert "boxes" in renderer.packer._mask_dirty
        frame = renderer.render().segmentation
        assert base not in frame[1, 0].unique().tolist() and base + 1 in frame[1, 0].unique().tolist()
    finally:
        renderer.close()
