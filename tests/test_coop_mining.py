"""Tests for envs/coop_mining.py: a stag hunt in space (iron alone, gold in pairs)."""
from __future__ import annotations

import math

import pytest
import torch

from marl_render.envs import coop_mining, list_envs, make_env
from marl_render.envs.roster import Bot, HeldOut

S = coop_mining.NUM_IRON + coop_mining.NUM_GOLD
IRON, GOLD = 0, coop_mining.NUM_IRON  # the first iron site, the first gold site
# Sites: iron 0 at (-1, 0), gold 8 at (1, 0); the others along y = -1.7, far from everyone.
SITES = torch.stack((torch.linspace(-1.8, 1.8, S), torch.full((S,), -1.7)), -1)
SITES[IRON], SITES[GOLD] = torch.tensor([-1.0, 0.0]), torch.tensor([1.0, 0.0])
# Six agents along y = 1.5, facing +y, away from every site.
TOP = torch.stack((torch.linspace(-1.5, 1.5, 6), torch.full((6,), 1.5)), -1)
# Three places 0.3 m from gold 8, each facing it: below, above and to the right of it.
AT_GOLD = torch.tensor([[1.0, -0.3], [1.0, 0.3], [1.3, 0.0]])
FACING_GOLD = torch.tensor([0.0, math.pi, math.pi / 2])


def make(**kwargs):
    return make_env("coop_mining", **{"num_worlds": 2, "resolution": 8, "seed": 0, **kwargs})


def place(env, miners=0, at_iron=False, **fields):
    """Sites at SITES, all present; agents along TOP, except the first `miners` at AT_GOLD facing gold 8
    (or agent 0 0.3 m below iron 0, facing it)."""
    W = env.num_worlds
    pos, yaw = TOP.expand(W, -1, -1).clone(), torch.zeros(W, 6)
    pos[:, :miners], yaw[:, :miners] = AT_GOLD[:miners], FACING_GOLD[:miners]
    if at_iron:
        pos[:, 0] = torch.tensor([-1.0, -0.3])
    state = env.get_state()
    state.update(pos=pos, vel=torch.zeros_like(pos), yaw=yaw, ores=SITES.expand(W, -1, -1).clone(),
                 timer=torch.zeros(W, S, dtype=torch.int64), pending=torch.zeros(W, S, 6, dtype=torch.int64), **fields)
    env.set_state(state)


def mine(env, *agents):
    a = torch.zeros(env.num_worlds, env.num_agents, dtype=torch.long)
    a[:, list(agents)] = coop_mining.MINE
    return a


def per_agent(env, values: dict) -> torch.Tensor:
    want = torch.zeros(env.num_worlds, env.num_agents)
    for agent, value in values.items():
        want[:, agent] = value
    return want


def test_layout_spaces_state_size_info_and_registry():
    assert "coop_mining" in list_envs()
    env = make(state_obs=True)
    N = env.num_agents
    assert N == 6 and env.num_actions == 6 and env.action_meanings[5] == "mine"
    assert env.state_dim == 6 + 6 * S + 2 * (N - 1)
    assert env.scenario.is_gold.tolist() == [False] * 8 + [True] * 6
    obs = env.reset(seed=1)
    assert obs["state"].shape == (2, N, env.state_dim)
    _, reward, _, _, info = env.step(env.random_actions(torch.Generator().manual_seed(0)))
    assert reward.shape == (2, N) and reward.dtype == torch.float32
    for key in ("iron", "gold", "gold_lost", "ores_left"):
        assert info[key].shape == (2,) and info[key].dtype == torch.int64, key
    assert coop_mining.CoopMining.mixed_motive is True
    assert not env.scenario.tagged_out(env.sim).any() and env.scenario.tagged_out(env.sim).shape == (2, N)
    env.close()
    with make(continuous=True) as env:
        assert env.action_dim == 3


@pytest.mark.parametrize("kwargs, error, word", [
    ({"gold_reward": 0.0}, ValueError, "gold_reward"), ({"gold_reward": 1e39}, ValueError, "gold_reward"),
    ({"gold_window": 0}, ValueError, "gold_window"), ({"gold_window": 2.5}, TypeError, "gold_window"),
    ({"respawn_delay": -1}, ValueError, "respawn_delay"), ({"num_agents": 13}, ValueError, "num_agents")])
