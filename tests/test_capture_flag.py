"""Tests for envs/capture_flag.py: two teams capture each other's flag."""

import math

import pytest
import torch

from marl_render.envs import list_envs, make_env
from marl_render.envs.capture_flag import BASE_Y, HOME_ROWS

W, RES = 2, 16
RED0, RED1, BLUE0, BLUE1 = range(4)
FAR = [[-2.0, -1.0], [-2.0, -2.0], [2.0, 1.0], [2.0, 2.0]]  # nobody touches anybody or a flag


def make(**kwargs):
    return make_env("capture_flag", **{"num_worlds": W, "num_agents": 4, "resolution": RES, "seed": 0, **kwargs})


def noop(env):
    return env.step(torch.zeros(env.num_worlds, env.num_agents, dtype=torch.long))


def place(env, pos, yaw=None, carrier=(-1, -1)):
    """Bodies at rest at pos [N, 2] (yaw [N]) in every world, the flags' carriers as given."""
    state = env.get_state()
    state["pos"] = torch.tensor(pos).expand(env.num_worlds, -1, -1).clone()
    state["vel"] = torch.zeros_like(state["vel"])
    if yaw is not None:
        state["yaw"] = torch.tensor(yaw).expand(env.num_worlds, -1).clone()
    state["carrier"] = torch.tensor(carrier).expand(env.num_worlds, 2).clone()
    env.set_state(state)


def test_teams_state_size_and_info():
    env = make_env("capture_flag", num_worlds=1, resolution=8, state_obs=True)
    assert env.num_agents == 16 and "capture_flag" in list_envs()
    assert env.groups == {"red": [f"red_{i}" for i in range(8)], "blue": [f"blue_{i}" for i in range(8)]}
    assert env.state_dim == 15 + 2 * (4 + 4)  # K = 4 teammates and 4 opponents
    obs = env.reset(seed=0)
    assert obs["state"].shape == (1, 16, 31)
    _, _, _, _, info = env.step(env.random_actions())
    assert {"captures_blue", "captures_red", "flag_carried", "tags"} <= set(info)
    assert all(info[k].shape == (1,) and info[k].dtype == torch.int64 for k in env.scenario.info_keys)
    env.close()
    env = make(state_obs=True)  # two per team: 1 teammate, 2 opponents
    assert env.state_dim == 15 + 2 * (1 + 2)
    env.close()


def test_spawn_in_own_half_flags_home():
    env = make_env("capture_flag", num_worlds=4, num_agents=64, resolution=8, seed=3)
    env.reset()
    y = env.sim.pos[..., 1]
    assert (y[:, :32] < -0.2).all() and (y[:, 32:] > 0.2).all()
    assert (torch.cdist(env.sim.pos, env.sim.pos) + torch.eye(64) * 9 > 0.3).all()  # no overlaps
    assert (env.sim.carrier == -1).all()
    env.close()


def test_bad_arguments_name_themselves():
    for kwargs, word in [({"num_agents": 5}, "num_agents"), ({"num_agents": 66}, "num_agents"),
                         ({"num_agents": 2}, "num_agents"), ({"captures_to_win": -1}, "captures_to_win"),
                         ({"k_nearest": 0}, "k_nearest"), ({"capture_reward": -1.0}, "capture_reward"),
                         ({"shaping": -0.5}, "shaping"),
                         ({"flags": 3}, "flags")]:
        with pytest.raises((TypeError, ValueError), match=word):
            make(**kwargs)


def test_tag_in_the_opponents_half_sends_home_and_drops_the_flag():
    env = make()
    env.reset()
    # red_0 carries blue's flag in blue's half and touches blue_0 (gap 0.03 m): it is tagged.
    pos = [[0.0, 0.5], FAR[1], [0.0, 0.83], FAR[3]]
    place(env, pos, carrier=(-1, RED0))
    _, reward, terminated, _, info = noop(env)
    assert info["tags"].tolist() == [1, 1] and info["flag_carried"].tolist() == [0, 0]
    assert torch.allclose(env.sim.pos[:, RED0], torch.tensor([0.0, -HOME_ROWS[0]]))
    assert (env.sim.vel[:, RED0] == 0).all() and (env.sim.carrier == -1).all()
    assert (reward == 0).all() and not terminated.any()
    # The same touch in red's own half tags blue_0 instead.
    place(env, [[0.0, -0.83], FAR[1], [0.0, -0.5], FAR[3]])
    _, _, _, _, info = noop(env)
    assert info["tags"].tolist() == [1, 1]
    assert torch.allclose(env.sim.pos[:, BLUE0], torch.tensor([0.0, HOME_ROWS[0]]))
    assert torch.allclose(env.sim.pos[:, RED0], torch.tensor([0.0, -0.83]), atol=1e-3)
    env.close()


