"""Tests for envs/territory.py: claims painted with a beam, paid each step, overpainted, defended by zaps."""
import types

import pytest
import torch

from marl_render.envs import make_env
from marl_render.envs import territory as tr
from marl_render.threads import limited_threads

W, RES = 2, 16
# Agent 0 in the middle room at (-0.25, -0.25), the centre of cell 65 (row 5, column 5), facing +y:
# its beam reaches the cell above, 77. Agent 1 further up in that room, agent 2 in a corner room.
START = torch.tensor([[-0.25, -0.25], [-0.25, 0.75], [2.0, 2.0]])
HERE, AHEAD = 65, 77


def make(**kwargs):
    return make_env("territory", **{"num_worlds": W, "resolution": RES, "seed": 0, "num_agents": 3, **kwargs})


def act(env, **who):
    """Noop for all, `paint` / `zap` / `forward` for the listed agents."""
    a = torch.zeros(env.num_worlds, env.num_agents, dtype=torch.long)
    for what, agents in who.items():
        a[:, list(agents)] = {"paint": tr.PAINT, "zap": tr.ZAP, "forward": 1}[what]
    return a


def place(env, pos=START, yaw=(0.0, 0.0, 0.0), **fields):
    """Agents at rest at pos facing yaw, every wall slot closed with its door 0.5 m off its middle."""
    state = env.get_state()
    pos = pos.expand(env.num_worlds, -1, -1).clone()
    closed = torch.zeros(env.num_worlds, 12, dtype=torch.bool)
    state.update(pos=pos, vel=torch.zeros_like(pos), yaw=torch.tensor(yaw).expand(env.num_worlds, -1).clone(),
                 door=torch.full((env.num_worlds, 12), 0.5), wall_open=closed, **fields)
    env.set_state(state)


def test_the_beam_paints_the_cell_ahead_and_held_cells_pay_each_step():
    env = make(claim_reward=0.5)
    env.reset()
    place(env)
    _, reward, terminated, _, info = env.step(act(env, paint=[0]))
    assert (env.sim.owner >= 0).nonzero()[:, 1].tolist() == [AHEAD] * W and env.sim.owner[:, AHEAD].tolist() == [0] * W
    assert reward.tolist() == [[0.5, 0.0, 0.0]] * W and info["painted"].tolist() == [1] * W
    assert info["claimed"].tolist() == [1] * W and not terminated.any()
    owner = torch.full((W, tr.C), -1)
    owner[:, :5], owner[:, 100:103] = 0, 1  # 5 cells of agent 0, 3 of agent 1: paid every step, no beam
    place(env, owner=owner)
    for _ in range(2):
        _, reward, _, _, info = env.step(act(env))
        assert reward.tolist() == [[2.5, 1.5, 0.0]] * W and info["painted"].tolist() == [0] * W
    env.close()


def test_claims_are_overpainted_and_the_lowest_index_wins_a_cell():
    env = make(claim_reward=0.25)
    env.reset()
    owner = torch.full((W, tr.C), -1)
    owner[:, AHEAD] = 1
    place(env, owner=owner)
    _, reward, _, _, info = env.step(act(env, paint=[0]))
    assert env.sim.owner[:, AHEAD].tolist() == [0] * W and info["painted"].tolist() == [1] * W
    assert reward[:, :2].tolist() == [[0.25, 0.0]] * W
    # Agent 1 on the cell two above, facing down: both beams reach cell 77; agent 0 keeps it.
    owner[:, AHEAD] = -1
    place(env, torch.tensor([[-0.25, -0.25], [-0.25, 0.75], [2.0, 2.0]]), (0.0, 3.14159, 0.0), owner=owner)
    env.step(act(env, paint=[0, 1]))
    assert env.sim.owner[:, AHEAD].tolist() == [0] * W and (env.sim.owner >= 0).sum().item() == W
    env.close()


def test_a_wall_stops_the_beams():
    env = make()
    env.reset()
    # Agent 0 just below the wall between the middle room and the one above (y = 1), facing it; agent 1
    # beyond it, 0.8 m away; the door is off the line between them.
    place(env, torch.tensor([[0.0, 0.75], [0.0, 1.55], [2.0, -2.0]]), (0.0, 0.0, 0.0))
    _, _, _, _, info = env.step(act(env, paint=[0]))
    assert info["painted"].tolist() == [0] * W  # the point 0.45 m ahead lies behind the wall
    env.step(act(env, zap=[0]))
    assert env.sim.hits.sum().item() == 0
    env.close()