def test_bad_keywords_are_refused_by_name(kwargs, error, word):
    with pytest.raises(error, match=word):
        make(**kwargs)


def test_iron_pays_one_to_its_miner_alone_and_comes_back_later():
    env = make(respawn_delay=2)
    env.reset(seed=0)
    place(env, at_iron=True)
    _, reward, _, _, info = env.step(mine(env, 0, 3))  # agent 3 strikes at nothing
    assert torch.equal(reward, per_agent(env, {0: 1.0})) and info["iron"].tolist() == [1, 1]
    assert env.sim.timer[:, IRON].tolist() == [2, 2] and env.sim.iron[:, 0].tolist() == [1, 1]
    _, reward, _, _, _ = env.step(mine(env, 0))
    assert not reward.any()  # gone
    env.step(mine(env))
    assert env.sim.timer[:, IRON].tolist() == [0, 0]  # back
    env.close()


def test_gold_pays_each_of_two_miners_within_the_window_and_nothing_to_one_alone():
    env = make(gold_window=3, gold_reward=4.0)
    env.reset(seed=0)
    place(env, miners=2)
    for _ in range(4):  # one agent alone: nothing, however long it strikes
        _, reward, _, _, info = env.step(mine(env, 0))
        assert not reward.any() and info["gold"].sum() == 0
        assert env.sim.pending[:, GOLD, 0].tolist() == [3, 3] and env.sim.timer[:, GOLD].sum() == 0
    env.step(mine(env))
    _, reward, _, _, info = env.step(mine(env, 1))  # two steps after agent 0's last strike: within 3
    assert torch.equal(reward, per_agent(env, {0: 4.0, 1: 4.0})) and info["gold"].tolist() == [1, 1]
    assert env.sim.gold[:, :2].tolist() == [[1, 1]] * 2 and env.sim.timer[:, GOLD].tolist() == [20, 20]
    assert not env.sim.pending.any()
    # Three steps apart is too late: agent 0's strike has lapsed.
    place(env, miners=2)
    env.step(mine(env, 0))
    env.step(mine(env))
    env.step(mine(env))
    _, reward, _, _, info = env.step(mine(env, 1))
    assert not reward.any() and env.sim.pending[:, GOLD, :2].tolist() == [[0, 3]] * 2
    env.close()


def test_three_miners_crumble_gold_for_everyone():
    env = make()
    env.reset(seed=0)
    place(env, miners=3)
    _, reward, _, _, info = env.step(mine(env, 0, 1, 2))
    assert not reward.any() and info["gold_lost"].tolist() == [1, 1] and info["gold"].sum() == 0
    assert env.sim.timer[:, GOLD].tolist() == [20, 20] and not env.sim.pending.any()
    place(env, miners=3)  # one first, then two more in one step: three pending at once
    env.step(mine(env, 0))
    _, reward, _, _, info = env.step(mine(env, 1, 2))
    assert not reward.any() and info["gold_lost"].tolist() == [1, 1]
    env.close()


def test_pending_strikes_that_break_the_rules_are_refused_by_set_state():
    env = make()
    env.reset(seed=0)
    state = env.get_state()
    state["pending"][0, IRON, 0] = 1
    with pytest.raises(ValueError, match="pending"):
        env.set_state(state)
    state = env.get_state()
    state["pending"][0, GOLD, :2] = 1
    with pytest.raises(ValueError, match="pending"):
        env.set_state(state)
    env.close()