def test_capture_scores_zero_sum_and_can_end_the_episode():
    env = make(captures_to_win=2)
    env.reset()
    pos = [[0.0, -BASE_Y + 0.3], FAR[1], FAR[2], FAR[3]]  # red_0 on its base with blue's flag
    place(env, pos, carrier=(-1, RED0))
    _, reward, terminated, _, info = noop(env)
    assert info["captures_red"].tolist() == [1, 1] and info["captures_blue"].tolist() == [0, 0]
    assert reward.tolist() == [[1.0, 1.0, -1.0, -1.0]] * W
    assert (env.sim.carrier == -1).all() and env.sim.captures.tolist() == [[1, 0]] * W
    assert not terminated.any()
    place(env, pos, carrier=(-1, RED0))
    _, reward, terminated, _, _ = noop(env)
    assert terminated.all() and env.sim.captures.tolist() == [[2, 0]] * W
    env.close()


def test_shaping_rewards_progress_towards_the_next_capture():
    env, plain = make(shaping=0.5), make()
    for e in (env, plain):
        e.reset()
    forward = torch.tensor([[1, 0, 0, 0]] * W)  # red_0 drives, the others stand still
    # red_0 (yaw 0 faces +y) is red's nearest agent to blue's flag and drives towards it.
    pos = [[0.0, -1.0], [-2.0, -2.0], [2.0, 1.0], [2.0, 2.0]]
    place(env, pos, yaw=[0.0, 0.0, 0.0, 0.0])
    place(plain, pos, yaw=[0.0, 0.0, 0.0, 0.0])
    _, reward, _, _, _ = env.step(forward)
    _, unshaped, _, _, _ = plain.step(forward)
    gain = env.sim.pos[:, RED0, 1] - (-1.0)  # red_0 drove straight at blue's flag on x = 0
    assert (unshaped == 0).all() and (gain > 0).all()
    assert torch.allclose(reward[:, :2], (0.5 * gain)[:, None].expand(-1, 2), atol=1e-5)
    assert (reward[:, 2:] == 0).all()  # blue did not move
    # Carrying blue's flag, red_0 gains by heading home (yaw pi faces -y) and loses going away.
    place(env, [[0.0, 1.0], *pos[1:]], yaw=[math.pi, 0.0, 0.0, 0.0], carrier=(-1, RED0))
    _, reward, _, _, _ = env.step(forward)
    assert (reward[:, :2] > 0).all()
    place(env, [[0.0, 1.0], *pos[1:]], yaw=[0.0, 0.0, 0.0, 0.0], carrier=(-1, RED0))
    _, reward, _, _, _ = env.step(forward)
    assert (reward[:, :2] < 0).all()
    # A tag undoes progress: red_0, carrying in blue's half, is tagged and loses what it had made
    # (so running into defenders and being sent home cannot be farmed for shaping reward).
    place(env, [[0.0, 0.5], [-2.0, -2.0], [0.0, 0.83], [2.0, 2.0]], carrier=(-1, RED0))
    _, reward, _, _, info = noop(env)
    assert info["tags"].tolist() == [1, 1]
    # Before: the carrier 3.5 m from red's base; after: blue's flag is home and red's nearest agent
    # to it is red_1 at (-2, -2), sqrt(29) m away, plus the 6 m between the bases.
    lost = 0.5 * ((math.sqrt(29.0) + 2 * BASE_Y) - 3.5)
    assert torch.allclose(reward[:, :2], torch.full((W, 2), -lost), atol=1e-4)
    # A capture is credited its movement only (none here): no loss for the flag's return home.
    place(env, [[0.0, -BASE_Y + 0.3], [-2.0, -2.0], [2.0, 1.0], [2.0, 2.0]], carrier=(-1, RED0))
    _, reward, _, _, info = noop(env)
    assert info["captures_red"].tolist() == [1, 1]
    assert reward.tolist() == [[1.0, 1.0, -1.0, -1.0]] * W
    env.close(), plain.close()


