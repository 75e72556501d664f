"""Tests for envs/clean_up.py: a public good (a river to clean) apart from the reward (apples)."""
from __future__ import annotations

import math

import pytest
import torch

from marl_render.envs import clean_up, list_envs, make_env
from marl_render.envs.roster import Bot, HeldOut

D, M = 16, 32  # river cells, apple places
COLUMN_0 = [0, 8]  # the river cells of the column at x = -1.75 (both rows)
# Seven agents in the middle band, out of the apples' and the river's reach, facing +y (the river).
MIDDLE = torch.tensor([[-1.75, 0.2], [-1.2, 0.2], [-0.6, 0.2], [0.0, 0.2], [0.6, 0.2], [1.2, 0.2], [1.75, 0.2]])


def make(**kwargs):
    return make_env("clean_up", **{"num_worlds": 2, "resolution": 8, "seed": 0, **kwargs})


def noop(env, **agents):
    """Discrete actions: noop for all, `agents` {index: action} in every world."""
    a = torch.zeros(env.num_worlds, env.num_agents, dtype=torch.long)
    for index, action in agents.items():
        a[:, int(index[1:])] = action
    return a


def place(env, pos=None, yaw=None, **fields):
    """Agents at rest at pos [W, N, 2] (default MIDDLE) facing yaw [W, N] (default +y), fields as given."""
    state = env.get_state()
    W = env.num_worlds
    pos = MIDDLE.expand(W, -1, -1).clone() if pos is None else pos
    yaw = torch.zeros(W, env.num_agents) if yaw is None else yaw
    state.update(pos=pos, vel=torch.zeros_like(pos), yaw=yaw, **fields)
    env.set_state(state)


def brown(pixels):
    """Dirt-coloured pixels of uint8 images [..., H, W, 3], per image."""
    r, g, b = pixels.to(torch.int32).unbind(-1)
    return ((r > g + 20) & (g > b + 20) & (r < 160)).sum((-1, -2))


def red(pixels):
    r, g, b = pixels.to(torch.int32).unbind(-1)
    return ((r - g > 80) & (r - b > 80)).sum((-1, -2))


def test_layout_spaces_state_size_info_and_registry():
    assert "clean_up" in list_envs()
    env = make(state_obs=True)
    N = env.num_agents
    assert N == 7 and env.num_actions == 7 and env.action_meanings[5:] == ("zap", "clean")
    assert env.state_dim == 7 + 3 * D + 3 * M + 3 * (N - 1)
    s = env.scenario
    assert s.dirt_cells.shape == (D, 2) and s.apples.shape == (M, 2)
    assert (s.dirt_cells[:, 1] > 1.1).all() and (s.apples[:, 1] < -0.55).all()  # river and orchard, apart
    obs = env.reset(seed=1)
    assert obs["state"].shape == (2, N, env.state_dim) and obs["action_mask"].all()
    _, reward, _, _, info = env.step(env.random_actions(torch.Generator().manual_seed(0)))
    assert reward.shape == (2, N) and reward.dtype == torch.float32
    for key, dtype in clean_up.CleanUp.info_keys.items():
        assert info[key].shape == (2,) and info[key].dtype == dtype, key
    assert clean_up.CleanUp.mixed_motive is True
    env.close()
    with make(continuous=True) as env:
        assert env.action_dim == 4


@pytest.mark.parametrize("kwargs, error, word", [
    ({"dirt_rate": 1.5}, ValueError, "dirt_rate"), ({"dirt_rate": "0.1"}, TypeError, "dirt_rate"),
    ({"dirt_threshold": 0.0}, ValueError, "dirt_threshold"), ({"apple_regrowth": -0.1}, ValueError, "apple_regrowth"),
    ({"initial_dirt": math.nan}, ValueError, "initial_dirt"), ({"tag_timeout": 0}, ValueError, "tag_timeout"),
    ({"num_agents": 15}, ValueError, "num_agents")])
def test_bad_keywords_are_refused_by_name(kwargs, error, word):
    with pytest.raises(error, match=word):
        make(**kwargs)


def test_the_beam_cleans_the_cells_in_front_only_and_pays_nothing():
    env = make(dirt_rate=0.0, apple_regrowth=0.0)
    env.reset(seed=0)
    pos = MIDDLE.expand(2, -1, -1).clone()
    pos[:, 0] = torch.tensor([-1.75, 0.9])  # on the bank below column 0, facing the river
    pos[:, 6] = torch.tensor([1.75, 0.9])  # below column 7, facing away from the river
    yaw = torch.zeros(2, 7)
    yaw[:, 6] = math.pi
    place(env, pos, yaw, dirt=torch.ones(2, D, dtype=torch.bool), present=torch.zeros(2, M, dtype=torch.bool))
    _, reward, _, _, info = env.step(noop(env, a0=clean_up.CLEAN, a6=clean_up.CLEAN, a3=clean_up.CLEAN))
    dirt = env.sim.dirt
    assert (~dirt).nonzero()[:, 1].tolist() == COLUMN_0 * 2  # both worlds: column 0's two cells, nothing else
    assert info["cleaned"].tolist() == [2, 2] and torch.equal(reward, torch.zeros(2, 7))
    assert env.sim.cleaned[:, 0].tolist() == [2, 2] and env.sim.cleaned[:, 1:].sum() == 0
    assert torch.allclose(info["dirt_fraction"], torch.full((2,), 14 / 16))
    env.close()


