"""Tests for envs/push.py: two teams push a ball into the other team's goal."""

import math

import pytest
import torch

from marl_render.envs import list_envs, make_env, push

W, RES = 3, 32


def make(**kwargs):
    kwargs = {"num_worlds": W, "resolution": RES, "seed": 0, **kwargs}
    return make_env("push", **kwargs)


def noop(env):
    if env.continuous:
        return torch.zeros(env.num_worlds, env.num_agents, 2)
    return torch.zeros(env.num_worlds, env.num_agents, dtype=torch.long)


def place(env, agents, ball, ball_vel=(0.0, 0.0), yaw=None, agent_vel=None):
    """Agents at `agents` [W, N, 2] (moving at agent_vel, else at rest) and the ball at `ball` [W, 2]
    with `ball_vel`, through get_state / set_state."""
    N = env.num_agents
    state = env.get_state()
    agents = torch.as_tensor(agents, dtype=torch.float32).expand(W, N, 2)
    ball = torch.as_tensor(ball, dtype=torch.float32).expand(W, 2)
    state["pos"] = torch.cat((agents, ball[:, None]), 1).clone()
    state["vel"] = torch.zeros_like(state["pos"])
    state["vel"][:, -1] = torch.as_tensor(ball_vel, dtype=torch.float32)
    if agent_vel is not None:
        state["vel"][:, :-1] = agent_vel
    if yaw is not None:
        state["yaw"] = torch.as_tensor(yaw, dtype=torch.float32).expand(W, N).clone()
    env.set_state(state)


SIDELINE = [[-1.2, -0.3], [1.2, -0.3], [-1.2, 0.3], [1.2, 0.3]]  # 4 agents out of the ball's way


# --------------------------------------------------------------------------- contract
# Observation, reward and done shapes and dtypes: tests/test_envs_core.py checks them for every env.
def test_teams_state_size_and_info():
    env = make(state_obs=True)
    N = env.num_agents
    assert N == 4 and env.groups == {"red": ["red_0", "red_1"], "blue": ["blue_0", "blue_1"]}
    assert env.state_dim == 10 + 2 * (N - 1)
    obs = env.reset(seed=1)
    assert obs["action_mask"].all()
    _, _, _, _, info = env.step(env.random_actions(torch.Generator().manual_seed(0)))
    assert info["goal"].shape == (W,) and info["goal"].dtype == torch.int64
    env.close()


def test_team_sizes_and_registry():
    assert "push" in list_envs()
    env = make_env("push", num_worlds=1, resolution=8, num_agents=6)
    assert isinstance(env.scenario, push.Push)
    assert env.groups == {"red": [f"red_{i}" for i in range(3)], "blue": [f"blue_{i}" for i in range(3)]}
    env.close()
    env = make(num_agents=2, resolution=8)
    assert env.groups == {"red": ["red_0"], "blue": ["blue_0"]}
    env.close()
    with pytest.raises(ValueError, match="even"):
        make(num_agents=3)
    with pytest.raises(ValueError, match="goal_reward"):
        make(goal_reward=0.0)


def test_reset_layout():
    env = make(num_worlds=32, num_agents=12)
    env.reset(seed=6)
    agents, ball = env.sim.pos[:, :-1], env.sim.pos[:, -1]
    assert (agents[:, :6, 1] < -0.4).all() and (agents[:, 6:, 1] > 0.4).all()  # own halves
    assert (ball.abs() <= torch.tensor([0.3, 0.1])).all() and (env.sim.vel == 0).all()
    gaps = torch.cdist(env.sim.pos, env.sim.pos) + torch.eye(13) * 9
    assert (gaps >= 2 * push.AGENT_RADIUS).all()  # nobody overlaps at the start
    facing = push.scenery.heading(env.sim.yaw)[..., 1]
    assert (facing[:, :6] > 0.8).all() and (facing[:, 6:] < -0.8).all()  # facing the opponents' goal
    env.close()