def test_closest_opponent_picks_up_a_flag_at_home_and_it_follows():
    env = make()
    env.reset()
    # Both blue agents touch red's flag; blue_0 is closer. red_0 stands on its own flag: no pick-up.
    pos = [[0.0, -BASE_Y + 0.5], FAR[1], [-0.12, -BASE_Y], [0.19, -BASE_Y]]
    place(env, pos, yaw=[0.0, 0.0, 0.0, 0.0])
    _, _, _, _, info = noop(env)
    assert env.sim.carrier.tolist() == [[BLUE0, -1]] * W and info["flag_carried"].tolist() == [1, 1]
    flags = env.scenario.flag_position(env.sim)
    assert torch.allclose(flags[:, 0], env.sim.pos[:, BLUE0] - torch.tensor([0.0, 0.22]), atol=1e-5)
    assert torch.allclose(flags[:, 1], torch.tensor([0.0, BASE_Y]))
    env.close()


def test_state_observation_contents():
    env = make(num_worlds=1, state_obs=True)
    env.reset()
    place(env, [[1.0, -1.0], [1.0, -2.0], [2.0, 0.5], [-1.0, 1.0]], yaw=[0.0] * 4, carrier=(BLUE0, -1))
    state = env.scenario.observation(env.sim, env.alive)[0, RED0]
    red_flag = torch.tensor([2.0, 0.5 - 0.22])
    expected = [1.0, -1.0, 0.0, 0.0, 1.0, 0.0, -1.0, -2.0, *(red_flag - torch.tensor([1.0, -1.0])).tolist(), 1.0,
                -1.0, 4.0, 0.0, 0.0, 0.0, -1.0, 1.0, 1.5, -2.0, 2.0]  # mates then opponents, nearest first
    assert torch.allclose(state, torch.tensor(expected))
    env.close()


def test_the_flag_a_camera_faces_shows_its_team_colour():
    env = make(resolution=32, state_obs=False)
    env.reset()
    # red_0 looks at blue's base (+y), blue_0 at red's (-y); the others face the side walls.
    place(env, [[0.0, BASE_Y - 0.7], [-2.0, 0.5], [0.0, -BASE_Y + 0.7], [2.0, -0.5]],
          yaw=[0.0, 1.57, 3.1416, -1.57])
    pixels = noop(env)[0]["pixels"].to(torch.int32)  # [W, N, H, W, 3]
    r, g, b = pixels[:, :, 20:28, 12:20].unbind(-1)  # below the centre: the base pad and the flag's pole
    bluish, reddish = (b - r > 40).float().mean((-1, -2)), (r - b > 40).float().mean((-1, -2))
    assert (bluish[:, RED0] > 0.5).all() and (reddish[:, RED0] == 0).all()
    assert (reddish[:, BLUE0] > 0.5).all() and (bluish[:, BLUE0] == 0).all()
    env.close()


def test_seeded_episodes_are_identical_and_state_round_trips():
    runs = []
    for _ in range(2):
        env = make(state_obs=True, resolution=8)
        env.reset(seed=5)
        g, out = torch.Generator().manual_seed(1), []
        for t in range(30):
            actions = env.heuristic_actions() if t % 2 else env.random_actions(g)
            obs, reward, *_ = env.step(actions)
            out.append((obs["state"].clone(), obs["pixels"].clone(), reward.clone()))
        runs.append(out)
        saved = env.get_state()
    assert all(torch.equal(a, b) for x, y in zip(*runs, strict=True) for a, b in zip(x, y, strict=True))
    actions = [env.random_actions(torch.Generator().manual_seed(k)) for k in range(5)]
    first = [env.step(a)[0]["state"] for a in actions]
    env.set_state(saved)
    assert all(torch.equal(a, env.step(b)[0]["state"]) for a, b in zip(first, actions, strict=True))
    env.close()


def test_heuristic_red_beats_random_red_against_random_blue():
    env = make_env("capture_flag", num_worlds=4, num_agents=8, resolution=4, seed=0, max_steps=120)
    returns = []
    for scripted in (True, False):
        env.reset(seed=2)
        g, total = torch.Generator().manual_seed(0), torch.zeros(4)
        for _ in range(120):
            actions = env.random_actions(g)
            if scripted:
                actions[:, :4] = env.heuristic_actions()[:, :4]
            total += env.step(actions)[1][:, RED0]
        returns.append(total.mean().item())
    assert returns[0] > returns[1]
    env.close()