def test_two_zaps_remove_an_agent_for_the_rest_of_the_episode():
    env = make(zap_cooldown=3, claim_reward=0.25, state_obs=True)
    env.reset()
    owner = torch.full((W, tr.C), -1)
    owner[:, 140:144] = 1  # agent 1 holds 4 cells
    place(env, owner=owner)
    _, reward, terminated, _, info = env.step(act(env, zap=[0]))
    assert env.sim.hits.tolist() == [[0, 1, 0]] * W and info["zaps"].tolist() == [1] * W and not terminated.any()
    assert env.sim.cooldown[:, 0].tolist() == [3] * W and reward[:, 1].tolist() == [1.0] * W
    marks = env.renderer.instance_state("marks")["active"]
    assert marks.tolist() == [[False, True, False]] * W  # the first hit shows over its head
    mask = env.step(act(env, zap=[0]))[0]["action_mask"]  # cooling down: this zap does not fire
    assert env.sim.hits[:, 1].tolist() == [1] * W and not mask[:, 0, tr.ZAP].any() and mask[:, 1, tr.ZAP].all()
    env.step(act(env))
    env.step(act(env))
    assert not env.scenario.tagged_out(env.sim).any()
    _, reward, terminated, _, info = env.step(act(env, zap=[0]))
    assert terminated.tolist() == [[False, True, False]] * W and info["removed"].tolist() == [1] * W
    assert env.scenario.tagged_out(env.sim).tolist() == [[False, True, False]] * W
    assert reward[:, 1].tolist() == [0.0] * W and env.alive.tolist() == [[True, False, True]] * W
    assert not env.renderer.instance_state("agents")["active"][:, 1].any()  # no longer drawn
    for _ in range(2):  # its cells stay painted and pay nobody; it is gone for the episode
        _, reward, terminated, _, info = env.step(act(env, forward=[1]))
        assert reward[:, 1].tolist() == [0.0] * W and (env.sim.owner == 1).sum(-1).tolist() == [4] * W
        assert env.alive[:, 1].tolist() == [False] * W and info["removed"].tolist() == [1] * W
    env.close()


def test_paint_is_drawn_in_the_painters_colour_on_the_floor_ahead():
    env = make(resolution=24)
    env.reset()
    place(env)
    before = env.step(act(env))[0]["pixels"]
    after = env.step(act(env, paint=[0]))[0]["pixels"]
    bottom = (slice(None), 0, slice(20, 24), slice(8, 16))  # agent 0's view: the floor just ahead
    r, g, b = after[bottom].to(torch.int32).unbind(-1)
    assert ((r - g > 40) & (r - b > 40)).all()  # agent 0's paint: a light red
    r, g, b = before[bottom].to(torch.int32).unbind(-1)
    assert not ((r - g > 40) & (r - b > 40)).any()
    assert torch.equal(env.renderer.instance_state("paint")["active"], env.sim.owner >= 0)
    env.close()


@limited_threads(1)
def returns(policy, worlds=8, steps=80, **kwargs):
    """The collective return per world over `steps` steps of the rules alone (no rendering), every slot
    played by `policy`: "heuristic", "random" or a bot's script."""
    env = make_env("territory", num_worlds=worlds, resolution=8, seed=0, levels=100, **kwargs)
    env.reset()
    s, state = env.scenario, env.sim
    alive = torch.ones(worlds, env.num_agents, dtype=torch.bool)
    generator = torch.Generator().manual_seed(0)
    total = torch.zeros(worlds)
    zaps = 0
    for _ in range(steps):
        if policy == "heuristic":
            actions = s.heuristic(state, alive)
        elif policy == "random":
            actions = torch.randint(env.num_actions, alive.shape, generator=generator)
        else:
            view = types.SimpleNamespace(scenario=s, sim=state, alive=alive, num_agents=env.num_agents,
                                         num_worlds=worlds, device=env.device)
            actions = policy(view)
        zaps += int((actions == tr.ZAP).sum())
        step = s.step(state, actions, alive, generator)
        state, total = step.state, total + (step.reward * alive).sum(-1)
        alive = alive & ~step.terminated
    env.close()
    return total, state, zaps


def test_the_heuristic_claims_far_more_than_random():
    heuristic, state, _ = returns("heuristic", worlds=6, steps=60)
    random, _, _ = returns("random", worlds=6, steps=60)
    assert heuristic.min() > 2 * random.max()  # in every world (measured: 32 to 36, random 7 to 11)
    assert (state.owner >= 0).sum(-1).min() > 80  # measured: 98 to 103 of the 144 cells after 60 steps


@pytest.mark.parametrize("bot", ["painter", "zapper", "defender"])
def test_the_test_bots_play_as_described(bot):
    total, state, zaps = returns(getattr(tr, bot), worlds=4, steps=40)
    if bot == "painter":
        assert zaps == 0 and (state.hits == 0).all() and (state.owner >= 0).sum(-1).min() > 60
    elif bot == "zapper":
        assert (~state.shown).sum() >= 4  # it removes agents
    else:
        assert (state.owner >= 0).sum(-1).min() > 60
        room = tr.room_of(state.pos[:, :9])
        assert (room.sort(-1).values == torch.arange(9)).all()  # each stays in its own room
