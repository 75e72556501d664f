"""Tests for envs/cooking.py: collaborative cooking (dispensers, pots, dishes, delivery of the recipe)."""
import math
import types
from collections import deque

import pytest
import torch

from marl_render.envs import cooking as ck
from marl_render.envs import make_env
from marl_render.threads import limited_threads

W, RES = 2, 16
UP, DOWN, LEFT, RIGHT = 0.0, math.pi, math.pi / 2, -math.pi / 2  # yaw facing +y, -y, -x, +x
# The cramped room centred in the 9 x 5 grid: cells by index (row * 9 + column).
POT, ONION_BOX, TOMATO_BOX, DISHES, SERVE, COUNTER = 4, 11, 15, 30, 32, 31
BELOW_POT, RIGHT_OF_ONIONS, LEFT_OF_TOMATOES, ABOVE_DISHES, MIDDLE, ABOVE_SERVE = 13, 12, 14, 21, 22, 23


def make(**kwargs):
    return make_env("cooking", **{"num_worlds": W, "resolution": RES, "seed": 0, "cook_time": 3, **kwargs})


def interact(env, who=(0,)):
    a = torch.zeros(env.num_worlds, env.num_agents, dtype=torch.long)
    a[:, list(who)] = ck.INTERACT
    return a


def place(env, cells, yaws, **fields):
    """Agents at rest on the centres of `cells` (one per agent) facing `yaws`, other fields as given."""
    state = env.get_state()
    pos = env.scenario.centres[torch.tensor(cells)].expand(env.num_worlds, -1, -1)
    state.update(pos=pos.clone(), vel=torch.zeros_like(pos), yaw=torch.tensor(yaws).expand(env.num_worlds, -1).clone(),
                 **fields)
    env.set_state(state)


def test_the_cramped_room_is_parsed_into_the_grid():
    env = make()
    env.reset()
    cells = env.sim.cells[0]
    assert cells[POT] == ck.POT and cells[ONION_BOX] == ck.ONION_BOX and cells[TOMATO_BOX] == ck.TOMATO_BOX
    assert cells[DISHES] == ck.DISHES and cells[SERVE] == ck.SERVE and cells[COUNTER] == ck.COUNTER
    assert (cells == ck.FLOOR).nonzero().flatten().tolist() == [12, 13, 14, 21, 22, 23]
    start = env.scenario.centres[torch.tensor([21, 14])]
    assert torch.allclose(env.sim.pos[0], start)  # agent 0 on mark 1, agent 1 on mark 2
    assert env.state_dim == 748 and env.num_actions == 6 and env.action_meanings[5] == "interact"
    env.close()
    with make(state_obs=True, num_agents=3) as env:
        assert env.reset()["state"].shape == (W, 3, 738 + 20)


def test_bad_keywords_are_refused_by_name():
    for kwargs, error, words in [({"kitchen": "galley"}, ValueError, "kitchen must be one of"),
                                 ({"num_ingredients": 3}, ValueError, "num_ingredients must be 1 or 2"),
                                 ({"cook_time": 0}, ValueError, "cook_time"),
                                 ({"delivery_reward": -1.0}, ValueError, "delivery_reward"),
                                 ({"recipe_view": "two"}, ValueError, "recipe_view must be"),
                                 ({"recipe_view": "one", "num_agents": 3}, ValueError, "recipe_view='one' needs"),
                                 ({"num_agents": 5}, ValueError, "num_agents")]:
        with pytest.raises(error, match=words):
            make(**kwargs)


def test_a_soup_from_dispenser_to_delivery():
    env = make(num_agents=1)
    env.reset()
    place(env, [RIGHT_OF_ONIONS], [LEFT], recipe=torch.tensor([0, 1]))
    env.step(interact(env))
    assert env.sim.held[:, 0].tolist() == [ck.ONION] * W
    place(env, [BELOW_POT], [UP], pot=env.sim.pot.index_put((torch.arange(W), torch.full((W,), POT)),
                                                            torch.tensor([2, 0])))
    _, reward, _, _, _ = env.step(interact(env))  # the third onion: the pot is full and starts cooking
    assert env.sim.held[:, 0].tolist() == [ck.EMPTY] * W and env.sim.pot[:, POT].tolist() == [[3, 0]] * W
    assert env.sim.cook[:, POT].tolist() == [0] * W and reward.abs().sum() == 0
    place(env, [ABOVE_DISHES], [DOWN])
    env.step(interact(env))  # a dish; the pot cooks meanwhile
    assert env.sim.held[:, 0].tolist() == [ck.DISH] * W and env.sim.cook[:, POT].tolist() == [1] * W
    place(env, [BELOW_POT], [UP])
    env.step(interact(env))  # cooked for 2 of 3 steps: plating fails
    assert env.sim.held[:, 0].tolist() == [ck.DISH] * W and env.sim.cook[:, POT].tolist() == [2] * W
    env.step(interact(env))
    assert env.sim.held[:, 0].tolist() == [ck.SOUP] * W  # onion soup (no tomato) on the dish
    assert env.sim.pot[:, POT].tolist() == [[0, 0]] * W and env.sim.cook[:, POT].tolist() == [0] * W
    place(env, [ABOVE_SERVE], [DOWN])
    _, reward, terminated, _, info = env.step(interact(env))
    # World 0's recipe is onion soup: it pays; world 1 wanted one tomato: a wrong soup pays nothing.
    assert reward[:, 0].tolist() == [20.0, 0.0] and not terminated.any()
    assert info["delivered"].tolist() == [1, 0] and info["wrong"].tolist() == [0, 1]
    assert info["served"].tolist() == [1, 0] and env.sim.held[:, 0].tolist() == [ck.EMPTY] * W
    env.close()


