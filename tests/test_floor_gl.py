"""The independent raw-GL floor (marl_render/bench/floor_gl.py) draws what the envs draw."""
import numpy as np
import pytest
import torch

import marl_render as mr
from marl_render.bench.floor_gl import FloorGL, from_env, shared_corners
from marl_render.envs import make_env

DEFAULT_LIGHTING = mr.Scene(1, 1).lighting  # what lit() compares against: the Scene default


def stepped_env(name, **kwargs):
    env = make_env(name, seed=0, **kwargs)
    env.reset(seed=0)
    generator = torch.Generator().manual_seed(1)
    for _ in range(4):
        obs, *_ = env.step(env.random_actions(generator))
    return env, obs["pixels"]


def lit(color, normal, lighting=DEFAULT_LIGHTING):
    """8-bit colour of a surface with `normal` under the default Lambert lighting."""
    to_light = -np.asarray(lighting.direction) / np.linalg.norm(lighting.direction)
    shade = np.asarray(lighting.ambient) + np.asarray(lighting.color) * max(float(np.dot(normal, to_light)), 0.0)
    return np.round(255 * np.clip(np.asarray(color) * shade, 0, 1)).astype(int)


def assert_same_picture(env_pixels, floor_pixels):
    difference = (env_pixels.int() - floor_pixels.int()).abs()
    assert floor_pixels.shape == env_pixels.shape and floor_pixels.dtype == torch.uint8
    assert float(difference.float().mean()) < 0.05
    assert float((difference.amax(-1) > 2).float().mean()) < 0.002


@pytest.mark.parametrize("tiles, cull", [(256, False), (3, True)])
def test_cartpole_floor_draws_the_env_picture(tiles, cull):
    from marl_render.envs.cartpole import FLOOR_COLOR, SELF_COLOR, SKY_COLOR

    env, pixels = stepped_env("cartpole", num_worlds=8)
    try:
        with from_env(env, tiles_per_framebuffer=tiles, cull=cull) as floor:
            drawn = floor.render()
            assert len(floor._framebuffers) == (1 if tiles == 256 else 3)
            assert_same_picture(pixels, drawn)
            image = drawn[:, 0].int().numpy()
            # Known pixels in every world: sky top left, the lit floor slab bottom centre, the
            # cart's front face (facing the camera, -y) at the image centre.
            assert (image[:, 0, 0] == np.round(255 * np.asarray(SKY_COLOR))).all()
            assert (np.abs(image[:, 63, 32] - lit(FLOOR_COLOR, (0, 0, 1))) <= 1).all()
            assert (np.abs(image[:, 32, 32] - lit(SELF_COLOR, (0, -1, 0))) <= 1).all()
    finally:
        env.close()


@pytest.mark.parametrize("cull", [False, True])
def test_spread_floor_draws_every_agent_view_of_the_env(cull):
    env, pixels = stepped_env("spread", num_worlds=3, num_agents=4)
    try:
        with from_env(env, tiles_per_framebuffer=5, cull=cull) as floor:
            drawn = floor.render()
            assert drawn.shape == (3, 4, 64, 64, 3)
            assert_same_picture(pixels, drawn)
            # Eyes are level with the wall tops: every view's top row is sky.
            sky = torch.tensor(np.round(255 * np.asarray(env.background)), dtype=torch.uint8)
            assert bool((drawn[:, :, 0] == sky).all())
            # Views differ (each agent looks its own way), so tiles were not mixed up.
            assert not torch.equal(drawn[:, 0], drawn[:, 1])
    finally:
        env.close()


