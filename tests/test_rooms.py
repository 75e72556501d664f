"""Tests for envs/rooms.py: find a goal in procedurally generated rooms (and bring the news home)."""
import math

import pytest
import torch

from marl_render.envs import list_envs, make_env, rooms
from marl_render.envs.rooms import ARENA, DOOR_RANGE, DOOR_WIDTH, REACH, ROOM, WALL_THICKNESS, room_of

W, RES = 2, 32
NOOP, FORWARD = 0, 1
FACE_PLUS_X = -math.pi / 2  # yaw 0 faces +y, yaw > 0 turns left (towards -x)
ROOM_CENTRE = torch.tensor(rooms.TABLES["room_centre"])  # [9, 2]


def make(**kwargs):
    return make_env("rooms", **{"num_worlds": W, "resolution": RES, "seed": 0, **kwargs})


def edit(env, **fields):
    """Overwrite state fields (tensors broadcast to the field's shape), bodies at rest."""
    state = env.get_state()
    state["vel"] = torch.zeros_like(state["vel"])
    for name, value in fields.items():
        state[name] = torch.as_tensor(value, dtype=state[name].dtype).expand_as(state[name]).clone()
    env.set_state(state)


def worlds(state, order):
    """A get_state() dict with its worlds taken in `order` (a list of world indices)."""
    return {k: v if k == "rng" else v[order].clone() for k, v in state.items()}


def actions(env, action):
    return torch.full((env.num_worlds, env.num_agents), action)


def magenta(pixels):
    """bool [..., H, W]: goal-coloured pixels of uint8 images [..., H, W, 3]."""
    r, g, b = pixels.to(torch.int32).unbind(-1)
    return (r > 60) & (b > 0.6 * r) & (g < 0.3 * r)


# --------------------------------------------------------------------------- contract
def test_defaults_info_and_bad_keywords():
    assert "rooms" in list_envs()
    env = make(state_obs=True)
    assert env.num_agents == 2 and env.max_steps == 300 and env.state_dim == 46 + 2
    obs = env.reset()
    assert obs["state"].shape == (W, 2, 48) and obs["action_mask"].all()
    _, _, _, _, info = env.step(env.random_actions(torch.Generator().manual_seed(0)))
    for key in ("found", "returned", "rooms_visited"):
        assert info[key].shape == (W,) and info[key].dtype == torch.int64
    env.close()
    for kwargs, error, name in [({"open_wall": 1.5}, ValueError, "open_wall"),
                                ({"open_wall": "x"}, TypeError, "open_wall"),
                                ({"return_home": 1}, TypeError, "return_home"),
                                ({"found_reward": 0.0}, ValueError, "found_reward"),
                                ({"step_penalty": -0.1}, ValueError, "step_penalty"),
                                ({"explore_reward": -0.1}, ValueError, "explore_reward"),
                                ({"num_agents": 5}, ValueError, "num_agents"), ({"doors": 2}, TypeError, "doors")]:
        with pytest.raises(error, match=name):
            make(**kwargs)


def test_layout_is_random_per_world_and_episode_and_walls_leave_one_door():
    env = make(num_worlds=16, num_agents=4)
    env.reset(seed=3)
    s = env.sim
    first = s.door.clone()
    assert not torch.equal(s.door[0], s.door[1]) and (s.door.abs() <= DOOR_RANGE).all()
    assert 0 < s.wall_open.float().mean() < 0.5  # open_wall = 0.2
    # Agents start in their home room (marked visited), the goal in another room, clear of its walls.
    assert (room_of(s.pos) == s.home[:, None]).all() and (room_of(s.goal[:, 0]) != s.home).all()
    assert torch.equal(s.visited, torch.nn.functional.one_hot(s.home, 9).bool())
    inside = s.goal[:, 0] - ROOM_CENTRE[room_of(s.goal[:, 0])]  # the goal within its room
    assert (inside.abs() <= ROOM / 2 - rooms.GOAL_MARGIN + 1e-5).all()
    # Each slot's two pieces and its door fill the slot end to end (into the corners).
    centre, size, shown = env.scenario.walls(s)
    length = size[..., :2].max(-1).values.reshape(16, 12, 2)
    assert torch.allclose(length.sum(-1) + DOOR_WIDTH, torch.full((16, 12), ROOM + WALL_THICKNESS))
    assert (length > 0.1).all() and (size[..., :2].min(-1).values == WALL_THICKNESS).all()
    assert torch.equal(shown.reshape(16, 12, 2), (~s.wall_open)[..., None].expand(16, 12, 2))
    env.reset()
    assert not torch.equal(env.sim.door, first)
    env.close()