def test_the_delivery_pays_every_agent_and_only_the_recipe_counts():
    env = make(delivery_reward=5.0)
    env.reset()
    place(env, [ABOVE_SERVE, MIDDLE], [DOWN, UP], held=torch.tensor([[ck.SOUP + 2, 0], [ck.SOUP + 1, 0]]),
          recipe=torch.tensor([2, 2]))
    _, reward, _, _, info = env.step(interact(env))
    assert reward.tolist() == [[5.0, 5.0], [0.0, 0.0]] and info["wrong"].tolist() == [0, 1]
    env.close()


def test_counters_hold_items_and_one_agent_acts_on_a_cell_per_step():
    env = make()
    env.reset()
    # Agent 0 on cell 22 faces the plain counter below it: it puts its tomato down, then takes it back.
    place(env, [MIDDLE, BELOW_POT], [DOWN, UP], held=torch.tensor([[ck.TOMATO, 0]] * W))
    env.step(interact(env))
    assert env.sim.item[:, COUNTER].tolist() == [ck.TOMATO] * W and env.sim.held[:, 0].tolist() == [0] * W
    env.step(interact(env))
    assert env.sim.item[:, COUNTER].tolist() == [0] * W and env.sim.held[:, 0].tolist() == [ck.TOMATO] * W
    # Two agents at the onion dispenser's cell in the same step: agent 0 takes an onion, agent 1 nothing.
    place(env, [RIGHT_OF_ONIONS, RIGHT_OF_ONIONS], [LEFT, LEFT], held=torch.zeros(W, 2, dtype=torch.long))
    env.step(interact(env, who=(0, 1)))
    assert env.sim.held.tolist() == [[ck.ONION, 0]] * W
    env.close()


def test_a_tomato_in_the_hands_is_red_in_the_middle_of_the_view():
    env = make(resolution=24)
    env.reset()
    place(env, [MIDDLE, ABOVE_DISHES], [UP, UP], held=torch.tensor([[ck.TOMATO, ck.EMPTY]] * W))
    pixels = env.step(torch.zeros(W, 2, dtype=torch.long))[0]["pixels"].to(torch.int32)  # [W, A, H, W, 3]
    r, g, b = pixels[:, :, 12, 12].unbind(-1)
    assert ((r - g > 100) & (r - b > 100))[:, 0].all()  # agent 0 sees its tomato
    assert not ((r - g > 100) & (r - b > 100))[:, 1].any()  # agent 1's hands are empty
    env.close()


def recipe_pixels(recipe_view):
    """Both agents look at the delivery point (the recipe's balls float over it): their views."""
    env = make(resolution=32, recipe_view=recipe_view, state_obs=True)
    env.reset()
    place(env, [MIDDLE, MIDDLE + 1], [DOWN, DOWN], recipe=torch.tensor([0, 3]))
    obs = env.step(torch.zeros(W, 2, dtype=torch.long))[0]
    env.close()
    return obs["pixels"], obs["state"]


def test_recipe_view_one_shows_the_recipe_to_agent_0_only():
    shared, shared_state = recipe_pixels("all")
    private, private_state = recipe_pixels("one")
    assert torch.equal(private[:, 0], shared[:, 0])  # agent 0 sees what it saw
    assert not torch.equal(private[:, 1], shared[:, 1])  # agent 1 no longer sees the balls
    # Where they differ agent 1 sees the sky instead of the balls (seen from below, in their shade): onion
    # yellow in world 0 (3 onions), tomato red in world 1 (3 tomatoes).
    r, g, b = shared[:, 1].to(torch.int32).unbind(-1)
    missing = (private[:, 1] != shared[:, 1]).any(-1)
    assert missing.sum((-1, -2)).min() >= 10
    assert ((r > 60) & (10 * g > 7 * r) & (2 * b < g))[0][missing[0]].all()
    assert ((r > 60) & (r > 4 * g) & (r > 4 * b))[1][missing[1]].all()
    assert torch.equal(private[:, 1][missing], torch.tensor([140, 166, 191], dtype=torch.uint8).expand(
        int(missing.sum()), 3))
    recipe = slice(6 + 8 + 16 * ck.G, 6 + 8 + 16 * ck.G + 4)
    assert shared_state[..., recipe].tolist() == [[[1, 0, 0, 0]] * 2, [[0, 0, 0, 1]] * 2]
    assert private_state[..., recipe].tolist() == [[[1, 0, 0, 0], [0] * 4], [[0, 0, 0, 1], [0] * 4]]


