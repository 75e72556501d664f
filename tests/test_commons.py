"""Tests for envs/commons.py: a commons harvest with regrowing apples and tagging."""

import math

import pytest
import torch

from marl_render.envs import commons, list_envs, make_env

W, RES = 2, 24
M = 45  # apples of the fixed layout
CENTRE = 4  # the apple at (0, 0): the middle of patch 0's 3 x 3 grid
NEAR_CENTRE = [1, 3, 5, 7]  # its grid neighbours


def make(**kwargs):
    kwargs = {"num_worlds": W, "resolution": RES, "seed": 0, **kwargs}
    return make_env("commons", **kwargs)


def actions(env, zap=(), forward=()):
    """Noop for all but the agents in `zap` (zap) and `forward` (forward), in every world."""
    if env.continuous:
        a = torch.zeros(env.num_worlds, env.num_agents, 3)
        a[:, list(zap), 2] = 1.0
        a[:, list(forward), 0] = 1.0
        return a
    a = torch.zeros(env.num_worlds, env.num_agents, dtype=torch.long)
    a[:, list(zap)], a[:, list(forward)] = 5, 1
    return a


def place(env, pos, yaw, **fields):
    """Agents at rest at pos [W, N, 2] facing yaw [W, N], other state fields as given."""
    state = env.get_state()
    state.update(pos=pos, vel=torch.zeros_like(pos), yaw=yaw, **fields)
    env.set_state(state)


def red(pixels):
    """Apple-coloured pixels in uint8 images [..., H, W, 3], per image."""
    r, g, b = pixels.to(torch.int32).unbind(-1)
    return ((r - g > 80) & (r - b > 80)).sum((-1, -2))


# Five agents out of the apples' way, in a row at y = -1.7, facing +y.
ROW = torch.tensor([[-1.7, -1.7], [-0.6, -1.7], [0.5, -1.7], [1.0, -0.5], [1.7, 0.5]])


def test_layout_spaces_state_size_and_info():
    env = make(state_obs=True)
    N = env.num_agents
    assert N == 5 and env.scenario.num_apples == M and env.state_dim == 7 + 3 * M + 3 * (N - 1)
    assert env.action_meanings[5] == "zap" and env.num_actions == 6
    assert torch.equal(env.scenario.apples[CENTRE], torch.zeros(2))
    assert env.scenario.neighbours[CENTRE].nonzero().flatten().tolist() == NEAR_CENTRE
    obs = env.reset(seed=1)
    assert obs["state"].shape == (W, N, env.state_dim) and obs["action_mask"].all()
    _, _, _, _, info = env.step(env.random_actions(torch.Generator().manual_seed(0)))
    for key in ("collected", "apples_left", "tags", "depleted_at"):
        assert info[key].shape == (W,) and info[key].dtype == torch.int64, key
    env.close()
    env = make(continuous=True)
    assert env.action_dim == 3
    env.close()


def test_options_and_registry():
    assert "commons" in list_envs()
    env = make_env("commons", num_worlds=1, resolution=8, num_agents=2, tag_timeout=3, regrowth=(0, 0, 0.5, 1.0))
    assert isinstance(env.scenario, commons.Commons) and env.num_agents == 2
    env.close()
    for kwargs, error, word in [({"regrowth": (0.1, 0.2)}, ValueError, "regrowth"),
                                ({"regrowth": (0, 0, 0, 1.5)}, ValueError, "regrowth"),
                                ({"tag_timeout": 0}, ValueError, "tag_timeout"),
                                ({"tag_timeout": 2.0}, TypeError, "tag_timeout"),
                                ({"num_agents": 13}, ValueError, "num_agents")]:
        with pytest.raises(error, match=word):
            make(**kwargs)


def test_collecting_regrowth_and_depletion():
    # Certain regrowth next to a present apple, none without: each case's outcome is exact.
    env = make(regrowth=(0.0, 1.0, 1.0, 1.0))
    env.reset(seed=0)
    pos = ROW.repeat(W, 1, 1)
    pos[:, 0] = torch.zeros(2)  # agent 0 stands on the centre apple
    present = torch.ones(W, M, dtype=torch.bool)
    present[1, :] = False
    present[1, CENTRE] = True  # world 1: the last apple
    place(env, pos, torch.zeros(W, 5), present=present, steps=torch.tensor([0, 7]))
    obs, reward, terminated, truncated, info = env.step(actions(env))
    assert reward.tolist() == [[1.0, 0.0, 0.0, 0.0, 0.0]] * W
    assert info["collected"].tolist() == [1, 1] and env.sim.collected[:, 0].tolist() == [1, 1]
    # World 0: the centre apple has 4 present neighbours and is back at once; world 1: gone for good.
    assert env.sim.present[0].all() and not env.sim.present[1].any()
    assert info["apples_left"].tolist() == [M, 0] and info["depleted_at"].tolist() == [-1, 8]
    assert torch.equal(env.renderer.instance_state("apples")["active"], env.sim.present)
    assert not terminated.any() and not truncated.any()
    _, reward, _, _, info = env.step(actions(env))
    assert reward.tolist() == [[1.0, 0.0, 0.0, 0.0, 0.0], [0.0] * 5] and info["depleted_at"].tolist() == [-1, 8]
    env.close()