@pytest.mark.parametrize("cull", [False, True])
def test_floor_draws_commons_apples_as_impostors_like_the_env(cull):
    """The env draws its apples as impostors (the default): so does the floor, with its own code."""
    env, pixels = stepped_env("commons", num_worlds=2, resolution=32)
    try:
        assert env.renderer.impostor_groups == {"apples"}
        with from_env(env, cull=cull) as floor:
            assert [draw.impostor for draw in floor._draws].count(True) == 1
            assert_same_picture(pixels, floor.render())
        with from_env(env, cull=cull, impostors=False) as meshes:  # the 80-triangle meshes: another picture
            assert not any(draw.impostor for draw in meshes._draws)
            assert not torch.equal(meshes.render(), pixels)
    finally:
        env.close()


@pytest.mark.parametrize("cull", [False, True])
def test_floor_hides_the_viewer_body_and_inactive_instances(cull):
    scene = mr.Scene(1, 2, resolution=16, effects=())
    scene.add_group("boxes", "box", capacity=2)
    with FloorGL(scene, cull=cull) as floor:
        floor.set_cameras(torch.tensor([0.0, -3.0, 0.0]).repeat(1, 2, 1), torch.tensor([1.0, 0, 0, 0]).repeat(1, 2, 1))
        floor.set_instances("boxes", position=torch.zeros(1, 2, 3), color=torch.tensor([[[1.0, 0, 0], [0, 1.0, 0]]]),
                            active=torch.tensor([[True, True]]), owner=torch.tensor([[0, -1]]))
        centre = floor.render()[0, :, 8, 8].tolist()
        assert centre == [[0, 255, 0], [255, 0, 0]]  # view 0 sees through its own red box
        floor.set_instances("boxes", active=torch.tensor([[True, False]]))
        background = np.round(255 * np.asarray(scene.background)).tolist()
        assert floor.render()[0, :, 8, 8].tolist() == [background, [255, 0, 0]]


def test_shared_corners_put_each_face_normal_on_the_provoking_vertex():
    box = mr.box()
    positions, normals, triangles = shared_corners(box)
    assert len(positions) == 8 and triangles.shape == (12, 3)
    a, b, c = (positions[triangles[:, i]] for i in range(3))
    face = np.cross(b - a, c - a)
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    # Counter-clockwise seen from outside (winding kept) and the last vertex carries the face normal.
    assert np.allclose(normals[triangles[:, 2]], face, atol=1e-6)
    assert sorted(map(tuple, np.round(face).astype(int).tolist())) == sorted(
        map(tuple, np.round(box.normals[box.triangles[:, 0]]).astype(int).tolist()))


def test_floor_refuses_skinned_groups():
    scene = mr.Scene(1, 1, resolution=16, effects=())
    scene.add_group("walkers", mr.skinned_limb(), capacity=1)
    with pytest.raises(ValueError, match=r"FloorGL has no skinning; groups \['walkers'\]"):
        FloorGL(scene)


def test_bench_floor_measures_an_env_against_the_floor_with_its_stages():
    from marl_render.bench import floor
    from marl_render.envs import registry

    row = floor.measure("spread", 2, 3, 16, rounds=1, block_seconds=0.01, compile_physics=True)
    assert not row["physics_compiled"]  # spread has no compiled kernel: the flag passes it by
    assert (row["env"], row["worlds"], row["agents"], row["resolution"]) == ("spread", 2, 3, 16)
    assert set(row["stages_ms"]) == {"update", "pack", "cull", "draw", "read", "copy", "physics", "env"}
    assert row["env_ms_per_step"] > 0 and row["floor_ms_per_frame"] > 0
    # ratio is seconds / seconds; the ms fields are each scaled by 1e3 and rounded, so their quotient may
    # differ from it in the last bit (seen in CI): equal to 12 digits, far below any real error.
    assert row["ratio"] == pytest.approx(row["floor_ms_per_frame"] / row["env_ms_per_step"], rel=1e-12, abs=0)
    assert registry.has_compiled_physics("cartpole") and not registry.has_compiled_physics("spread")
    lines = floor.markdown([row, {**row, "env": "cartpole", "physics_compiled": True}])
    assert lines[2].startswith("| spread | 3 | 2 |") and lines[3].startswith("| cartpole (compiled physics) | 3 | 2 |")
