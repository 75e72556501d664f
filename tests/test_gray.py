"""Grayscale observations drawn by the renderer: one channel read back, in either layout."""
import numpy as np
import pytest
import torch

import marl_render as mr
from marl_render.envs import make_env
from marl_render.shaders import GRAY_WEIGHTS


def spread_scene_and_state():
    env = make_env("spread", num_worlds=2, num_agents=3, seed=0)
    env.reset(seed=0)
    state = {name: env.renderer.instance_state(name) for name in env.renderer.scene.groups}
    return env, state


def render(scene, state, **options):
    with mr.BatchRenderer(scene, **options) as renderer:
        for name, kwargs in state.items():
            renderer.update(name, **kwargs)
        return renderer.render().rgb


def test_gray_is_the_luma_of_the_rgb_picture_in_both_layouts():
    env, state = spread_scene_and_state()
    try:
        scene = env.renderer.scene
        rgb = render(scene, state)
        last, first = render(scene, state, color="gray"), render(scene, state, color="gray", channels_first=True)
    finally:
        env.close()
    assert last.shape == (2, 3, 64, 64, 1) and first.shape == (2, 3, 1, 64, 64) and last.dtype == torch.uint8
    assert torch.equal(last.reshape(-1), first.reshape(-1))  # one channel: the same bytes
    luma = rgb.double() @ torch.tensor(GRAY_WEIGHTS, dtype=torch.float64)
    # From the unrounded colour in the shader, so within one step of the luma of the 8-bit RGB.
    assert float((last[..., 0].double() - luma).abs().max()) <= 1.0
    sky = round(255 * float(np.dot(env.background, GRAY_WEIGHTS)))
    assert bool((last[:, :, 0, :, 0] == sky).all())  # the top rows are sky in every view
    assert len(last.unique()) > 10


@pytest.mark.parametrize("options", [{"supersample": 2}, {"readback": "copy"}])
def test_gray_with_supersampling_and_copy_readback(options):
    env, state = spread_scene_and_state()
    try:
        plain = render(env.renderer.scene, state, color="gray")
        other = render(env.renderer.scene, state, color="gray", **options)
    finally:
        env.close()
    assert other.shape == plain.shape
    if "readback" in options:
        assert torch.equal(other, plain)
    else:  # anti-aliased: flat areas keep their value, edges blend
        assert float((other.float() - plain.float()).abs().mean()) < 3.0


def test_unknown_color_is_refused():
    scene = mr.Scene(1, 1, resolution=8)
    with pytest.raises(ValueError, match=r"color must be one of \['rgb', 'gray'\], got 'grey'"):
        mr.BatchRenderer(scene, color="grey")


def test_grayscale_envs_and_wrappers_report_one_channel():
    from torchrl.envs.utils import check_env_specs

    from marl_render.wrappers import make_parallel_env, make_torchrl_env

    with make_env("cartpole", num_worlds=3, grayscale=True, seed=0) as env:
        obs = env.reset(seed=0)
        assert env.pixel_channels == 1 and obs["pixels"].shape == (3, 1, 64, 64, 1)
        obs, *_ = env.step(env.random_actions())
        assert obs["pixels"].shape == (3, 1, 64, 64, 1)
        # The overview stays in colour for people.
        assert env.render_overview().shape[-1] == 3
    with pytest.raises(TypeError, match=r"grayscale must be a bool"):
        make_env("cartpole", grayscale="yes")
    parallel = make_parallel_env("spread", resolution=16, grayscale=True, render_mode="rgb_array")
    observations, _ = parallel.reset(seed=0)
    assert parallel.observation_space("agent_0").shape == (16, 16, 1)
    assert observations["agent_0"].shape == (16, 16, 1)
    assert parallel.render().shape[-1] == 3
    parallel.close()
    torchrl_env = make_torchrl_env("spread", num_worlds=2, resolution=16, grayscale=True)
    data = torchrl_env.reset()
    assert data["agents", "pixels"].shape == (2, 3, 16, 16, 1)
    check_env_specs(torchrl_env)
    torchrl_env.close()