# --------------------------------------------------------------------------- physics
def test_walls_block_bodies_and_open_slots_do_not():
    env = make()
    env.reset()
    # Slot 0 is the wall x = -1 between rooms 0 and 1 (y in [-3, -1]); its door is put at the
    # top (y in [-1.85, -1.15]). Agent 0 drives at it along y = -2.6 in both worlds; in world 1
    # the slot is open. Agent 1 waits in room 8.
    door = torch.zeros(W, 12)
    door[:, 0] = DOOR_RANGE
    wall_open = torch.zeros(W, 12, dtype=torch.bool)
    wall_open[1, 0] = True
    edit(env, pos=torch.tensor([[-2.0, -2.6], [2.0, 2.0]]), yaw=torch.tensor([FACE_PLUS_X, 0.0]), door=door,
         wall_open=wall_open, visited=torch.zeros(9, dtype=torch.bool))
    obstacles = env.scenario.obstacles(env.sim)
    assert (obstacles.center[1, :2] == rooms.FAR_AWAY).all() and (obstacles.center[0, :2].abs() < ARENA + 1).all()
    drive = torch.tensor([[FORWARD, NOOP]] * W)
    for _ in range(60):
        _, _, _, _, info = env.step(drive)
        assert env.sim.pos[0, 0, 0] <= -ROOM / 2 - WALL_THICKNESS / 2 - rooms.AGENT_RADIUS + 1e-4
    assert env.sim.pos[0, 0, 0] > -1.25  # it did reach the wall
    # World 1: through the open slot into room 1, up to slot 1's wall (x = 1; its door is at y = -2).
    assert abs(env.sim.pos[1, 0, 0] - (ROOM / 2 - WALL_THICKNESS / 2 - rooms.AGENT_RADIUS)) < 1e-4
    assert env.sim.visited.nonzero().tolist() == [[0, 0], [0, 8], [1, 0], [1, 1], [1, 8]]
    assert info["rooms_visited"].tolist() == [2, 3]
    assert torch.equal(env.sim.pos[:, 1], torch.tensor([[2.0, 2.0]] * W))
    env.close()


def test_no_body_ever_enters_a_wall():
    # Four agents jostling in doorways (heuristic and random steps in turn), new layouts on autoreset.
    env = make(num_worlds=8, num_agents=4, resolution=8, autoreset=True)
    env.reset()
    g = torch.Generator().manual_seed(0)
    for t in range(150):
        env.step(env.random_actions(g) if t % 2 else env.heuristic_actions())
        centre, size, shown = env.scenario.walls(env.sim)
        outside = (env.sim.pos[:, :, None] - centre[:, None]).abs() - size[:, None, :, :2] / 2  # [W, A, 24, 2]
        gap = torch.where((outside < 0).all(-1), outside.max(-1).values, outside.clamp_min(0).norm(dim=-1))
        assert (gap[shown[:, None].expand_as(gap)] >= rooms.AGENT_RADIUS - 1e-4).all(), t
    env.close()


# --------------------------------------------------------------------------- rules
def test_finding_the_goal_rewards_everyone_once_and_terminates():
    env = make(step_penalty=0.01)
    env.reset(seed=1)
    s = env.sim
    near = s.goal[:, 0] + torch.tensor([[REACH - 0.02, 0.0], [REACH + 0.05, 0.0]])  # world 1: just out of reach
    edit(env, pos=torch.stack((near, ROOM_CENTRE[s.home]), 1))
    _, reward, terminated, truncated, info = env.step(actions(env, NOOP))
    assert torch.allclose(reward, torch.tensor([[0.99, 0.99], [-0.01, -0.01]]))
    assert terminated.tolist() == [[True, True], [False, False]] and not truncated.any()
    assert info["found"].tolist() == [1, 0] and info["returned"].tolist() == [0, 0]
    assert env.sim.finder.tolist() == [[True, False], [False, False]]
    flags = env.state_observation()[..., 42:44]  # (this agent reached the goal, some agent did)
    assert flags.tolist() == [[[1.0, 1.0], [0.0, 1.0]], [[0.0, 0.0], [0.0, 0.0]]]
    assert info["rooms_visited"].tolist() == [2, 2]  # home and the goal's room
    env.close()