# --------------------------------------------------------------------------- goals
def test_goal_scored_rewards_the_right_team_and_ends_the_episode():
    env = make()
    env.reset(seed=0)
    # World 0: the ball rolls into blue's goal (+y): red scores. World 1: into red's goal
    # (-y): blue scores. World 2: into the +y end wall beside the goal mouth: nothing.
    ball = torch.tensor([[0.0, 1.62], [0.1, -1.62], [1.0, 1.62]])
    ball_vel = torch.tensor([[0.0, 1.5], [0.0, -1.5], [0.0, 1.5]])
    place(env, SIDELINE, ball, ball_vel)
    obs, reward, terminated, truncated, info = env.step(noop(env))
    assert info["goal"].tolist() == [1, -1, 0]
    assert reward.tolist() == [[1.0, 1.0, -1.0, -1.0], [-1.0, -1.0, 1.0, 1.0], [0.0] * 4]
    assert terminated.tolist() == [[True] * 4, [True] * 4, [False] * 4]
    assert info["done_worlds"].tolist() == [True, True, False] and not truncated.any()
    assert env.sim.pos[2, -1, 1] > push.GOAL_LINE  # deep enough, but outside the mouth
    # Terminated worlds stay over (no autoreset): rewards 0, still terminated.
    _, reward, terminated, _, _ = env.step(noop(env))
    assert (reward[:2] == 0).all() and terminated[:2].all()
    env.close()


def test_goal_with_autoreset_starts_a_new_episode():
    env = make(autoreset=True, goal_reward=2.0)
    env.reset(seed=0)
    place(env, SIDELINE, torch.tensor([[0.0, 1.62], [0.0, 0.0], [0.0, 0.0]]), torch.tensor([[0.0, 1.5]] * 3))
    _, reward, terminated, _, info = env.step(noop(env))
    assert reward[0].tolist() == [2.0, 2.0, -2.0, -2.0] and terminated[0].all()
    assert info["done_worlds"].tolist() == [True, False, False]
    assert env.step_count.tolist() == [0, 1, 1] and env.alive.all()
    assert env.sim.pos[0, -1].abs().max() <= 0.3 and (env.sim.vel[0] == 0).all()
    env.close()


def test_ball_is_pushed_by_an_agent():
    env = make(continuous=True)
    env.reset(seed=0)
    agents = torch.tensor(SIDELINE)
    agents[0] = torch.tensor([0.0, -0.5])  # red_0 right behind the ball, facing +y
    place(env, agents, torch.tensor([0.0, -0.2]), yaw=torch.zeros(W, 4))
    actions = torch.zeros(W, 4, 2)
    actions[:, 0, 0] = 1.0
    for _ in range(8):
        env.step(actions)
    ball, ball_vel = env.sim.pos[:, -1], env.sim.vel[:, -1]
    assert (ball[:, 1] > 0.2).all() and (ball_vel[:, 1] > 0.3).all()
    assert torch.allclose(ball[:, 0], torch.zeros(W), atol=1e-4)
    env.close()


def test_shaping_is_zero_sum_and_follows_the_ball():
    env = make(shaping=1.0)
    env.reset(seed=0)
    place(env, SIDELINE, torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]),
          torch.tensor([[0.0, 1.0], [0.0, -1.0], [0.0, 0.0]]))
    _, reward, _, _, _ = env.step(noop(env))
    assert (reward[0, :2] > 0.05).all() and (reward[1, :2] < -0.05).all() and (reward[2] == 0).all()
    assert torch.allclose(reward[:, :2], -reward[:, 2:])
    assert torch.allclose(reward[0, 0], env.sim.pos[0, -1, 1])
    env.close()


def test_state_obs_is_in_the_team_frame():
    # A configuration symmetric under the 180 degree turn: each red agent sees exactly
    # what its mirrored blue counterpart sees.
    env = make(state_obs=True)
    env.reset(seed=0)
    a = torch.tensor([[-0.7, -0.9], [0.4, -0.3]])
    yaw = torch.tensor([0.3, -1.0, 0.3 + math.pi, -1.0 + math.pi])
    place(env, torch.cat((a, -a)), torch.tensor([0.0, 0.0]), yaw=yaw,
          agent_vel=torch.tensor([[0.2, 0.1], [0.0, -0.3], [-0.2, -0.1], [0.0, 0.3]]))
    state = env.state_observation()
    assert torch.allclose(state[:, :2], state[:, 2:], atol=1e-6)
    # red's own frame is the world frame.
    assert torch.allclose(state[0, 0, :6], torch.tensor([-0.7, -0.9, 0.2, 0.1, math.cos(0.3), math.sin(0.3)]))
    assert torch.allclose(state[0, 0, 6:8], torch.tensor([0.7, 0.9]))  # ball relative to the agent
    assert torch.allclose(state[0, 0, 10:12], torch.tensor([1.1, 0.6]))  # teammate first
    env.close()


# --------------------------------------------------------------------------- state handling
# Determinism, partial resets, bad actions and declared physics terms: tests/test_envs_core.py
# runs them for every env.
