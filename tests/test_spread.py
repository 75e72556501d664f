"""Spread (cooperative navigation): egocentric views, egocentric actions, shared reward."""
from __future__ import annotations

import math

import torch

from marl_render.envs import make_env, scenery
from marl_render.envs.egomotion import ACTION_MEANINGS
from marl_render.envs.spread import AGENT_RADIUS, ARENA, Spread

NOOP, FORWARD, LEFT, RIGHT, BACK = range(5)


def make(**kw):
    kw.setdefault("num_worlds", 2)
    kw.setdefault("resolution", 32)
    kw.setdefault("seed", 0)
    return make_env("spread", **kw)


def place(env, pos, yaw, landmarks=None):
    """Put the bodies of every world where we want them, at rest (through get_state / set_state)."""
    W = env.num_worlds
    state = env.get_state()
    state["pos"] = torch.as_tensor(pos, dtype=torch.float32).expand(W, -1, -1).clone()
    state["vel"] = torch.zeros_like(state["vel"])
    state["yaw"] = torch.as_tensor(yaw, dtype=torch.float32).expand(W, -1).clone()
    if landmarks is not None:
        state["landmarks"] = torch.as_tensor(landmarks, dtype=torch.float32).expand(W, -1, -1).clone()
    env.set_state(state)


def noop(env):
    return env.step(torch.full((env.num_worlds, env.num_agents), NOOP))


def agent_pixels(pixels):
    """[..., H, W] bool: pixels showing an agent body (the team's blue)."""
    rgb = pixels.int()
    return (rgb[..., 2] > 2 * rgb[..., 0]) & (rgb[..., 2] > rgb[..., 1]) & (rgb[..., 2] > 50)


def test_defaults():
    env = make()
    assert isinstance(env.scenario, Spread)
    assert env.num_agents == 3 and env.scenario.num_landmarks == 3 and env.max_steps == 100
    assert env.agent_names == ["agent_0", "agent_1", "agent_2"] and env.groups == {"agents": env.agent_names}
    assert env.num_actions == 5 and len(ACTION_MEANINGS) == 5
    assert env.state_dim == 6 + 2 * 3 + 2 * 2
    env.close()
    env = make(num_agents=4, num_landmarks=2, continuous=True)
    assert env.action_dim == 2 and env.state_dim == 6 + 4 + 6
    env.close()


def test_views_are_egocentric_and_differ_between_agents():
    env = make(num_agents=4)
    obs = env.reset()
    pixels = obs["pixels"].int()
    for w in range(2):
        for i in range(4):
            for j in range(i + 1, 4):
                assert (pixels[w, i] - pixels[w, j]).abs().float().mean() > 1.0
    env.close()


def dark_pixels(pixels):
    """[..., H, W] bool: the near-black noses."""
    return pixels.int().amax(-1) < 40


def test_own_body_is_hidden_from_own_view():
    env = make(resolution=48)
    env.reset()
    # Agent 0 at the origin facing +Y; agent 1 straight ahead (facing away); agent 2 behind agent 0.
    place(env, [[0.0, 0.0], [0.0, 0.8], [0.0, -0.8]], [0.0, 0.0, 0.0],
          landmarks=[[1.0, -1.0], [1.1, -1.1], [1.2, -1.2]])
    pixels = noop(env)[0]["pixels"]
    seen = agent_pixels(pixels).float().mean((-1, -2))  # fraction of each view [W, A]
    assert bool((seen[:, 0] > 0.01).all()), seen  # agent 0 sees agent 1 ahead
    assert bool((seen[:, 2] > 0.01).all()), seen  # agent 2 sees agent 0 ahead
    assert bool((seen[:, 1] == 0).all()), seen  # agent 1 sees nobody ahead and not its own body
    # Every nose faces away from every camera, and each agent's own nose (right in front of
    # its camera, it would cover a fifth of the view) is hidden from its own view.
    assert int(dark_pixels(pixels).sum()) == 0
    # Agent 1 turns around: now it sees the others, and agents 0 and 1 see each other's nose;
    # agent 2 still sees only agent 0's back.
    place(env, [[0.0, 0.0], [0.0, 0.8], [0.0, -0.8]], [0.0, math.pi, 0.0])
    pixels = noop(env)[0]["pixels"]
    seen = agent_pixels(pixels).float().mean((-1, -2))
    assert bool((seen[:, 1] > 0.01).all()), seen
    assert bool((dark_pixels(pixels[:, :2]).sum((-1, -2)) > 0).all())
    assert int(dark_pixels(pixels[:, 2]).sum()) == 0
    env.close()


