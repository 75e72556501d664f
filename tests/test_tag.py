"""Tests for envs/tag.py: predators and prey in a walled arena with obstacles."""

import math

import pytest
import torch

from marl_render.envs import list_envs, make_env, tag

W, RES = 3, 32


def make(**kwargs):
    kwargs = {"num_worlds": W, "resolution": RES, "seed": 0, **kwargs}
    return make_env("tag", **kwargs)


def noop(env):
    if env.continuous:
        return torch.zeros(env.num_worlds, env.num_agents, 2)
    return torch.zeros(env.num_worlds, env.num_agents, dtype=torch.long)


def place(env, pos, yaw=None):
    """Put the bodies at `pos` [W, N, 2] at rest (and yaw [W, N]), through get_state / set_state."""
    state = env.get_state()
    state["pos"] = torch.as_tensor(pos, dtype=torch.float32).expand(env.num_worlds, env.num_agents, 2).clone()
    state["vel"] = torch.zeros_like(state["vel"])
    if yaw is not None:
        state["yaw"] = torch.as_tensor(yaw, dtype=torch.float32).expand(env.num_worlds, env.num_agents).clone()
    env.set_state(state)


def green(pixels):
    """Number of prey-coloured (green) pixels in uint8 images [..., H, W, 3], per image."""
    r, g, b = pixels.to(torch.int32).unbind(-1)
    return ((g - r > 40) & (g - b > 30)).sum((-1, -2))


# --------------------------------------------------------------------------- contract
# Observation, reward and done shapes and dtypes: tests/test_envs_core.py checks them for every env.
def test_teams_state_size_and_info():
    env = make(state_obs=True)
    N, K = env.num_agents, env.scenario.num_obstacles
    assert (N, env.scenario.num_predators, env.scenario.num_prey, K) == (4, 3, 1, 2)
    assert env.groups == {"predator": ["predator_0", "predator_1", "predator_2"], "prey": ["prey_0"]}
    assert env.state_dim == 6 + 3 * (N - 1) + 2 * K
    env.reset(seed=1)
    _, _, _, _, info = env.step(env.random_actions(torch.Generator().manual_seed(0)))
    assert info["caught"].shape == (W,) and info["caught"].dtype == torch.int64
    assert info["prey_left"].shape == (W,) and info["prey_left"].dtype == torch.int64
    env.close()


def test_team_sizes():
    for kwargs, sizes in [({}, (3, 1)), ({"num_agents": 2}, (1, 1)), ({"num_agents": 8}, (6, 2)),
                          ({"num_prey": 2}, (3, 2)), ({"num_predators": 2}, (2, 1)),
                          ({"num_agents": 5, "num_prey": 2}, (3, 2)), ({"num_agents": 5, "num_predators": 4}, (4, 1)),
                          ({"num_predators": 1, "num_prey": 3}, (1, 3))]:
        env = make(num_worlds=1, resolution=8, **kwargs)
        assert (env.scenario.num_predators, env.scenario.num_prey) == sizes, kwargs
        assert env.num_agents == sum(sizes)
        assert env.agent_names == [f"predator_{i}" for i in range(sizes[0])] + [f"prey_{j}" for j in range(sizes[1])]
        env.close()
    with pytest.raises(ValueError, match="num_predators \\+ num_prey"):
        make(num_agents=4, num_predators=2, num_prey=1)
    with pytest.raises(ValueError, match="at least one predator"):
        make(num_agents=3, num_prey=3)
    with pytest.raises(ValueError, match="num_agents"):
        make(num_agents=1)
    with pytest.raises(ValueError, match="num_obstacles"):
        make(num_obstacles=9)


def test_registered():
    assert "tag" in list_envs()
    env = make_env("tag", num_worlds=1, resolution=8, num_prey=2)
    assert isinstance(env.scenario, tag.Tag) and env.num_agents == 5
    env.close()


