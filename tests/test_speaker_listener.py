"""speaker_listener: the lamp is the only channel, the goal ring is the speaker's alone, and the rules."""
import math

import pytest
import torch

from marl_render.envs import make_env
from marl_render.envs.evaluation import evaluate, heuristic_policy, random_policy
from marl_render.envs.speaker_listener import REACH

RES = 32


def make(**kwargs):
    kwargs = {"num_worlds": 2, "resolution": RES, "seed": 0, **kwargs}
    return make_env("speaker_listener", **kwargs)


def placed(env, listener, listener_yaw, targets, goal=0, lamp=-1, speaker_yaw=0.0):
    """Set both worlds to the same hand-made state and return the observation of a noop step."""
    state = env.get_state()
    state["pos"][:] = torch.tensor([[0.0, -1.2], listener])
    state["vel"].zero_()
    state["yaw"][:] = torch.tensor([speaker_yaw, listener_yaw])
    state["targets"][:] = torch.tensor(targets)
    state["goal"][:] = goal
    state["lamp"][:] = lamp
    env.set_state(state)
    return env.step(torch.zeros(2, 2, dtype=torch.long))[0]


def colour_pixels(view: torch.Tensor, colour, tolerance=60) -> int:
    """Pixels of `view` [H, W, 3] within `tolerance` of `colour` (0-255) in every channel (shading)."""
    diff = (view.to(torch.int32) - torch.tensor(colour, dtype=torch.int32)).abs()
    return int((diff < tolerance).all(-1).sum())


def hue_pixels(view: torch.Tensor, colour, tolerance=0.04) -> int:
    """Pixels of `view` whose chromaticity (rgb / sum) is within `tolerance` of `colour`'s, whatever
    the shading (a lit sphere is darker on its far side)."""
    rgb = view.to(torch.float32)
    chroma = rgb / rgb.sum(-1, keepdim=True).clamp_min(1)
    want = torch.tensor(colour, dtype=torch.float32)
    return int(((chroma - want / want.sum()).abs() < tolerance).all(-1).sum())


