"""Flat-shaded meshes drawn from shared corners give the pixels of the full mesh."""
import numpy as np
import pytest
import torch

import marl_render as mr
from marl_render.provoking import shared_corner_mesh


def face_normals(mesh):
    a, b, c = (mesh.positions[mesh.triangles[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    return normal / np.linalg.norm(normal, axis=1, keepdims=True)


def test_a_box_needs_its_8_corners_with_each_face_normal_on_the_last_vertex():
    box = mr.box()
    corners = shared_corner_mesh(box)
    assert corners.positions.shape == (8, 3) and corners.triangles.shape == (12, 3)
    # Same triangles in space, wound the same way, each ending on a corner with its normal.
    assert np.allclose(face_normals(corners), face_normals(box), atol=1e-6)
    assert np.allclose(corners.normals[corners.triangles[:, 2]], face_normals(box), atol=1e-6)
    assert np.allclose(np.sort(corners.positions[corners.triangles].reshape(12, 9).sum(1)),
                       np.sort(box.positions[box.triangles].reshape(12, 9).sum(1)))


def test_smooth_meshes_are_refused():
    with pytest.raises(ValueError, match=r"mesh 'sphere' is not flat-shaded"):
        shared_corner_mesh(mr.sphere())


def test_renderer_draws_the_same_pixels_from_corners_as_from_24_vertex_boxes():
    """A white texture keeps the 24-vertex box (UVs differ per face) and changes no colour."""
    generator = torch.Generator().manual_seed(3)
    W, A, C = 2, 2, 6
    position = torch.rand(W, C, 3, generator=generator) * 4 - 2
    position[..., 1] += 4
    pose = dict(position=position, rotation=torch.randn(W, C, 4, generator=generator),
                scale=torch.rand(W, C, 3, generator=generator) + 0.3, color=torch.rand(W, C, 3, generator=generator),
                active=torch.ones(W, C, dtype=torch.bool))
    frames = []
    for texture in (None, np.full((1, 1, 3), 255, np.uint8)):
        effects = ("lighting", "segmentation") + (("texture",) if texture is not None else ())
        scene = mr.Scene(num_worlds=W, agents_per_world=A, resolution=(40, 56), effects=effects)
        scene.add_group("boxes", "box", capacity=C, texture=texture)
        with mr.BatchRenderer(scene) as renderer:
            renderer.update("boxes", **pose)
            renderer.set_cameras(position=torch.tensor([[[-1.0, 0, 1], [1.0, 0, 0.5]]]).repeat(W, 1, 1),
                                 look_at=torch.tensor([0.0, 4, 0]).repeat(W, A, 1))
            frames.append(renderer.render())
            drawn = renderer._groups["boxes"].node.node().get_geom(0).get_vertex_data().get_num_rows()
            assert drawn == (8 if texture is None else 24)
    assert torch.equal(frames[0].rgb, frames[1].rgb)
    assert torch.equal(frames[0].segmentation, frames[1].segmentation)
    assert len(frames[0].segmentation.unique()) > 3  # several boxes in view