def test_explore_reward_counts_rooms_entered_for_the_first_time():
    env = make(explore_reward=0.25, num_worlds=1)
    env.reset(seed=1)
    s = env.sim
    others = [room for room in range(9) if room != int(s.home[0]) and room != int(rooms.room_of(s.goal[:, 0])[0])]
    # Both agents jump into two new rooms: +0.25 each, shared; then staying there earns nothing.
    edit(env, pos=ROOM_CENTRE[others[:2]][None])
    _, reward, _, _, info = env.step(actions(env, NOOP))
    assert reward.tolist() == [[0.5, 0.5]] and info["rooms_visited"].tolist() == [3]
    _, reward, _, _, _ = env.step(actions(env, NOOP))
    assert reward.tolist() == [[0.0, 0.0]]
    # Back to the home room (visited from the start): nothing either.
    edit(env, pos=ROOM_CENTRE[s.home].expand(1, 2, 2) + torch.tensor([[-0.4, 0.0], [0.4, 0.0]]))
    _, reward, _, _, _ = env.step(actions(env, NOOP))
    assert reward.tolist() == [[0.0, 0.0]]
    env.close()


def test_return_home_variant():
    env = make(return_home=True, num_worlds=1)
    env.reset(seed=2)
    s = env.sim
    home = ROOM_CENTRE[s.home]  # [1, 2]
    # Agent 1 stays home all along: not having reached the goal, it does not count.
    edit(env, pos=torch.stack((s.goal[:, 0], home), 1))
    _, reward, terminated, _, info = env.step(actions(env, NOOP))
    assert reward.tolist() == [[1.0, 1.0]] and not terminated.any()
    assert (info["found"].item(), info["returned"].item()) == (1, 0)
    _, reward, terminated, _, info = env.step(actions(env, NOOP))  # still at the goal: nothing new
    assert reward.tolist() == [[0.0, 0.0]] and not terminated.any()
    edit(env, pos=torch.stack((home + 0.5, home), 1))
    _, reward, terminated, _, info = env.step(actions(env, NOOP))
    assert reward.tolist() == [[1.0, 1.0]] and terminated.all()
    assert (info["found"].item(), info["returned"].item()) == (1, 1)
    env.close()


def test_state_obs_gives_the_goal_only_in_its_room():
    env = make(state_obs=True)
    env.reset(seed=4)
    s = env.sim
    goal = s.goal[:, 0]
    away = ROOM_CENTRE[s.home]
    edit(env, pos=torch.stack((goal + 0.3, away), 1))  # agent 0 in the goal's room, agent 1 at home
    obs = env.state_observation()
    seen, rel = obs[..., 6 + 33], obs[..., 6 + 34:6 + 36]
    assert seen.tolist() == [[1.0, 0.0]] * W
    assert torch.allclose(rel[:, 0], torch.full((W, 2), -0.3)) and (rel[:, 1] == 0).all()
    assert torch.equal(obs[:, 0, 6:15], env.sim.visited.float())
    assert torch.equal(obs[:, 0, 15:27], (~env.sim.wall_open).float()) and torch.equal(obs[:, 0, 27:39], env.sim.door)
    assert torch.allclose(obs[:, 1, 44:46], torch.zeros(W, 2))  # agent 1 sits at the home centre
    env.close()