def test_egocentric_actions():
    env = make(num_agents=3)
    env.reset()
    place(env, [[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0]], [0.0, math.pi / 2, 0.0])
    yaw0 = env.sim.yaw.clone()
    env.step(torch.tensor([[FORWARD, FORWARD, LEFT]] * 2))
    pos = env.sim.pos
    assert bool((pos[:, 0, 1] > 0.01).all()) and bool((pos[:, 0, 0].abs() < 1e-6).all())  # +Y
    assert bool((pos[:, 1, 0] < -1.01).all())  # yaw pi/2 faces -X
    assert bool((env.sim.yaw[:, 2] > yaw0[:, 2]).all())  # left turn increases yaw
    assert bool((pos[:, 2] == torch.tensor([1.0, 0.0])).all())  # turning does not move
    env.step(torch.tensor([[BACK, RIGHT, NOOP]] * 2))
    assert bool((env.sim.yaw[:, 1] < math.pi / 2 + 1e-6).all())
    env.close()


def test_continuous_actions_thrust_and_turn():
    env = make(continuous=True)
    env.reset()
    place(env, [[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0]], [0.0, 0.0, 0.0])
    a = torch.tensor([[[1.0, 0.0], [-1.0, 0.0], [0.0, -0.5]]] * 2)
    env.step(a)
    assert bool((env.sim.pos[:, 0, 1] > 0).all()) and bool((env.sim.pos[:, 1, 1] < 0).all())
    assert torch.allclose(env.sim.yaw[:, 2], torch.tensor(-0.5 * 3.0 * 0.1))
    env.close()


def test_walls_keep_agents_inside():
    env = make()
    env.reset()
    for _ in range(40):
        env.step(torch.full((2, 3), FORWARD))
    limit = ARENA - AGENT_RADIUS + 1e-5
    assert float(env.sim.pos.abs().max()) <= limit
    env.close()


def test_reward_is_shared_coverage_minus_collisions():
    env = make(state_obs=True)
    env.reset()
    # Agents 0 and 1 touch; each agent sits on one landmark except agent 2 (0.5 m off).
    place(env, [[0.0, 0.0], [0.29, 0.0], [-1.0, -1.0]], [0.0, 0.0, 0.0],
          landmarks=[[0.0, 0.0], [0.29, 0.0], [-1.0, -0.5]])
    _, reward, _, _, info = noop(env)
    pos = env.sim.pos
    coverage = torch.cdist(env.sim.landmarks, pos).amin(-1).sum(-1)
    assert torch.allclose(info["coverage"], coverage)
    assert info["collisions"].tolist() == [1, 1]
    assert torch.allclose(reward, (-coverage - 1.0)[:, None].expand(2, 3))
    assert torch.allclose(reward[:, 0], torch.tensor(-1.5), atol=0.05)
    # Apart: no collision penalty.
    place(env, [[0.0, 0.0], [0.6, 0.0], [-1.0, -1.0]], [0.0, 0.0, 0.0])
    _, reward, _, _, info = noop(env)
    assert info["collisions"].tolist() == [0, 0]
    env.close()


def test_state_observation_contents():
    env = make(state_obs=True, num_worlds=1)
    env.reset()
    place(env, [[0.5, 0.0], [-1.0, 0.0], [1.0, 1.0]], [0.3, 0.0, 0.0],
          landmarks=[[0.0, 1.0], [0.5, 0.5], [1.0, 0.0]])
    obs = noop(env)[0]
    state = obs["state"][0, 0]
    assert torch.allclose(state[:2], torch.tensor([0.5, 0.0]))
    assert torch.allclose(state[2:4], torch.zeros(2))
    assert torch.allclose(state[4:6], torch.tensor([math.cos(0.3), math.sin(0.3)]))
    assert torch.allclose(state[6:12], torch.tensor([-0.5, 1.0, 0.0, 0.5, 0.5, 0.0]))
    assert torch.allclose(state[12:16], torch.tensor([-1.5, 0.0, 0.5, 1.0]))
    env.close()


def test_landmarks_have_distinct_colours_from_agents():
    env = make(num_agents=6)
    colors = env.scenario.instances(env.sim, full=True)["landmarks"]["color"][0]
    assert len({tuple(c.tolist()) for c in colors}) == 6
    assert not any(torch.allclose(c, torch.tensor(scenery.TEAM_COLORS["agents"])) for c in colors)
    env.close()