def test_regrowth_rate_follows_the_neighbour_count():
    # 64 worlds, one missing apple with exactly k present neighbours; p = regrowth[k].
    env = make(num_worlds=64, resolution=8, regrowth=(0.0, 0.0, 1.0, 0.0))
    env.reset(seed=0)
    present = torch.zeros(64, M, dtype=torch.bool)
    present[:32, [1, 3]] = True  # 2 present neighbours of the centre and of the corner apple 0
    present[32:, [1]] = True  # 1 present neighbour of the centre and of apples 0 and 2: never (p = 0)
    place(env, ROW.repeat(64, 1, 1), torch.zeros(64, 5), present=present)
    env.step(actions(env))
    assert env.sim.present[:32, [0, CENTRE]].all() and not env.sim.present[32:, [0, 2, CENTRE]].any()
    assert env.sim.present.sum(-1).tolist() == [4] * 32 + [1] * 32
    env.close()


@pytest.mark.parametrize("continuous", [False, True])
def test_zap_tags_the_nearest_agent_in_view_for_the_timeout(continuous):
    timeout = 3
    env = make(tag_timeout=timeout, continuous=continuous)
    env.reset(seed=0)
    pos = ROW.repeat(W, 1, 1)
    pos[:, 1] = torch.tensor([-1.7, -1.1])  # 0.6 m in front of agent 0
    pos[:, 2] = torch.tensor([-1.7, -0.7])  # behind agent 1: not the nearest
    yaw = torch.zeros(W, 5)
    yaw[1, 0] = math.pi  # world 1: agent 0 faces away
    place(env, pos, yaw, present=torch.zeros(W, M, dtype=torch.bool))
    obs, reward, _, _, info = env.step(actions(env, zap=[0]))
    assert info["tags"].tolist() == [1, 0] and (reward == 0).all()
    out = torch.zeros(W, 5, dtype=torch.bool)
    out[0, 1] = True
    assert torch.equal(env.sim.timeout, out * timeout) and torch.equal(env.sim.shown, ~out)
    assert torch.equal(env.renderer.instance_state("agents")["active"], ~out)  # not drawn
    if not continuous:
        assert obs["action_mask"][0, 1].tolist() == [True] + [False] * 5 and obs["action_mask"][1].all()
    # While out it cannot be tagged again: the next zap hits agent 2, the next nearest in view.
    held = env.sim.pos[0, 1].clone()
    _, _, _, _, info = env.step(actions(env, zap=[0]))
    assert info["tags"].tolist() == [1, 0] and env.sim.timeout[0, :3].tolist() == [0, timeout - 1, timeout]
    # Its actions do nothing (its body is inactive).
    for _ in range(timeout - 2):
        env.step(actions(env, forward=[1]))
        assert torch.equal(env.sim.pos[0, 1], held)
    assert env.sim.timeout[0, 1] == 1
    env.step(actions(env))
    # Back in play at a spawn point, drawn again.
    assert env.sim.timeout[0].tolist() == [0, 0, 1, 0, 0] and torch.equal(env.sim.shown, env.sim.timeout == 0)
    assert (env.sim.pos[0, 1] - env.scenario.respawn_points).norm(dim=-1).min() < 1e-6
    env.close()


def test_apples_are_seen_in_front_and_gone_when_collected():
    env = make(num_worlds=1, resolution=32)
    env.reset(seed=0)
    pos = ROW[None].clone()
    pos[0, 0] = torch.tensor([0.0, -0.7])  # facing patch 0 from 0.45 m
    place(env, pos, torch.zeros(1, 5))
    seen = red(env.step(actions(env))[0]["pixels"][0, 0])
    assert seen > 20, seen
    state = env.get_state()
    state["present"][:] = False
    env.set_state(state)
    assert red(env.step(actions(env))[0]["pixels"][0, 0]) == 0  # regrowth needs neighbours: none
    env.close()


def test_determinism_and_state_round_trip():
    def run(env, steps, generator):
        out = []
        for _ in range(steps):
            obs, reward, *_ = env.step(env.random_actions(generator))
            out.append((obs["pixels"], obs["state"], reward))
        return out

    def same(xs, ys):
        return all(torch.equal(x, y) for s, t in zip(xs, ys, strict=True) for x, y in zip(s, t, strict=True))

    a, b = make(state_obs=True, seed=3), make(state_obs=True, seed=3)
    a.reset(seed=3)
    b.reset(seed=3)
    first, second = run(a, 20, torch.Generator().manual_seed(1)), run(b, 20, torch.Generator().manual_seed(1))
    assert same(first, second)
    saved = a.get_state()
    later = run(a, 20, torch.Generator().manual_seed(2))
    a.set_state(saved)
    again = run(a, 20, torch.Generator().manual_seed(2))
    assert same(later, again)
    a.close()
    b.close()


def test_heuristic_beats_random():
    env = make_env("commons", num_worlds=8, resolution=8, seed=0, max_steps=120)
    returns = {}
    for policy in ("heuristic", "random"):
        env.reset(seed=4)
        g, total = torch.Generator().manual_seed(0), 0.0
        for _ in range(120):
            act = env.heuristic_actions() if policy == "heuristic" else env.random_actions(g)
            total += float(env.step(act)[1].sum())
        returns[policy] = total
    assert returns["heuristic"] > returns["random"], returns
    env.close()