# --------------------------------------------------------------------------- catching
def test_catch_removes_prey_and_ends_episode_when_all_caught():
    # 3 predators, 2 prey (indices 3, 4), no obstacles. Predator 2 at (0, -1) looks along +y at
    # both prey at y = 0.5. World 0: predator 0 touches prey 3. World 1: predators 0 and 1
    # touch prey 3 and 4. World 2: nobody touches anybody (control).
    env = make(num_predators=3, num_prey=2, num_obstacles=0)
    env.reset(seed=0)
    gap = 0.28  # centre distance: not overlapping (0.27), within the catch tolerance (0.29)
    away = [[-1.2, 1.2], [1.2, 1.2]]
    near = [[0.0, 0.5 + gap], [1.0, 0.5 + gap]]
    prey = [[0.0, 0.5], [1.0, 0.5]]
    watcher = [[0.0, -1.0]]
    pos = torch.tensor([[near[0], away[1]] + watcher + prey,
                        near + watcher + prey,
                        away + watcher + prey])
    place(env, pos, yaw=torch.zeros(W, 5))
    obs, reward, terminated, truncated, info = env.step(noop(env))

    assert info["caught"].tolist() == [1, 2, 0]
    assert info["prey_left"].tolist() == [1, 0, 2]
    assert env.alive.tolist() == [[True, True, True, False, True], [False] * 5, [True] * 5]
    assert terminated.tolist() == [[False, False, False, True, False], [True] * 5, [False] * 5]
    assert info["done_worlds"].tolist() == [False, True, False]
    assert not truncated.any()
    assert reward.tolist() == [[10.0, 10.0, 10.0, -10.0, 0.0], [20.0, 20.0, 20.0, -10.0, -10.0], [0.0] * 5]
    # The caught prey's body no longer collides ...
    assert env.sim.active.tolist() == env.alive.tolist()
    # ... but the frame of the catch still shows it (world 1's is the episode's last frame):
    # the watcher sees both prey in every world, and so does the overview.
    seen = green(obs["pixels"][:, 2])
    assert seen[0] > 0 and seen.tolist() == [seen[0]] * 3, seen.tolist()
    overview = green(env.render_overview(64))
    assert overview[0] > 0 and overview.tolist() == [overview[0]] * 3, overview.tolist()
    # Agents that left may only take noop.
    mask = obs["action_mask"]
    assert mask[2].all() and mask[0, :3].all() and mask[0, 4].all()
    assert mask[0, 3].tolist() == [True, False, False, False, False]
    assert mask[1, :, 0].all() and not mask[1, :, 1:].any()

    # Next step: the dead stay dead (terminated, reward 0, frozen) whatever they were told.
    frozen = env.sim.pos[:, 3].clone()
    actions = torch.ones(W, 5, dtype=torch.long)
    obs, reward, terminated, truncated, info = env.step(actions)
    assert torch.equal(env.sim.pos[:, 3][:2], frozen[:2])
    assert reward[0, 3] == 0 and (reward[1] == 0).all()
    assert terminated[0, 3] and terminated[1].all() and not terminated[2].any()
    # From this frame on the caught prey are gone: world 0 keeps prey 4, world 1 none.
    assert env.renderer.instance_state("agents")["active"].tolist() == env.alive.tolist()
    seen = green(obs["pixels"][:, 2])
    assert seen[1] == 0 and 0 < seen[0] < seen[2], seen.tolist()
    overview = green(env.render_overview(64))
    assert overview[1] == 0 and 0 < overview[0] < overview[2], overview.tolist()

    # Resetting world 0 brings its prey back; world 1 stays over.
    obs = env.reset_worlds(torch.tensor([True, False, False]))
    assert env.alive[0].all() and not env.alive[1].any() and env.sim.active[0].all()
    assert env.renderer.instance_state("agents")["active"][0].all()
    assert green(obs["pixels"][1]).sum() == 0
    env.close()


def test_restored_state_shows_what_its_frame_showed():
    # A state saved in the frame of a catch ("shown": the caught prey is still drawn) shows the
    # prey again when restored after it has gone.
    env = make(num_predators=3, num_prey=2, num_obstacles=0)
    env.reset(seed=0)
    place(env, [[0.0, 0.78], [-1.2, 1.2], [0.0, -1.0], [0.0, 0.5], [1.2, -1.2]], yaw=torch.zeros(W, 5))
    _, _, _, _, info = env.step(noop(env))
    assert info["caught"].tolist() == [1] * W
    saved, catch_frame = env.get_state(), green(env.render_overview(64))
    assert saved["shown"].all() and not saved["alive"][:, 3].any()
    env.step(noop(env))
    assert (green(env.render_overview(64)) < catch_frame).all()
    env.set_state(saved)
    assert torch.equal(green(env.render_overview(64)), catch_frame)
    env.close()


def test_shaping_signs():
    env = make(num_obstacles=0, shaping=0.5)
    env.reset(seed=0)
    place(env, torch.tensor([[-1.0, -1.0], [0.0, -1.0], [1.0, -1.0], [0.0, 1.0]]))
    _, reward, terminated, _, _ = env.step(noop(env))
    assert not terminated.any()
    assert torch.allclose(reward[:, :3], torch.tensor([-0.5 * math.hypot(1, 2), -1.0, -0.5 * math.hypot(1, 2)]))
    assert torch.allclose(reward[:, 3], torch.tensor(1.0))  # 0.5 x distance 2 to the nearest predator
    env.close()


def test_speed_caps():
    env = make(num_obstacles=0, continuous=True)
    env.reset(seed=0)
    place(env, torch.tensor([[-1.1, -1.3], [-0.4, -1.3], [0.3, -1.3], [1.0, -1.3]]), yaw=torch.zeros(W, 4))
    forward = torch.tensor([1.0, 0.0]).expand(W, 4, 2)
    top = torch.zeros(W, 4)
    for _ in range(12):
        env.step(forward)
        top = torch.maximum(top, env.sim.vel.norm(dim=-1))
    assert (top[:, :3] <= tag.MAX_SPEED["predator"] + 1e-5).all() and (top[:, :3] > 0.9).all()
    assert (top[:, 3] <= tag.MAX_SPEED["prey"] + 1e-5).all() and (top[:, 3] > 1.2).all()
    env.close()


# --------------------------------------------------------------------------- state handling
# Determinism, partial resets, bad actions and declared physics terms: tests/test_envs_core.py
# runs them for every env.
def test_obstacle_term_only_with_obstacles(check_only_declared_terms):
    for obstacles, declared in ((2, {"walls", "body_collisions", "drag", "obstacles"}),
                                (0, {"walls", "body_collisions", "drag"})):
        env = make(num_obstacles=obstacles)
        assert env.physics_terms == declared
        check_only_declared_terms(env)
        env.close()