def test_the_lamp_shows_in_the_listeners_view_only_when_lit():
    env = make()
    env.reset()
    far_targets = [[-1.0, 1.2], [0.0, 1.3], [1.0, 1.2]]  # behind the listener, who faces the speaker
    lamp_colour = (env.scenario.colors[1] * 255).tolist()
    dark = placed(env, [0.0, -0.5], math.pi, far_targets, goal=1, lamp=-1)["pixels"][0, 1]
    lit = placed(env, [0.0, -0.5], math.pi, far_targets, goal=1, lamp=1)["pixels"][0, 1]
    assert hue_pixels(dark, lamp_colour) == 0
    assert hue_pixels(lit, lamp_colour) >= 4
    assert bool((lit[: RES // 2] != dark[: RES // 2]).any())  # above the horizon: the lamp on the speaker's head
    env.close()


def test_the_goal_ring_is_hidden_from_the_listener():
    env = make()
    env.reset()
    targets = [[0.0, 0.0], [-1.2, 1.2], [1.2, 1.2]]
    # Both look at target 0 (the goal) from about 0.8 m: the speaker from the south, the listener from the north.
    obs = placed(env, [0.0, 0.8], math.pi, targets, goal=0, speaker_yaw=0.0)
    speaker_view, listener_view = obs["pixels"][0, 0], obs["pixels"][0, 1]
    white = (255, 255, 255)
    assert colour_pixels(speaker_view, white, tolerance=50) > 0
    assert colour_pixels(listener_view, white, tolerance=50) == 0
    overview = env.render_overview()[0]
    assert colour_pixels(overview, white, tolerance=50) > 0  # humans see it
    env.close()


def test_rules_reach_reward_termination_and_lamp():
    env = make()
    env.reset()
    targets = [[0.0, 0.5], [-1.0, 1.0], [1.0, 1.0]]
    state = env.get_state()
    state["pos"][:] = torch.tensor([[0.0, -1.2], [0.0, 0.4]])
    state["vel"].zero_()
    state["targets"][:] = torch.tensor(targets)
    state["goal"][:] = torch.tensor([0, 2])
    state["lamp"][:] = -1
    env.set_state(state)
    actions = torch.tensor([[5 + 2, 0], [5 + 0, 0]])  # world 0's speaker shows target 2, world 1's target 0
    obs, reward, terminated, truncated, info = env.step(actions)
    assert env.sim.lamp.tolist() == [2, 0]
    assert info["lamp_correct"].tolist() == [0, 0] and info["reached"].tolist() == [1, 0]
    d1 = (env.sim.pos[1, 1] - torch.tensor([1.0, 1.0])).norm()
    assert reward[0].tolist() == pytest.approx([1 - 0.1 * float(info["distance"][0])] * 2)
    assert reward[1].tolist() == pytest.approx([-0.1 * float(d1)] * 2)
    assert terminated.tolist() == [[True, True], [False, False]]
    assert float(info["distance"][0]) < REACH
    # The mask: the speaker may turn and signal, the listener drive.
    mask = obs["action_mask"][1]
    assert mask[0].tolist() == [True, False, True, True, False, True, True, True]
    assert mask[1].tolist() == [True, True, True, True, True, False, False, False]
    env.close()


def test_the_speaker_does_not_move_and_the_listeners_lamp_actions_do_nothing():
    env = make(continuous=True)
    env.reset()
    state = env.get_state()
    state["pos"][:, 1] = torch.tensor([0.0, 1.0])  # the listener far from the speaker, driving away from it
    state["yaw"][:, 1] = 0.0
    env.set_state(state)
    actions = torch.tensor([[1.0, 0.0, 0.9, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0, 0.9]]).expand(2, 2, 5)
    for _ in range(5):
        env.step(actions)
    assert torch.allclose(env.sim.pos[:, 0], torch.tensor([0.0, -1.2]).expand(2, 2))
    assert env.sim.lamp.tolist() == [0, 0]  # the speaker's largest lamp value, not the listener's
    env.close()


def test_state_observation_goal_only_for_the_speaker():
    env = make(state_obs=True, num_targets=4)
    obs = env.reset()
    state = obs["state"]
    assert state.shape == (2, 2, 9 + 4 * 4) == (2, 2, env.state_dim)
    goal = state[..., 6:10]
    assert goal[:, 0].sum(-1).tolist() == [1.0, 1.0] and goal[:, 1].abs().sum() == 0
    assert goal[:, 0].argmax(-1).tolist() == env.sim.goal.tolist()
    lamp = state[..., 10:15]
    assert lamp[..., 0].tolist() == [[1.0, 1.0]] * 2  # off
    env.close()


def test_determinism_and_state_round_trip():
    a, b = make(seed=5), make(seed=5)
    oa, ob = a.reset(), b.reset()
    assert torch.equal(oa["pixels"], ob["pixels"])
    g = torch.Generator().manual_seed(1)
    for _ in range(6):
        actions = a.random_actions(g)
        ra, rb = a.step(actions), b.step(actions)
        assert torch.equal(ra[0]["pixels"], rb[0]["pixels"]) and torch.equal(ra[1], rb[1])
    saved = a.get_state()
    first = a.step(torch.zeros(2, 2, dtype=torch.long))
    a.set_state(saved)
    again = a.step(torch.zeros(2, 2, dtype=torch.long))
    assert torch.equal(first[0]["pixels"], again[0]["pixels"]) and torch.equal(first[1], again[1])
    a.close(), b.close()


def test_bad_keywords_are_named():
    with pytest.raises(ValueError, match=r"num_targets must be an int in \[2, 6\], got 7"):
        make(num_targets=7)
    with pytest.raises(ValueError, match=r"num_agents must be an int in \[2, 2\]"):
        make(num_agents=3)
    with pytest.raises(TypeError, match="num_target"):
        make(num_target=3)


def test_the_heuristic_beats_random():
    heuristic = evaluate("speaker_listener", heuristic_policy, episodes=8, resolution=8)
    random = evaluate("speaker_listener", random_policy, episodes=8, resolution=8)
    assert heuristic["mean"] > random["mean"] + 5