def test_regrowth_falls_linearly_with_dirt_to_zero_at_the_threshold():
    env = make(num_worlds=64, dirt_rate=0.0, dirt_threshold=0.5, apple_regrowth=1.0)
    s = env.scenario
    dirt = torch.zeros(3, D, dtype=torch.bool)
    dirt[1, :4] = True  # a quarter: half the threshold
    dirt[2, :8] = True  # half: the threshold
    assert s.regrowth_rate(dirt).tolist() == [1.0, 0.5, 0.0]
    env.reset(seed=0)
    regrown = []
    for cells in (0, 4, 8, 12):
        dirty = torch.zeros(64, D, dtype=torch.bool)
        dirty[:, :cells] = True
        place(env, dirt=dirty, present=torch.zeros(64, M, dtype=torch.bool))
        env.step(noop(env))
        regrown.append(env.sim.present.float().mean().item())
    assert regrown[0] == 1.0 and regrown[2] == regrown[3] == 0.0
    assert 0.45 < regrown[1] < 0.55, regrown  # 2048 draws at p = 0.5
    env.close()


def test_eating_an_apple_gives_one_to_the_closest_agent_in_play():
    env = make(dirt_rate=0.0, apple_regrowth=0.0)
    env.reset(seed=0)
    apple = env.scenario.apples[5]
    pos = MIDDLE.expand(2, -1, -1).clone()
    pos[:, 0] = apple + torch.tensor([0.05, 0.0])
    pos[:, 1] = apple + torch.tensor([-0.15, 0.0])  # touching too, but farther
    pos[:, 2] = env.scenario.apples[9]  # on another apple, but tagged out
    timeout = torch.zeros(2, 7, dtype=torch.int64)
    timeout[:, 2] = 5
    place(env, pos, dirt=torch.zeros(2, D, dtype=torch.bool), present=torch.ones(2, M, dtype=torch.bool),
          timeout=timeout, shown=timeout == 0)
    _, reward, _, _, info = env.step(noop(env))
    want = torch.zeros(2, 7)
    want[:, 0] = 1.0
    assert torch.equal(reward, want) and info["eaten"].tolist() == [1, 1]
    assert (~env.sim.present).nonzero()[:, 1].tolist() == [5, 5] and env.sim.eaten[:, 0].tolist() == [1, 1]
    env.close()


def test_a_zapped_agent_is_out_for_the_timeout_then_back_mid_arena():
    env = make(tag_timeout=3)
    env.reset(seed=0)
    pos = MIDDLE.expand(2, -1, -1).clone()
    pos[:, 1] = torch.tensor([-1.75, 1.2])  # 1 m in front of agent 0
    place(env, pos)
    mask = env.step(noop(env, a0=clean_up.ZAP))[0]["action_mask"]
    s = env.scenario
    out = torch.zeros(2, 7, dtype=torch.bool)
    out[:, 1] = True
    assert env.sim.timeout[:, 1].tolist() == [3, 3] and torch.equal(s.tagged_out(env.sim), out)
    assert torch.equal(env.sim.shown, ~out)
    assert mask[:, 1].tolist() == [[True] + [False] * 6] * 2 and mask[:, 0].all()
    for _ in range(2):  # still out
        env.step(noop(env))
        assert torch.equal(s.tagged_out(env.sim), out)
    env.step(noop(env))
    assert not s.tagged_out(env.sim).any() and env.sim.shown.all()
    assert (env.sim.pos[:, 1, None] - s.respawn_points).norm(dim=-1).amin(-1).max() < 1e-6
    env.close()


def test_dirt_is_seen_in_the_river_and_gone_from_the_view_once_cleaned():
    env = make(num_worlds=1, resolution=32, dirt_rate=0.0)
    env.reset(seed=0)
    pos = MIDDLE[None].clone()
    pos[0, 0] = torch.tensor([-1.75, 0.9])
    place(env, pos, dirt=torch.ones(1, D, dtype=torch.bool))
    view = env.step(noop(env))[0]["pixels"][0, 0]
    before = brown(view)
    assert before > 50, before
    assert brown(view[-4:, 12:20]) == 4 * 8  # the bottom centre of the view: the dirt 0.3 m ahead
    view = env.step(noop(env, a0=clean_up.CLEAN))[0]["pixels"][0, 0]
    assert brown(view[-4:, 12:20]) == 0
    r, g, b = view[-4:, 12:20].to(torch.int32).unbind(-1)
    assert ((b > r + 40) & (b > g)).all()  # the clean river is blue there
    pos[0, 0], yaw = torch.tensor([0.0, -0.3]), torch.full((1, 7), math.pi)  # facing the orchard
    place(env, pos, yaw, present=torch.ones(1, M, dtype=torch.bool))
    assert red(env.step(noop(env))[0]["pixels"][0, 0]) > 10
    env.close()