def test_gold_is_seen_yellow_and_turns_pale_while_a_strike_is_pending():
    env = make(num_worlds=1, resolution=32)
    env.reset(seed=0)
    place(env, miners=2)
    pixels = env.step(mine(env))[0]["pixels"][0, 1]  # agent 1 looks down at gold 8 from 0.3 m
    r, g, b = pixels[24:27, 14:19].to(torch.int32).unbind(-1)  # the rock, low in the middle of the view
    assert ((r > 180) & (g > 140) & (b < 40)).all()  # gold yellow
    assert (pixels[24:27, :8] == pixels[24, 0]).all()  # plain floor beside it
    pixels = env.step(mine(env, 0))[0]["pixels"][0, 1]
    r, g, b = pixels[24:27, 14:19].to(torch.int32).unbind(-1)
    assert ((r > 180) & (g > 160) & (b > 100)).all()  # pale: agent 0's strike is pending
    env.close()


def test_the_heuristic_earns_far_more_than_random_play_and_than_iron_alone():
    env = make(num_worlds=4, max_steps=60)
    returns = {}
    for policy in ("heuristic", "random", "iron"):
        env.reset(seed=4)
        g, total = torch.Generator().manual_seed(0), 0.0
        for _ in range(60):
            act = {"heuristic": env.heuristic_actions, "random": lambda g=g: env.random_actions(g),
                   "iron": lambda: coop_mining.iron_miner(env)}[policy]()
            total += float(env.step(act)[1].sum())
        returns[policy] = total
    assert returns["heuristic"] > 5 * max(returns["random"], 1.0) and returns["heuristic"] > returns["iron"], returns
    env.close()


def test_the_bots_mine_as_described():
    env = make(num_worlds=1)
    env.reset(seed=0)
    place(env, miners=2)
    seeker = coop_mining.gold_seeker(env)
    assert seeker[0, :2].tolist() == [coop_mining.MINE] * 2  # at gold, facing it: strike
    assert (coop_mining.iron_miner(env)[0, :2] != coop_mining.MINE).all()  # gold is not theirs
    place(env, at_iron=True)
    assert coop_mining.iron_miner(env)[0, 0] == coop_mining.MINE
    assert coop_mining.gold_seeker(env)[0, 0] != coop_mining.MINE
    with make(num_worlds=1, continuous=True) as twin:
        twin.reset(seed=0)
        place(twin, at_iron=True)
        assert coop_mining.iron_miner(twin)[0, 0].tolist() == [0.0, 0.0, 1.0]
    env.close()


def test_the_heuristic_pairs_up_on_one_gold_and_mines_it():
    env = make(num_worlds=1)
    env.reset(seed=0)
    place(env, miners=2)
    _, reward, _, _, info = env.step(env.heuristic_actions())
    assert reward[0, :2].tolist() == [4.0, 4.0] and info["gold"].item() == 1


def test_the_roster_declares_test_bots_for_three_tagged_scenarios():
    task = coop_mining.CoopMining
    assert all(isinstance(bot, Bot) for bot in task.bots.values()) and task.card
    assert {name for name, bot in task.bots.items() if bot.population == "test"} >= {"iron_miner", "gold_seeker"}
    assert len(task.heldout) >= 3 and all(isinstance(h, HeldOut) for h in task.heldout)
    tags = set()
    for held in task.heldout:
        assert held.focal and all(name in coop_mining.numbered("agent", held.num_agents) for name in held.focal)
        assert all(task.bots[b].population == "test" for names in held.bots_by_role.values() for b in names)
        tags.add("resident" if 2 * len(held.focal) > held.num_agents else "visitor")
    assert tags == {"resident", "visitor"}


def test_appearance_changes_the_look_not_the_layout_and_gold_stays_yellow():
    with make(num_worlds=2, resolution=32, seed=5) as plain, \
            make(num_worlds=2, resolution=32, seed=5, appearance="heldout") as looked:
        plain.reset(), looked.reset()
        assert torch.equal(plain.sim.pos, looked.sim.pos) and torch.equal(plain.sim.ores, looked.sim.ores)
        views = []
        for env in (plain, looked):
            place(env, miners=2)
            views.append(env.step(mine(env))[0]["pixels"][:, 1])
        assert not torch.equal(views[0], views[1])
        r, g, b = views[1][:, 25:28, 15:18].to(torch.int32).unbind(-1)  # inside the rock despite camera jitter
        assert ((r > b + 60) & (g > b + 60)).all()  # the gold rock, hue-shifted a little, still yellow
