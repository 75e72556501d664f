"""The matrix task (envs/matrix.py): inventories as mixed strategies, paired by an interaction beam."""
from __future__ import annotations

import math

import pytest
import torch

from marl_render.envs import env_class, make_env
from marl_render.envs.matrix import GAMES, MatrixParams

FAR = (2.2, 2.2)  # where the tests put every resource: out of the agents' reach


def staged(env, pos, yaw, inventory, seed=0):
    """The env reset, then its agents at pos [A, 2] facing yaw [A] with `inventory` [A, K] in world 0
    and every resource far away; returns the state."""
    env.reset(seed=seed)
    state = env.get_state()
    A = env.num_agents
    state["pos"][0, :A] = torch.tensor(pos, dtype=state["pos"].dtype)
    state["vel"].zero_()
    state["yaw"][0] = torch.tensor(yaw, dtype=state["yaw"].dtype)
    state["inventory"][0] = torch.tensor(inventory)
    state["resources"][:] = torch.tensor(FAR)
    env.set_state(state)
    return state


def test_payoffs_are_the_matrix_game_of_the_two_inventories():
    """Prisoner's dilemma A = [[3, 0], [5, 1]]. Agent 0 (row, it beams) holds (3, 1): p = (.75, .25);
    agent 1 holds (1, 1): q = (.5, .5). Row: p A q = .75 * 1.5 + .25 * 3 = 1.875; column: q A p =
    .5 * 2.25 + .5 * 4 = 3.125. Both leave play with empty inventories and keep the other's."""
    with make_env("matrix", num_worlds=1, num_agents=2, resolution=8, episode_end=False) as env:
        staged(env, [(0.0, 0.0), (0.0, 0.8)], [0.0, 0.0], [[3, 1], [1, 1]])
        obs, reward, _, _, info = env.step(torch.tensor([[5, 0]]))
        assert reward.tolist() == [[1.875, 3.125]]
        assert info["interactions"].tolist() == [1]
        sim = env.sim
        assert sim.inventory.tolist() == [[[0, 0], [0, 0]]] and sim.partner.tolist() == [[[1, 1], [3, 1]]]
        assert sim.timeout.tolist() == [[5, 5]] and sim.shown.tolist() == [[False, False]]
        assert obs["inventory"].tolist() == [[[0.0, 0.0], [0.0, 0.0]]]
        # the social outcomes of this one-step episode: 5.0 in all, 1 - 2.5 / 20, earned at step 1, nobody in play
        assert info["efficiency"].tolist() == [5.0] and info["equality"].tolist() == [0.875]
        assert info["sustainability"].tolist() == [1.0] and info["peace"].tolist() == [0.0]
        assert obs["action_mask"][0, :, 1:].any().item() is False  # out of play: only noop


def test_the_beaming_agent_is_the_row_player_of_an_asymmetric_game():
    """Battle of the sexes, both holding only kind 0: the row player gets A[0][0] = 3, the column B[0][0] = 2."""
    with make_env("matrix", num_worlds=1, num_agents=2, resolution=8, game="battle_of_the_sexes",
                  episode_end=False) as env:
        staged(env, [(0.0, 0.8), (0.0, 0.0)], [math.pi, 0.0], [[2, 0], [1, 0]])
        _, reward, _, _, _ = env.step(torch.tensor([[5, 0]]))  # agent 0 faces -y, towards agent 1
        assert reward.tolist() == [[3.0, 2.0]]


def test_each_agent_meets_one_partner_and_the_shortest_beam_wins():
    """Agents 0 and 2 both beam agent 1 (0.5 m and 0.6 m away): 0 and 1 pair; 2 keeps its inventory.
    An agent with an empty inventory can neither beam nor be beamed."""
    with make_env("matrix", num_worlds=1, num_agents=4, resolution=8, episode_end=False) as env:
        staged(env, [(0.0, 0.0), (0.0, 0.5), (0.0, 1.1), (1.5, 0.0)], [0.0, 0.0, math.pi, math.pi / 2],
               [[1, 0], [1, 0], [0, 1], [0, 0]])
        _, reward, _, _, info = env.step(torch.tensor([[5, 0, 5, 0]]))
        assert reward.tolist() == [[3.0, 3.0, 0.0, 0.0]] and info["interactions"].tolist() == [1]
        assert env.sim.inventory[0, 2].tolist() == [0, 1]
    with make_env("matrix", num_worlds=1, num_agents=2, resolution=8, episode_end=False) as env:
        staged(env, [(0.0, 0.0), (0.0, 0.8)], [0.0, 0.0], [[1, 0], [0, 0]])
        _, reward, _, _, info = env.step(torch.tensor([[5, 0]]))
        assert reward.tolist() == [[0.0, 0.0]] and info["interactions"].tolist() == [0]