# --------------------------------------------------------------------------- pixels
def test_goal_and_walls_in_view():
    env = make(num_worlds=1, num_agents=1, depth=True)
    env.reset(seed=5)
    goal = env.sim.goal[0, 0]
    middle = (0, 0, slice(RES // 2 - 2, RES // 2 + 2), slice(RES // 2 - 2, RES // 2 + 2))
    # Facing the goal from 0.6 m: it fills the middle of the view; turned away, it is gone.
    edit(env, pos=(goal - torch.tensor([0.6, 0.0]))[None, None], yaw=torch.tensor([[FACE_PLUS_X]]))
    assert magenta(env.step(actions(env, NOOP))[0]["pixels"][middle]).all()
    edit(env, yaw=torch.tensor([[-FACE_PLUS_X]]))
    assert not magenta(env.step(actions(env, NOOP))[0]["pixels"]).any()
    # Facing slot 0's wall (x = -1, door moved to the top) from x = -1.6 in room 0: the middle of
    # the view is that wall, 0.55 m away along the floor (the camera looks 0.2 rad down).
    door = torch.zeros(1, 12)
    door[0, 0] = DOOR_RANGE
    edit(env, pos=torch.tensor([[[-1.6, -2.6]]]), yaw=torch.tensor([[FACE_PLUS_X]]), door=door,
         wall_open=torch.zeros(1, 12, dtype=torch.bool))
    obs = env.step(actions(env, NOOP))[0]
    expected = (1.6 - ROOM / 2 - WALL_THICKNESS / 2) / math.cos(0.2)
    assert torch.allclose(obs["depth"][middle], torch.full((4, 4), expected), atol=0.03)
    rgb = obs["pixels"][middle].to(torch.int32)
    assert ((rgb[..., 0] >= rgb[..., 1]) & (rgb[..., 1] >= rgb[..., 2]) & (rgb[..., 2] > 40)).all()  # warm grey
    env.close()


def test_one_worlds_walls_never_appear_in_another_worlds_views():
    env = make(num_agents=2)
    env.reset(seed=6)
    # The same agents and goal in both worlds; world 0 has no interior walls, world 1 all of them.
    base = worlds(env.get_state(), [0, 0])
    base["wall_open"][0] = True
    base["wall_open"][1] = False
    env.set_state(base)
    views, overview = env.step(actions(env, NOOP))[0]["pixels"], env.render_overview(64)
    assert not torch.equal(views[0], views[1]) and not torch.equal(overview[0], overview[1])  # walls are seen
    # A twin env holding the worlds the other way round, and single-world envs of each: every
    # world's pictures are those of its own layout alone.
    twin = make(num_agents=2)
    twin.reset()
    twin.set_state(worlds(env.get_state(), [1, 0]))
    assert torch.equal(twin.step(actions(twin, NOOP))[0]["pixels"], views.flip(0))
    assert torch.equal(twin.render_overview(64), overview.flip(0))
    twin.close()
    for w in range(W):
        alone = make(num_agents=2, num_worlds=1)
        alone.reset()
        alone.set_state(worlds(env.get_state(), [w]))
        assert torch.equal(alone.step(actions(alone, NOOP))[0]["pixels"][0], views[w])
        alone.close()
    env.close()


# --------------------------------------------------------------------------- state handling
def test_determinism_and_state_round_trip():
    def rollout(env, steps=25):
        g = torch.Generator().manual_seed(7)
        out = []
        for _ in range(steps):
            obs, reward, terminated, _, info = env.step(env.random_actions(g))
            out.append((obs["pixels"], obs["state"], reward, terminated, info["rooms_visited"]))
        return out

    a, b = make(state_obs=True, seed=11, autoreset=True), make(state_obs=True, seed=11, autoreset=True)
    a.reset(), b.reset()
    for x, y in zip(rollout(a), rollout(b), strict=True):
        assert all(torch.equal(u, v) for u, v in zip(x, y, strict=True))
    saved = a.get_state()
    first = rollout(a)
    a.reset(seed=99)
    a.set_state(saved)
    assert all(torch.equal(u, v) for x, y in zip(first, rollout(a), strict=True) for u, v in zip(x, y, strict=True))
    a.close(), b.close()


def test_heuristic_beats_random():
    returns = {}
    for policy in ("heuristic", "random"):
        env = make(num_worlds=8, resolution=8, max_steps=200)
        env.reset(seed=0)
        g, total = torch.Generator().manual_seed(0), torch.zeros(8)
        for _ in range(200):
            a = env.heuristic_actions() if policy == "heuristic" else env.random_actions(g)
            total += env.step(a)[1].mean(1)
        returns[policy] = total.mean().item()
        env.close()
    assert returns["heuristic"] > returns["random"] + 0.3, returns
