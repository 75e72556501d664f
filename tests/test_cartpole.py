"""CartPoleBalance: dm_control dynamics and reward, pixels that follow the cart."""
from __future__ import annotations

import math

import pytest
import torch

from marl_render.envs import make_env
from marl_render.envs.cartpole import FORCE_LEVELS, CartPoleBalance
from marl_render.envs.cartpole_dynamics import CARTPOLE, SLIDER_LIMIT, cartpole_step, slider_limit
from marl_render.envs.dmc_rewards import dmc_balance_reward


def make(**kw):
    kw.setdefault("num_worlds", 3)
    kw.setdefault("resolution", 32)
    kw.setdefault("seed", 0)
    return make_env("cartpole", **kw)


def test_defaults_follow_dm_control():
    env = make()
    assert isinstance(env.scenario, CartPoleBalance)
    assert env.max_steps == 1000 and env.num_agents == 1 and env.agent_names == ["agent_0"]
    assert env.num_actions == len(FORCE_LEVELS) and env.physics_terms == frozenset()
    assert env.state_dim == 5
    env.close()
    assert make_env("cartpole").resolution == (64, 64)


def test_reset_distribution_matches_balance_task():
    env = make(num_worlds=256)
    env.reset()
    x, theta, xdot, thetadot = env.sim.qstate.unbind(-1)
    assert float(x.abs().max()) <= 0.1 and float(x.std()) > 0.03
    assert float(theta.abs().max()) <= 0.034 and float(theta.std()) > 0.01
    assert float(xdot.abs().max()) < 0.05 and float(thetadot.abs().max()) < 0.05
    env.close()


@pytest.mark.parametrize("continuous", [False, True])
def test_dynamics_and_reward_agree_with_physics_functions(continuous):
    env = make(continuous=continuous, state_obs=True)
    env.reset()
    g = torch.Generator().manual_seed(5)
    for _ in range(20):
        if continuous:
            actions = torch.rand(3, 1, 1, generator=g) * 2 - 1
            u = actions[:, 0, 0].double()
        else:
            actions = torch.randint(0, env.num_actions, (3, 1), generator=g)
            u = torch.tensor(FORCE_LEVELS, dtype=torch.float64)[actions[:, 0]]
        before = env.sim.qstate
        obs, reward, terminated, truncated, _ = env.step(actions)
        expected = cartpole_step(before, u)
        assert torch.equal(env.sim.qstate, expected)  # no slider stop in this range
        assert torch.allclose(reward[:, 0], dmc_balance_reward(expected, u).float())
        x, theta, xdot, thetadot = expected.unbind(-1)
        state = torch.stack((x, torch.cos(theta), torch.sin(theta), xdot, thetadot), -1).float()
        assert torch.allclose(obs["state"][:, 0], state)
        assert not bool(terminated.any()) and not bool(truncated.any())
        assert float(reward.min()) >= 0 and float(reward.max()) <= 1
    env.close()


def test_balanced_pole_earns_high_reward_fallen_pole_low():
    env = make(num_worlds=2)
    env.reset()
    state = env.get_state()
    state["qstate"] = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, math.pi, 0.0, 0.0]], dtype=torch.float64)
    env.set_state(state)
    _, reward, _, _, _ = env.step(torch.full((2, 1), FORCE_LEVELS.index(0.0)))
    assert float(reward[0, 0]) > 0.99 and float(reward[1, 0]) < 0.01
    env.close()


def test_slider_stop_keeps_cart_on_the_rail():
    q = torch.tensor([[1.85, 0.1, 2.0, 0.5], [-1.9, 0.0, -1.0, 0.0], [1.85, 0.0, -1.0, 0.0]], dtype=torch.float64)
    out = slider_limit(q)
    assert out[:, 0].tolist() == [SLIDER_LIMIT, -SLIDER_LIMIT, SLIDER_LIMIT]
    assert out[0, 2] == 0 and out[1, 2] == 0 and out[2, 2] == -1.0  # moving back in: kept
    p = CARTPOLE
    J = p["pole_inertia"] + p["pole_mass"] * p["pole_com"] ** 2
    assert math.isclose(float(out[0, 3]), 0.5 + p["pole_mass"] * p["pole_com"] * math.cos(0.1) / J * 2.0)
    env = make(num_worlds=1)
    env.reset()
    for _ in range(200):
        env.step(torch.tensor([[len(FORCE_LEVELS) - 1]]))  # full force right
    assert float(env.sim.qstate[0, 0]) <= SLIDER_LIMIT
    env.close()


def cart_centroid(pixels: torch.Tensor) -> torch.Tensor:
    """Column centroid [W] of the orange (cart and pole) pixels in [W, 1, H, W, 3] images."""
    rgb = pixels[:, 0].int()
    orange = (rgb[..., 0] - rgb[..., 2] > 40) & (rgb[..., 0] > rgb[..., 1])
    assert bool((orange.sum((1, 2)) > 3).all()), "the cart is not visible"
    cols = torch.arange(rgb.shape[2]).float()
    return (orange.float() * cols).sum((1, 2)) / orange.float().sum((1, 2))


@pytest.mark.parametrize("direction", [+1, -1])
def test_cart_pixels_follow_the_cart(direction):
    env = make(num_worlds=2, resolution=48)
    obs = env.reset()
    start = cart_centroid(obs["pixels"])
    action = FORCE_LEVELS.index(float(direction))
    for _ in range(25):
        obs = env.step(torch.full((2, 1), action))[0]
    moved = env.sim.qstate[:, 0]
    assert bool((moved * direction > 0.2).all())
    shift = cart_centroid(obs["pixels"]) - start
    assert bool((shift * direction > 2).all()), shift  # pixels, same direction as the cart
    env.close()


def test_camera_is_dm_controls_fixed_side_view():
    env = make(num_worlds=1, resolution=64, depth=True)
    obs = env.reset()
    depth = obs["depth"][0, 0]
    # The cart's front face is 4 - 0.15 m away, straight ahead at the image centre.
    assert abs(float(depth[32, 32]) - 3.85) < 0.1
    # Floor in the lower half, sky (far plane) in the upper corners.
    assert float(depth[-1, 32]) < 6 and float(depth[0, 0]) == env.far
    env.close()