def test_walking_over_a_resource_collects_it_and_it_regrows():
    with make_env("matrix", num_worlds=1, num_agents=2, resolution=8, regrow_steps=3, episode_end=False) as env:
        state = staged(env, [(0.0, 0.0), (-1.5, -1.5)], [0.0, 0.0], [[0, 0], [0, 0]])
        state["resources"][0, 6] = torch.tensor([0.0, 0.1])  # resource 6: kind 1 (6 of each kind), under agent 0
        env.set_state(state)
        _, _, _, _, info = env.step(torch.zeros(1, 2, dtype=torch.int64))
        assert info["collected"].tolist() == [1] and env.sim.inventory[0, 0].tolist() == [0, 1]
        assert env.sim.regrow[0, 6].item() == 3
        for _ in range(3):
            env.step(torch.zeros(1, 2, dtype=torch.int64))
        assert env.sim.regrow[0, 6].item() == 0 and env.sim.inventory[0, 0].tolist() == [0, 1]  # back
        env.step(torch.zeros(1, 2, dtype=torch.int64))  # agent 0 still stands on it: collected again
        assert env.sim.inventory[0, 0].tolist() == [0, 2] and env.sim.regrow[0, 6].item() == 3


def test_games_user_payoffs_and_the_repeated_variant():
    assert set(GAMES) == {"prisoners_dilemma", "stag_hunt", "chicken", "pure_coordination", "battle_of_the_sexes",
                          "rock_paper_scissors"}
    assert MatrixParams(payoff=((4, 0), (5, 1))).matrices() == (((4.0, 0.0), (5.0, 1.0)), ((4.0, 5.0), (0.0, 1.0)))
    pair = (((1, 0), (0, 2)), ((2, 0), (0, 1)))
    assert MatrixParams(payoff=pair).matrices() == (((1.0, 0.0), (0.0, 2.0)), ((2.0, 0.0), (0.0, 1.0)))
    with pytest.raises(ValueError, match="game must be one of"):
        MatrixParams(game="poker")
    with pytest.raises(ValueError, match=r"payoff must be a K x K matrix .* got \(\(1, 2\), \(3,\)\)"):
        MatrixParams(payoff=((1, 2), (3,)))
    with pytest.raises(ValueError, match="payoff must be a K x K matrix"):
        MatrixParams(payoff=((1.0, math.nan), (0.0, 1.0)))
    with pytest.raises(ValueError, match="same size K, got 2 and 3"):
        MatrixParams(payoff=(((1, 0), (0, 1)), ((1, 0, 0), (0, 1, 0), (0, 0, 1))))
    with pytest.raises(ValueError, match="num_agents must be 2"):
        make_env("matrix", num_worlds=1, resolution=8, repeated=True, num_agents=4)
    with make_env("matrix", num_worlds=2, resolution=8, game="rock_paper_scissors") as env:
        assert env.num_agents == 8 and env.spec.observations["inventory"].shape == (3,)
        assert env.reset()["inventory"].shape == (2, 8, 3)
    with make_env("matrix", num_worlds=1, resolution=8, repeated=True) as env:
        assert env.num_agents == 2


def test_heuristic_beats_random_and_the_bots_play_their_kinds():
    """Over 4 worlds and 60 steps: the heuristic (cooperators) earns more than random play; the
    defector bots hold only kind 1, the cooperators only kind 0 (whatever they bumped into aside)."""
    bots = env_class("matrix").bots
    returns = {}
    for policy in ("heuristic", "random"):
        with make_env("matrix", num_worlds=4, resolution=8, seed=0, max_steps=60, episode_end=False) as env:
            env.reset()
            total = 0.0
            for _ in range(60):
                actions = env.heuristic_actions() if policy == "heuristic" else env.random_actions()
                total += float(env.step(actions)[1].sum())
            returns[policy] = total
    assert returns["heuristic"] > returns["random"] + 10
    for name, kind in (("cooperator", 0), ("defector", 1)):
        with make_env("matrix", num_worlds=2, resolution=8, seed=1, episode_end=False) as env:
            env.reset()
            held = torch.zeros(2, dtype=torch.int64)
            for _ in range(25):
                before = env.sim.inventory
                env.step(bots[name].script(env))
                held += (env.sim.inventory - before).clamp_min(0).sum((0, 1))
            assert held[kind] > held[1 - kind], (name, held)


def test_declarations():
    cls = env_class("matrix")
    assert cls.mixed_motive and cls.schelling == ("cooperator", "defector")
    assert {"cooperator", "defector", "reciprocator"} <= set(cls.bots) and len(cls.heldout) >= 3
    assert all(set(h.bots_by_role["agents"]) <= {n for n, b in cls.bots.items() if b.population == "test"}
               for h in cls.heldout)
    assert cls.card and set(cls.difficulties) == {"easy", "medium", "hard"}
    assert cls.episode_end_description().startswith("random (Melting Pot's): at least 150 steps")
