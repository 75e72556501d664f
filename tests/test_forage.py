"""Tests for envs/forage.py: agents collect respawning items."""


import pytest
import torch

from marl_render.envs import forage, list_envs, make_env

W, RES = 3, 32


def make(**kwargs):
    kwargs = {"num_worlds": W, "resolution": RES, "seed": 0, **kwargs}
    return make_env("forage", **kwargs)


def noop(env):
    if env.continuous:
        return torch.zeros(env.num_worlds, env.num_agents, 2)
    return torch.zeros(env.num_worlds, env.num_agents, dtype=torch.long)


def place(env, pos, items, yaw=None):
    """Agents at rest at pos [W, N, 2] (facing yaw [W, N]) and items at [W, I, 2], through set_state."""
    state = env.get_state()
    state.update(pos=pos, vel=torch.zeros_like(pos), items=items)
    if yaw is not None:
        state["yaw"] = yaw
    env.set_state(state)


def yellow(pixels):
    """Number of item-coloured (yellow) pixels in uint8 images [..., H, W, 3], per image."""
    r, g, b = pixels.to(torch.int32).unbind(-1)
    return ((r - b > 60) & (g - b > 50)).sum((-1, -2))


# --------------------------------------------------------------------------- contract
# Observation, reward and done shapes and dtypes: tests/test_envs_core.py checks them for every env.
def test_items_state_size_and_info():
    env = make(state_obs=True)
    N, I = env.num_agents, env.scenario.num_items  # noqa: E741
    assert (N, I) == (3, 6) and env.groups == {"agents": ["agent_0", "agent_1", "agent_2"]}
    assert env.state_dim == 6 + 3 * I + 2 * (N - 1)
    obs = env.reset(seed=1)
    assert obs["action_mask"].all()
    _, _, _, _, info = env.step(env.random_actions(torch.Generator().manual_seed(0)))
    assert info["collected"].shape == (W,) and info["collected"].dtype == torch.int64
    assert info["team_score"].shape == (W,) and info["team_score"].dtype == torch.float32
    env.close()


def test_options_and_registry():
    assert "forage" in list_envs()
    env = make_env("forage", num_worlds=1, resolution=8, num_agents=5, num_items=2, respawn_delay=1)
    assert isinstance(env.scenario, forage.Forage) and (env.num_agents, env.scenario.num_items) == (5, 2)
    env.close()
    for kwargs, error in [({"num_items": 0}, ValueError), ({"num_items": 33}, ValueError),
                          ({"respawn_delay": 0}, ValueError), ({"item_reward": -1.0}, ValueError),
                          ({"num_items": 2.0}, TypeError)]:
        with pytest.raises(error):
            make(**kwargs)


def test_reset_spawns_items_clear_of_agents():
    env = make(num_worlds=16)
    env.reset(seed=5)
    gap = torch.cdist(env.sim.items, env.sim.pos)
    assert (gap > forage.RESPAWN_CLEARANCE).float().mean() > 0.99  # the last-candidate fallback is rare
    agents = torch.cdist(env.sim.pos, env.sim.pos) + torch.eye(3) * 9
    assert (agents >= 2 * forage.AGENT_RADIUS).all()  # agents never start overlapping
    env.close()


# --------------------------------------------------------------------------- collecting
def test_touching_agent_collects_and_item_respawns():
    delay = 3
    env = make(respawn_delay=delay, state_obs=True)
    env.reset(seed=0)
    # Agents at rest; items in a row far from them.
    pos = torch.tensor([[-1.0, -1.0], [0.0, -1.0], [1.0, -1.0]]).repeat(W, 1, 1)
    pos[1, 0] = torch.tensor([-0.31, -1.0])  # world 1: agents 0 and 1 side by side (just touching)
    items = torch.stack((torch.linspace(-1.25, 1.25, 6), torch.full((6,), 1.2)), -1).repeat(W, 1, 1)
    items[0, 0] = torch.tensor([-1.0, -0.8])  # world 0: item 0 within reach of agent 0 only
    items[1, 0] = torch.tensor([-0.13, -1.0])  # world 1: both reach item 0, agent 1 is closer
    place(env, pos, items, yaw=torch.zeros(W, 3))
    seen_before = yellow(env.render_overview(64))
    obs, reward, terminated, truncated, info = env.step(noop(env))

    assert reward.tolist() == [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]
    assert info["collected"].tolist() == [1, 1, 0] and info["team_score"].tolist() == [1.0, 1.0, 0.0]
    assert not terminated.any() and not truncated.any()
    away = torch.zeros(W, 6, dtype=torch.bool)
    away[0, 0] = away[1, 0] = True
    assert torch.equal(forage.item_available(env.sim), ~away)
    assert torch.equal(env.renderer.instance_state("items")["active"], ~away)
    state = obs["state"].reshape(W, 3, -1)
    assert torch.equal(state[:, :, 6 + 12:6 + 18], (~away)[:, None].expand(W, 3, 6).float())  # availability flags
    seen_after = yellow(env.render_overview(64))
    assert seen_after[0] < seen_before[0] and seen_after[2] == seen_before[2], (seen_before, seen_after)

    # Away for `delay` steps (nobody collects it again although agent 0 still stands there) ...
    old = env.sim.items.clone()
    for step in range(1, delay):
        obs, reward, _, _, info = env.step(noop(env))
        assert (reward == 0).all() and torch.equal(forage.item_available(env.sim), ~away), step
        assert info["team_score"].tolist() == [1.0, 1.0, 0.0]
    # ... then back somewhere else, clear of every agent.
    obs, reward, _, _, info = env.step(noop(env))
    assert (reward == 0).all() and forage.item_available(env.sim).all()
    assert env.renderer.instance_state("items")["active"].all()
    assert torch.equal(env.sim.items[~away], old[~away]) and not torch.equal(env.sim.items[away], old[away])
    assert (torch.cdist(env.sim.items[:2, :1], env.sim.pos[:2]) > forage.RESPAWN_CLEARANCE).all()
    assert (env.sim.items.abs() <= forage.SPAWN).all()

    # The team score restarts with its world only.
    env.reset_worlds(torch.tensor([True, False, False]))
    assert env.sim.team_score.tolist() == [0.0, 1.0, 0.0]
    env.close()


def test_reward_is_per_item_and_agent():
    env = make(num_items=4)
    env.reset(seed=0)
    pos = torch.tensor([[-1.0, -1.0], [0.0, -1.0], [1.0, -1.0]]).repeat(W, 1, 1)
    items = torch.tensor([[-1.05, -1.0], [-0.95, -0.95], [1.0, -0.9], [0.0, 1.0]]).repeat(W, 1, 1)
    place(env, pos, items)
    _, reward, _, _, info = env.step(noop(env))
    assert reward.tolist() == [[2.0, 0.0, 1.0]] * W
    assert info["collected"].tolist() == [3] * W and info["team_score"].tolist() == [3.0] * W
    env.close()


# --------------------------------------------------------------------------- state handling
# Determinism, partial resets, bad actions and declared physics terms: tests/test_envs_core.py
# runs them for every env.
