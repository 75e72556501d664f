"""The PettingZoo front end (marl_render/wrappers/pettingzoo.py): PettingZoo's own API,
seed and render tests on every registered environment, agents leaving the episode, bad
input, and the wrappers users chain (supersuit, parallel_to_aec, torchrl)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from gymnasium import spaces
from gymnasium.utils.env_checker import data_equivalence
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test, render_test
from pettingzoo.utils.conversions import aec_to_parallel, parallel_to_aec

from marl_render.envs import list_envs, make_env
from departing_env import Departing
from marl_render.wrappers.pettingzoo import ActionTypeError, MarlRenderParallelEnv, make_parallel_env

RES = 32
ENVS = list_envs()


pytestmark = pytest.mark.usefixtures("single_torch_thread")


def make(name, **kw):
    kw.setdefault("resolution", RES)
    return make_parallel_env(name, **kw)


def departing(max_steps=5, **kw):
    return MarlRenderParallelEnv(Departing(num_worlds=1, resolution=RES, max_steps=max_steps, seed=0), **kw)


def sample(env, obs=None):
    return {a: env.action_space(a).sample() for a in env.agents}


def states_equal(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------------- PettingZoo's own tests
@pytest.mark.parametrize("name", ENVS)
@pytest.mark.parametrize("variant", [{}, {"continuous": True, "depth": True, "state_obs": True},
                                     {"action_mask": True, "state_obs": True}])
def test_parallel_api_test(name, variant):
    # parallel_api_test calls reset(options={"options": 1}): unknown options are ignored only on request.
    env = make(name, max_steps=12, unknown_options="ignore", **variant)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # PettingZoo reports API deviations as warnings
        parallel_api_test(env, num_cycles=30)  # > max_steps: the episode ends inside the test
    env.close()


def test_parallel_api_test_needs_the_options_opt_in():
    env = make("spread")
    with pytest.raises(ValueError, match="unknown reset option.*'options'.*unknown_options='ignore'"):
        parallel_api_test(env, num_cycles=2)
    env.close()


@pytest.mark.parametrize("name", ENVS)
def test_parallel_seed_test(name):
    parallel_seed_test(lambda: make(name, max_steps=20), num_cycles=20)


@pytest.mark.parametrize("name", ENVS)
def test_same_seed_same_episode_over_many_steps(name):
    # parallel_seed_test stops after its first step (it tests `any(terminations)` over the
    # dict's keys), so check a whole episode here.
    def episode(seed):
        env = make(name, max_steps=25, seed=7)
        out = [env.reset(seed=seed)]
        for i, agent in enumerate(env.possible_agents):
            env.action_space(agent).seed(100 + i)
        while env.agents:
            out.append(env.step(sample(env)))
        env.close()
        return out

    a, b, c = episode(42), episode(42), episode(43)
    assert len(a) == 26
    assert data_equivalence(a, b)
    assert not data_equivalence(a[0], c[0])


@pytest.mark.parametrize("name", ENVS)
def test_render_test(name):
    # render_test builds an env with render_mode="human" only to read metadata["render_modes"]
    # (["rgb_array"]), then drives the AEC API; "human" (a window) is not supported.
    def env_fn(render_mode=None):
        return parallel_to_aec(make(name, render_mode=None if render_mode == "human" else render_mode))

    render_test(env_fn)


def test_render_tiles_views_and_overview():
    env = make("spread", render_mode="rgb_array")
    with pytest.raises(RuntimeError, match="reset"):
        env.render()
    obs, _ = env.reset(seed=0)
    image = env.render()
    overview = env.core.render_overview()[0].numpy()
    H2, W2 = overview.shape[:2]
    scale = H2 // RES
    assert image.dtype == np.uint8 and image.shape == (H2, 3 * (RES * scale + 2) + W2, 3)
    assert np.array_equal(image[:, -W2:], overview)
    assert np.array_equal(image[::scale, :RES * scale:scale][:RES], obs["agent_0"])
    env.close()
    quiet = make("spread")
    quiet.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert quiet.render() is None  # render_mode=None: gymnasium warns and returns None
    quiet.close()


# ---------------------------------------------------------------------- spaces and outputs
def test_spaces_and_outputs():
    env = make("spread", num_agents=2)
    assert env.metadata["is_parallelizable"] and env.metadata["name"] == "spread"
    assert env.possible_agents == ["agent_0", "agent_1"]
    assert env.observation_space("agent_0") == spaces.Box(0, 255, (RES, RES, 3), np.uint8)
    assert env.action_space("agent_1") == spaces.Discrete(5)
    assert env.observation_space("agent_0") is not env.observation_space("agent_1")  # seeded separately
    obs, infos = env.reset(seed=1)
    assert env.agents == env.possible_agents and infos == {"agent_0": {}, "agent_1": {}}
    assert obs["agent_0"].dtype == np.uint8 and obs["agent_0"].shape == (RES, RES, 3)
    obs, rew, term, trunc, info = env.step({"agent_0": 1, "agent_1": np.int64(2)})
    assert all(type(r) is float for r in rew.values())
    assert term == {"agent_0": False, "agent_1": False} and trunc == term
    assert info["agent_0"]["step_count"] == 1 and {"collisions", "coverage"} <= set(info["agent_0"])
    env.close()

    env = make("cartpole", continuous=True, depth=True, state_obs=True)
    space = env.observation_space("agent_0")
    assert set(space.spaces) == {"pixels", "depth", "state"}
    assert space["depth"].dtype == np.float32 and space["state"].shape == (5,)
    assert env.action_space("agent_0") == spaces.Box(-1, 1, (1,), np.float32)
    obs, _ = env.reset(seed=0)
    assert space.contains(obs["agent_0"])
    env.close()

    env = make("spread", action_mask=True)
    mask_space = env.observation_space("agent_0")["action_mask"]
    obs, _ = env.reset(seed=0)
    assert obs["agent_0"]["action_mask"].dtype == np.int8 and mask_space.contains(obs["agent_0"]["action_mask"])
    env.close()
    with pytest.raises(ValueError, match="action_mask=True needs a discrete env"):
        make("cartpole", continuous=True, action_mask=True)


def test_episode_end_empties_agents():
    env = make("spread", max_steps=3)
    env.reset(seed=0)
    for _ in range(2):
        _, _, term, trunc, _ = env.step(sample(env))
        assert not any(trunc.values())
    obs, _, term, trunc, _ = env.step(sample(env))
    assert set(obs) == set(env.possible_agents) and all(trunc.values()) and not any(term.values())
    assert env.agents == []
    with pytest.raises(RuntimeError, match="episode is over.*reset"):
        env.step({})
    env.reset()
    assert env.agents == env.possible_agents
    env.close()


# ---------------------------------------------------------------------- agents leaving
def test_departed_agents_follow_pettingzoo_semantics():
    env = departing(max_steps=5)
    obs, _ = env.reset(seed=0)
    assert env.agents == ["predator_0", "prey_0", "prey_1"]
    step = lambda: env.step(sample(env))  # noqa: E731
    obs, rew, term, trunc, info = step()  # step 1: nobody leaves
    assert set(obs) == set(rew) == set(term) == set(trunc) == set(info) == {"predator_0", "prey_0", "prey_1"}
    obs, rew, term, trunc, info = step()  # step 2: prey_0 leaves, reported once
    assert term == {"predator_0": False, "prey_0": True, "prey_1": False}
    assert set(obs) == set(rew) == set(info) == {"predator_0", "prey_0", "prey_1"}
    assert rew["prey_0"] != 0.0  # rewarded for the step it was caught in
    assert env.agents == ["predator_0", "prey_1"]
    # an action for the departed agent is an error and changes nothing
    before = env.core.get_state()
    with pytest.raises(KeyError, match="'prey_0'.*left the episode"):
        env.step({"predator_0": 0, "prey_0": 0, "prey_1": 0})
    assert states_equal(before, env.core.get_state())
    obs, rew, term, trunc, info = step()  # step 3: prey_1 leaves
    assert set(obs) == {"predator_0", "prey_1"} and term["prey_1"] and not term["predator_0"]
    assert env.agents == ["predator_0"]
    step()
    obs, rew, term, trunc, info = step()  # step 5: max_steps
    assert set(obs) == {"predator_0"} and trunc == {"predator_0": True} and term == {"predator_0": False}
    assert env.agents == []
    obs, _ = env.reset()
    assert env.agents == env.possible_agents
    env.close()


def test_departed_agents_pass_pettingzoo_tests():
    env = departing(max_steps=6, unknown_options="ignore")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parallel_api_test(env, num_cycles=10)
    aec = parallel_to_aec(departing(max_steps=6, unknown_options="ignore"))
    api_test(aec, num_cycles=10)
    aec.close()


def test_departed_actions_can_be_ignored():
    env = departing(departed_actions="ignore")
    env.reset(seed=0)
    env.step(sample(env))
    env.step(sample(env))
    obs, *_ = env.step({"predator_0": 0, "prey_0": 3, "prey_1": 0})  # prey_0's action is ignored
    assert set(obs) == {"predator_0", "prey_1"}
    with pytest.raises(KeyError, match="unknown agent 'ghost'"):
        env.step({"predator_0": 0, "ghost": 0})
    env.close()


@pytest.mark.skipif("tag" not in ENVS, reason="tag is not registered yet")
def test_tag_random_episode_consistency():
    env = make("tag", max_steps=40)
    env.reset(seed=0)
    gone = set()
    while env.agents:
        acting = set(env.agents)
        obs, rew, term, trunc, info = env.step(sample(env))
        assert set(obs) == set(rew) == set(term) == set(trunc) == acting
        assert not (gone & set(env.agents))
        gone |= {a for a in acting if term[a] or trunc[a]}
        assert set(env.agents) == acting - gone
    env.close()


# ---------------------------------------------------------------------- bad input
def test_bad_actions_name_the_agent_and_change_nothing():
    env = make("spread", num_agents=2)
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"agent_0": 0, "agent_1": 0})
    env.reset(seed=0)
    before = env.core.get_state()
    cases = [
        ([0, 1], TypeError, "actions must be a dict"),
        ({"agent_0": 0}, KeyError, r"missing an action for agent\(s\) \['agent_1'\]"),
        ({"agent_0": 0, "agent_1": 0, "agent_7": 0}, KeyError, "unknown agent 'agent_7'"),
        ({"agent_0": 5, "agent_1": 0}, ValueError, r"actions\['agent_0'\] must be an int in \[0, 5\).*got 5"),
        ({"agent_0": 0, "agent_1": -1}, ValueError, r"actions\['agent_1'\].*got -1"),
        ({"agent_0": 1.0, "agent_1": 0}, ValueError, r"actions\['agent_0'\] must be an int"),
        ({"agent_0": True, "agent_1": 0}, ValueError, r"actions\['agent_0'\]"),
        ({"agent_0": "1", "agent_1": 0}, ValueError, r"actions\['agent_0'\]"),
        ({"agent_0": np.array([1, 2]), "agent_1": 0}, ValueError, r"actions\['agent_0'\]"),
        ({"agent_0": np.nan, "agent_1": 0}, ValueError, r"actions\['agent_0'\]"),
    ]
    for actions, error, message in cases:
        with pytest.raises(error, match=message):
            env.step(actions)
        assert states_equal(before, env.core.get_state())
    with pytest.raises(ActionTypeError):  # both a TypeError and a ValueError
        env.step({"agent_0": 0.5, "agent_1": 0})
    env.step({"agent_0": np.array(1), "agent_1": torch.tensor(4)})  # 0-d arrays / tensors are fine
    env.close()

    env = make("cartpole", continuous=True)
    env.reset(seed=0)
    before = env.core.get_state()
    for action, message in [(np.array([np.nan], np.float32), "non-finite"), (np.array([1.5]), r"clip them"),
                            (np.zeros(2), r"shape \(2,\)"), ("x", "must be a float array"),
                            (np.array([True]), "must be a float array")]:
        with pytest.raises(ValueError, match=r"actions\['agent_0'\].*" + message):
            env.step({"agent_0": action})
        assert states_equal(before, env.core.get_state())
    env.step({"agent_0": [0.5]})
    env.step({"agent_0": -1.0})  # a scalar for a (1,) Box
    env.close()


def test_bad_reset_and_construction_arguments():
    env = make("spread")
    with pytest.raises(ValueError, match=r"unknown reset option\(s\) 'warp'"):
        env.reset(options={"warp": 1})
    with pytest.raises(TypeError, match="options must be None or a dict"):
        env.reset(options=[1])
    with pytest.raises((TypeError, ValueError), match="seed"):
        env.reset(seed=-1)
    with pytest.raises((TypeError, ValueError), match="seed"):
        env.reset(seed="1")
    env.reset(seed=0, options={})
    with pytest.raises(KeyError, match="unknown agent 'x'"):
        env.observation_space("x")
    env.close()
    env.close()  # twice is fine
    with pytest.raises(RuntimeError, match="closed"):
        env.reset()
    with pytest.raises(ValueError, match="render_mode must be None or one of"):
        make("spread", render_mode="human")
    with pytest.raises(TypeError, match="num_worlds"):
        make("spread", num_worlds=2)
    with pytest.raises(TypeError, match="autoreset"):
        make("spread", autoreset=True)
    with pytest.raises(ValueError, match="departed_actions"):
        make("spread", departed_actions="drop")
    with pytest.raises(TypeError, match="num_landmark"):
        make("spread", num_landmark=2)  # the registry names unknown env kwargs


# ---------------------------------------------------------------------- chained wrappers
def test_supersuit_image_wrappers():
    ss = pytest.importorskip("supersuit", reason="pip install supersuit to test the supersuit chain")
    env = make("spread", max_steps=6)
    env = ss.color_reduction_v0(env, mode="full")
    env = ss.resize_v1(env, 16, 16)
    env = ss.frame_stack_v1(env, 3)
    assert env.observation_space("agent_0").shape == (16, 16, 3)
    obs, _ = env.reset(seed=0)
    steps = 0
    while env.agents:
        obs, rew, term, trunc, info = env.step(sample(env))
        steps += 1
    assert steps == 6 and all(trunc.values())
    assert all(env.observation_space(a).contains(o) for a, o in obs.items())
    env.close()


def test_parallel_to_aec_round_trip():
    par = make("spread", max_steps=4)
    aec = parallel_to_aec(par)
    aec.reset(seed=0)
    assert aec.agents == par.possible_agents
    for agent in aec.agent_iter():
        obs, reward, term, trunc, info = aec.last()
        assert obs.shape == (RES, RES, 3)
        aec.step(None if term or trunc else aec.action_space(agent).sample())
    assert aec.agents == [] and par.agents == []
    assert aec_to_parallel(aec) is par  # PettingZoo unwraps the round trip
    aec.close()


def test_torchrl_pettingzoo_wrapper():
    from torchrl.envs import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    env = PettingZooWrapper(env=make("spread", max_steps=4, action_mask=True), use_mask=True)
    check_env_specs(env)
    td = env.rollout(6, break_when_any_done=False)
    assert td["next", "agent", "observation", "pixels"].shape == (6, 3, RES, RES, 3)
    assert td["next", "agent", "action_mask"].shape == (6, 3, 5)
    assert td["next", "done"][3].all()  # max_steps=4
    env.close()

    # Agents leaving: torchrl's wrapper sends an action for every agent (departed ones too), and
    # by default (done_on_any=True for parallel envs) resets as soon as one agent is done.
    env = PettingZooWrapper(env=departing(max_steps=5, departed_actions="ignore"), use_mask=True, done_on_any=False)
    td = env.rollout(4, break_when_any_done=False)
    assert td["next", "prey", "mask"].tolist() == [[True, True], [False, True], [False, False], [False, False]]
    assert td["next", "prey", "terminated"][1].squeeze(-1).tolist() == [True, False]
    env.close()
    env = PettingZooWrapper(env=departing(max_steps=5), use_mask=True, done_on_any=False)
    with pytest.raises(KeyError, match="left the episode.*departed_actions='ignore'"):
        env.rollout(4, break_when_any_done=False)
    env.close()


def test_supersuit_vectorising_chain():
    ss = pytest.importorskip("supersuit", reason="pip install supersuit to test the supersuit chain")
    env = ss.frame_stack_v1(ss.resize_v1(make("spread", seed=0), 16, 16), 2)
    vec = ss.concat_vec_envs_v1(ss.pettingzoo_env_to_vec_env_v1(env), 2, num_cpus=0, base_class="gymnasium")
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (6, 16, 16, 6) and obs.dtype == np.uint8  # 2 copies x 3 agents, 2 frames x RGB
    actions = np.array([vec.action_space.sample() for _ in range(vec.num_envs)])
    obs, reward, terminated, truncated, _ = vec.step(actions)
    assert obs.shape == (6, 16, 16, 6) and reward.shape == (6,) and terminated.shape == (6,)
    assert obs[:, :, :, 3:].std() > 0, "frames must show the arena"
    vec.close()


def test_pickling_rebuilds_the_same_configuration():
    import pickle

    env = make("spread", seed=3, resolution=24)
    copy = pickle.loads(pickle.dumps(env))
    try:
        assert copy is not env and copy.possible_agents == env.possible_agents
        first, _ = env.reset(seed=5)
        again, _ = copy.reset(seed=5)
        assert all(np.array_equal(first[a], again[a]) for a in env.possible_agents)
        assert again["agent_0"].shape == (24, 24, 3)
    finally:
        copy.close()
        env.close()
    bare = MarlRenderParallelEnv(make_env("spread", num_worlds=1, resolution=16))
    with pytest.raises(TypeError, match="only envs built by make_parallel_env can be pickled"):
        pickle.dumps(bare)
    bare.close()