def test_the_heuristic_eats_far_more_than_random_play():
    env = make(num_worlds=4, max_steps=60)
    returns = {}
    for policy in ("heuristic", "random"):
        env.reset(seed=4)
        g, total = torch.Generator().manual_seed(0), 0.0
        for _ in range(60):
            act = env.heuristic_actions() if policy == "heuristic" else env.random_actions(g)
            total += float(env.step(act)[1].sum())
        returns[policy] = total
    assert returns["heuristic"] > 5 * max(returns["random"], 1.0), returns
    env.close()


def test_the_bots_clean_free_ride_and_zap_as_described():
    env = make(num_worlds=1)
    env.reset(seed=0)
    pos = MIDDLE[None].clone()
    pos[0, 0] = torch.tensor([-1.75, 0.9])  # below dirty column 0, facing it
    pos[0, 1] = torch.tensor([-1.75, 0.3])  # 0.6 m behind agent 0, facing it
    place(env, pos, dirt=torch.ones(1, D, dtype=torch.bool))
    assert clean_up.cleaner(env)[0, 0] == clean_up.CLEAN
    free = clean_up.free_rider(env)
    assert not ((free == clean_up.CLEAN) | (free == clean_up.ZAP)).any()
    assert clean_up.zapper(env)[0, 1] == clean_up.ZAP
    assert env.scenario.heuristic(env.sim, env.alive)[0, 0] == clean_up.CLEAN  # agents 0 and 1 clean
    with make(num_worlds=1, continuous=True) as twin:
        twin.reset(seed=0)
        place(twin, pos, dirt=torch.ones(1, D, dtype=torch.bool))
        assert clean_up.cleaner(twin)[0, 0].tolist() == [0.0, 0.0, 0.0, 1.0]
    env.close()


def test_the_roster_declares_test_bots_for_three_tagged_scenarios():
    task = clean_up.CleanUp
    assert all(isinstance(bot, Bot) for bot in task.bots.values()) and task.card
    assert {name for name, bot in task.bots.items() if bot.population == "test"} >= {"cleaner", "free_rider", "zapper"}
    assert len(task.heldout) >= 3 and all(isinstance(h, HeldOut) for h in task.heldout)
    tags = set()
    for held in task.heldout:
        assert held.focal and all(name in clean_up.numbered("agent", held.num_agents) for name in held.focal)
        assert all(task.bots[b].population == "test" for names in held.bots_by_role.values() for b in names)
        tags.add("resident" if 2 * len(held.focal) > held.num_agents else "visitor")
    assert tags == {"resident", "visitor"}


def test_appearance_changes_the_look_not_the_layout_and_the_river_stays_blue():
    with make(num_worlds=2, resolution=32, seed=5) as plain, \
            make(num_worlds=2, resolution=32, seed=5, appearance="heldout") as looked:
        plain.reset(), looked.reset()
        assert torch.equal(plain.sim.pos, looked.sim.pos) and torch.equal(plain.sim.dirt, looked.sim.dirt)
        pos = MIDDLE.expand(2, -1, -1).clone()
        pos[:, 0] = torch.tensor([-1.75, 0.9])  # facing the river cells of column 0, cleaned
        dirt = torch.ones(2, D, dtype=torch.bool)
        dirt[:, COLUMN_0] = False
        views = []
        for env in (plain, looked):
            place(env, pos, dirt=dirt)
            views.append(env.step(noop(env))[0]["pixels"][:, 0])
        assert not torch.equal(views[0], views[1])
        r, g, b = views[1][:, -4:, 12:20].to(torch.int32).unbind(-1)
        assert (b > r + 20).all()  # the river, hue-shifted a little, still blue in every world


def test_the_cooperator_cleans_while_the_river_is_dirty_and_eats_otherwise():
    """The Schelling diagram's cooperator (schelling = ("cooperator", "free_rider")): below half of
    dirt_threshold (0.2: 3 of 16 cells) it acts as the free rider, from half of it up as the cleaner."""
    assert clean_up.CleanUp.schelling == ("cooperator", "free_rider")
    assert list(clean_up.CleanUp.bots)[:5] == ["cleaner", "free_rider", "zapper", "lazy0.5", "noisy0.1"]
    env = make(num_worlds=2)
    env.reset(seed=0)
    pos = MIDDLE[None].repeat(2, 1, 1)
    pos[:, 0] = torch.tensor([-1.75, 0.9])  # below dirty column 0, facing it
    dirt = torch.zeros(2, D, dtype=torch.bool)
    dirt[:, :3] = True  # world 0: 3 dirty cells, a fraction 0.1875 < 0.2
    dirt[1, 3] = True  # world 1: 4, 0.25 >= 0.2
    place(env, pos, dirt=dirt)
    actions = clean_up.cooperator(env)
    assert torch.equal(actions[0], clean_up.free_rider(env)[0])
    assert torch.equal(actions[1], clean_up.cleaner(env)[1]) and actions[1, 0] == clean_up.CLEAN
    assert not torch.equal(actions[0], actions[1])
    env.close()