def reachable(cells) -> tuple:
    """(the floor cells reachable from the first floor cell by 4-neighbour steps, all floor cells)."""
    floor = {i for i, c in enumerate(cells) if c == ck.FLOOR}
    start = min(floor)
    seen, todo = {start}, deque([start])
    while todo:
        i = todo.popleft()
        r, c = divmod(i, ck.GW)
        for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
            j = rr * ck.GW + cc
            if 0 <= rr < ck.GH and 0 <= cc < ck.GW and j in floor and j not in seen:
                seen.add(j)
                todo.append(j)
    return seen, floor


def test_procedural_kitchens_are_whole_and_differ_between_levels():
    env = make(num_worlds=32, kitchen="procedural", levels="test", num_agents=4)
    env.reset()
    cells = env.sim.cells.tolist()
    for world in cells:
        seen, floor = reachable(world)
        assert seen == floor  # every floor cell can be reached
        kinds = sorted(c for c in world if c not in (ck.FLOOR, ck.COUNTER))
        assert kinds == [ck.POT, ck.POT, ck.DISHES, ck.SERVE, ck.ONION_BOX, ck.TOMATO_BOX]
        for i, c in enumerate(world):  # every station has a floor cell beside it
            if c not in (ck.FLOOR, ck.COUNTER):
                r, col = divmod(i, ck.GW)
                beside = [(r + dr) * ck.GW + col + dc for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1))
                          if 0 <= r + dr < ck.GH and 0 <= col + dc < ck.GW]
                assert any(world[j] == ck.FLOOR for j in beside)
    assert len({tuple(world) for world in cells}) > 16  # kitchens differ between levels
    here = ((env.sim.pos + torch.tensor([ck.HX, ck.HY])) / ck.CELL).floor().long()
    index = (ck.GH - 1 - here[..., 1]) * ck.GW + here[..., 0]
    assert (env.sim.cells.gather(1, index) == ck.FLOOR).all()  # agents spawn on distinct floor cells
    assert all(len(set(row)) == 4 for row in index.tolist())
    env.close()


@limited_threads(1)
def served(env, policy, steps):
    """Soups of the recipe served per world over `steps` steps of the rules alone (no rendering)."""
    s, state = env.scenario, env.sim
    alive = torch.ones(env.num_worlds, env.num_agents, dtype=torch.bool)
    generator = torch.Generator().manual_seed(0)
    for _ in range(steps):
        actions = s.heuristic(state, alive) if policy == "heuristic" else torch.randint(
            env.num_actions, alive.shape, generator=generator)
        state = s.step(state, actions, alive, generator).state
    return state.served


def test_the_heuristic_serves_soups_and_random_does_not():
    """Over 16 procedural kitchens (levels of the train set), 250 steps of the rules alone."""
    env = make(num_worlds=16, resolution=8, kitchen="procedural", cook_time=5, levels=100)
    env.reset()
    heuristic, random = served(env, "heuristic", 250), served(env, "random", 250)
    env.close()
    assert (heuristic > 0).float().mean() >= 0.75  # measured: 13 of 16 kitchens, 13 soups
    assert random.sum() == 0


@limited_threads(1)
def test_the_test_bots_fetch_or_plate_only():
    """Agent 0 plays the fetcher, agent 1 the plater, 200 steps in 8 procedural kitchens: the fetcher never
    holds a dish nor a soup but fills pots, the plater never holds an ingredient but plates soups."""
    env = make(num_worlds=8, resolution=8, kitchen="procedural", cook_time=5, levels=100)
    env.reset()
    s, state = env.scenario, env.sim
    alive = torch.ones(8, 2, dtype=torch.bool)
    held, filled = [], torch.zeros(8, dtype=torch.int64)
    for _ in range(200):
        view = types.SimpleNamespace(scenario=s, sim=state, alive=alive)
        actions = torch.stack((ck.fetcher(view)[:, 0], ck.plater(view)[:, 1]), 1)
        step = s.step(state, actions, alive, torch.Generator()).state
        filled += (step.pot.sum((1, 2)) > state.pot.sum((1, 2))).long()  # an ingredient went into a pot
        state = step
        held.append(state.held)
    env.close()
    held = torch.stack(held)
    assert (held[..., 0] <= ck.TOMATO).all() and (filled > 0).all()
    assert ((held[..., 1] == ck.EMPTY) | (held[..., 1] >= ck.DISH)).all() and (held[..., 1] >= ck.SOUP).any()


def test_one_ingredient_makes_the_tomato_dispenser_a_counter_and_refuses_tomatoes():
    with make(difficulty="easy") as env:  # num_ingredients=1, cook_time=10
        env.reset()
        assert env.sim.cells[:, TOMATO_BOX].tolist() == [ck.COUNTER] * W and env.sim.recipe.tolist() == [0] * W
        state = env.get_state()
        state["held"] = torch.tensor([[ck.TOMATO, 0]] * W)
        with pytest.raises(ValueError, match="num_ingredients=1 the state may hold no tomatoes"):
            env.set_state(state)
        assert env.sim.held.tolist() == [[0, 0]] * W
