"""The PettingZoo front end (marl_render/wrappers/pettingzoo.py): PettingZoo's own API,
seed and render tests on every registered environment, agents leaving the episode, bad
input, and the wrappers users chain (supersuit, parallel_to_aec, torchrl)."""
from __future__ import annotations

import re
import sys
import warnings

import numpy as np
import pytest
import torch
from gymnasium import spaces
from gymnasium.utils.env_checker import data_equivalence
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test, render_test
from pettingzoo.utils.conversions import aec_to_parallel, parallel_to_aec

from departing_env import Departing
from marl_render.envs import list_envs, make_env
from marl_render.wrappers import window
from marl_render.wrappers.pettingzoo import ActionTypeError, MarlRenderParallelEnv, make_parallel_env

RES = 32
ENVS = list_envs()


pytestmark = pytest.mark.usefixtures("single_torch_thread")


def make(name, **kw):
    kw.setdefault("resolution", RES)
    kw.setdefault("episode_end", False)  # fixed ends: these contracts count steps (random: test_episodes.py)
    return make_parallel_env(name, **kw)


def departing(max_steps=5, **kw):
    return MarlRenderParallelEnv(make_env(Departing, num_worlds=1, resolution=RES, max_steps=max_steps, seed=0), **kw)


def sample(env, obs=None):
    return {a: env.action_space(a).sample() for a in env.agents}


def states_equal(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------------- PettingZoo's own tests
@pytest.mark.parametrize("name", ENVS)
def test_pettingzoo_tests_pass_with_default_arguments(name):
    # PettingZoo's three env tests, each with its default arguments, on the env as
    # make_parallel_env(name) builds it (default resolution, max_steps, reset options...).
    env = make_parallel_env(name)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # PettingZoo reports API deviations as warnings
        parallel_api_test(env)  # calls reset(options={"options": 1}): unknown options are ignored
    env.close()
    parallel_seed_test(lambda: make_parallel_env(name))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "human" on a headless machine warns (once per env: tested below)
        render_test(lambda render_mode=None: parallel_to_aec(make_parallel_env(name, render_mode=render_mode)))


@pytest.mark.parametrize("name", ENVS)
def test_aec_env_passes_api_test_with_default_arguments(name):
    """make_aec_env (parallel_to_aec of make_parallel_env) passes PettingZoo's api_test without a
    warning: agent names follow its <descriptor>_<number> pattern (push's agents were once team_a_0)."""
    from pettingzoo import AECEnv

    from marl_render.envs import make_aec_env

    env = make_aec_env(name)
    assert isinstance(env, AECEnv) and env.possible_agents == env.unwrapped.core.agent_names
    assert all(re.fullmatch("[a-z]+_[0-9]+", agent) for agent in env.possible_agents)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        if env.unwrapped.core.vector_obs:  # a Dict observation (matrix: pixels and inventory): api_test's advice
            warnings.filterwarnings("ignore", message="Observation is not a NumPy array")  # for Box / Discrete ones
            warnings.filterwarnings("ignore", message="Observation space for each agent probably should be")
        api_test(env)
    env.close()


@pytest.mark.parametrize("name", ENVS)
@pytest.mark.parametrize("variant", [{"continuous": True, "depth": True, "state_obs": True},
                                     {"action_mask": True, "state_obs": True}])
def test_parallel_api_test_variants(name, variant):
    env = make(name, max_steps=12, **variant)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parallel_api_test(env, num_cycles=30)  # > max_steps: the episode ends inside the test
    env.close()


def test_unknown_reset_options_are_ignored_unless_strict():
    env = make("spread", seed=0)
    first, _ = env.reset(seed=3, options={"warp": 1, "options": 1})
    again, _ = env.reset(seed=3)
    assert all(np.array_equal(first[a], again[a]) for a in env.possible_agents)
    env.close()
    strict = make("spread", unknown_options="raise")
    with pytest.raises(ValueError, match=r"unknown reset option\(s\) 'options'.*unknown_options='raise'"):
        parallel_api_test(strict, num_cycles=2)
    strict.close()


def test_a_near_miss_of_a_known_reset_option_warns_once_and_is_ignored():
    env = make("spread", seed=0)
    with pytest.warns(UserWarning, match=r"reset option 'levle' is not one this env knows; did you mean 'level'\? "
                                         r"It is ignored"):
        first, _ = env.reset(seed=3, options={"levle": 3})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per env; a key like no known one ("warp") is ignored quietly
        again, _ = env.reset(seed=3, options={"levle": 3, "warp": 1, 7: 1})
    assert all(np.array_equal(first[a], again[a]) for a in env.possible_agents)
    env.close()


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


def test_render_is_the_renderers_frame_not_the_callers_observation():
    # Observations are the caller's memory: writing into them must not change what render() shows.
    env = make("spread", render_mode="rgb_array", action_mask=True)
    obs, _ = env.reset(seed=0)
    before = env.render()
    obs["agent_0"]["pixels"][:] = 255
    obs["agent_2"]["pixels"][:] = 0
    assert np.array_equal(env.render(), before)
    obs, *_ = env.step({a: 0 for a in env.agents})
    before = env.render()
    obs["agent_1"]["pixels"][:] = 7
    assert np.array_equal(env.render(), before)
    env.close()


@pytest.mark.parametrize("name", ENVS)
def test_metadata_render_fps_is_the_simulated_rate(name):
    env = make(name)
    assert env.metadata["render_modes"] == ["human", "rgb_array"]
    assert env.metadata["render_fps"] == {"cartpole": 100.0}.get(name, 10.0) == 1 / env.core.dt
    env.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a Linux display is found through DISPLAY")
def test_human_render_on_a_headless_machine_warns_once(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    env = make("spread", render_mode="human", max_steps=3)
    with pytest.raises(RuntimeError, match="reset"):
        env.render()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env.reset(seed=0)  # "human" shows every reset and step
        while env.agents:
            env.step(sample(env))
        assert env.render() is None
    assert [str(w.message) for w in caught] == [
        "render_mode='human' shows nothing: this machine has no display (neither DISPLAY nor WAYLAND_DISPLAY is "
        "set). Use render_mode='rgb_array' to get the frames as arrays."]
    assert env.core.views.overview_renderer is None  # nothing was rendered for a window that cannot exist
    env.close()


def test_human_render_shows_the_rgb_array_frame_in_a_window(monkeypatch):
    pytest.importorskip("matplotlib", reason="render_mode='human' draws with matplotlib")
    import matplotlib.pyplot as plt

    monkeypatch.setattr(window, "window_unavailable", lambda: None)  # as on a machine with a display
    env = make("spread", render_mode="human", seed=0)
    twin = make("spread", render_mode="rgb_array", seed=0)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "FigureCanvasAgg is non-interactive")  # the test runs on Agg
        env.reset(seed=1)
        twin.reset(seed=1)
        shown = plt.figure("marl_render spread").axes[0].images[0].get_array()
        assert np.array_equal(shown, twin.render())
        env.step({a: 1 for a in env.agents})
        twin.step({a: 1 for a in twin.agents})
        assert env.render() is None
        shown = plt.figure("marl_render spread").axes[0].images[0].get_array()
        assert np.array_equal(shown, twin.render())
    env.close()
    assert "marl_render spread" not in plt.get_figlabels()
    twin.close()


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


@pytest.mark.parametrize("name", ENVS)
def test_state_is_every_agents_state_observation(name):
    env = make(name, state_obs=True, seed=0)
    space = env.state_space
    A, state_dim = len(env.possible_agents), env.core.state_dim
    assert space == spaces.Box(-np.inf, np.inf, (A * state_dim,), np.float32)
    with pytest.raises(RuntimeError, match=r"reset\(\) before state\(\)"):
        env.state()
    obs, _ = env.reset(seed=0)
    for _ in range(2):
        state = env.state()
        assert state.dtype == np.float32 and state.shape == (A * state_dim,) and space.contains(state)
        assert np.array_equal(state, np.concatenate([obs[a]["state"] for a in env.possible_agents]))
        obs, *_ = env.step({a: 1 for a in env.agents})  # forward: the state moves
        assert not np.array_equal(env.state(), state)
    env.close()


def test_state_through_torchrl_return_state():
    from torchrl.envs import PettingZooWrapper

    pz = make("tag", max_steps=4)
    env = PettingZooWrapper(env=pz, use_mask=True, return_state=True)
    td = env.rollout(3)
    assert td["next", "state"].shape == (3, *pz.state_space.shape) == (3, 4 * pz.core.state_dim)
    assert td["next", "state"].dtype == torch.float32 and td["next", "state"].std() > 0
    env.close()


STEP_STATISTICS = {  # the info keys each task declares, written out (not read from the task)
    "cartpole": set(), "spread": {"collisions", "coverage"}, "forage": {"collected", "team_score"},
    "tag": {"caught", "prey_left"}, "push": {"goal"}, "rooms": {"found", "returned", "rooms_visited"},
    "speaker_listener": {"reached", "distance", "lamp_correct"},
    "commons": {"collected", "apples_left", "tags", "depleted_at"},
    "capture_flag": {"captures_red", "captures_blue", "tags", "flag_carried"},
    "clean_up": {"eaten", "cleaned", "dirt_fraction", "apples_left", "tags"},
    "coop_mining": {"iron", "gold", "gold_lost", "ores_left"},
    "matrix": {"collected", "interactions"},
    "cooking": {"delivered", "wrong", "served"}, "territory": {"painted", "claimed", "zaps", "removed"},
}
SOCIAL = {"efficiency", "equality", "sustainability", "peace"}  # mixed-motive tasks' outcomes (envs/episodes.py)


@pytest.mark.parametrize("name", ENVS)
def test_infos_carry_the_envs_step_statistics(name):
    # spread's collisions and coverage, forage's collected and team_score, tag's caught and
    # prey_left, push's goal: the core's info of the world, per agent, as Python scalars.
    env = make(name, seed=0)
    env.reset(seed=0)
    twin = make_env(name, num_worlds=1, resolution=RES, seed=0, episode_end=False)  # as make()
    twin.reset(seed=0)
    for _ in range(3):
        actions = {a: 1 for a in env.agents}
        _, _, _, _, infos = env.step(actions)
        _, _, _, _, info = twin.step(torch.ones(1, twin.num_agents, dtype=torch.long))
        want = {k: v[0].item() for k, v in info.items() if k != "done_worlds"}
        social = SOCIAL if env.core.scenario.mixed_motive else set()
        assert set(want) == {"step_count"} | STEP_STATISTICS[name] | social
        assert infos == {agent: want for agent in actions}
        assert all(type(v) is type(want[k]) for i in infos.values() for k, v in i.items())
    env.close()
    twin.close()


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
    env = departing(max_steps=5, departed_actions="raise")
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
    with pytest.raises(KeyError, match="'prey_0'.*left the episode.*departed_actions='raise'"):
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
    env = departing(max_steps=6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parallel_api_test(env, num_cycles=10)
    aec = parallel_to_aec(departing(max_steps=6))
    api_test(aec, num_cycles=10)
    aec.close()


def test_departed_actions_are_ignored_by_default():
    env = departing()
    env.reset(seed=0)
    env.step(sample(env))
    env.step(sample(env))
    before = env.core.get_state()
    # prey_0 left: its action is ignored, even one that would be invalid, and it is not reported
    obs, rew, *_ = env.step({"predator_0": 0, "prey_0": 99, "prey_1": 0})
    assert set(obs) == set(rew) == {"predator_0", "prey_1"}
    assert torch.equal(env.core.get_state()["pos"][0, 1], before["pos"][0, 1])
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


def test_tag_last_frame_shows_the_catch():
    # The episode ends with the catch of the only prey: its last observations and render()
    # still show the prey (green) beside its catcher; the next episode starts with everybody.
    env = make("tag", num_obstacles=0, render_mode="rgb_array")
    env.reset(seed=0)
    # predator_0 within a catch of the prey, all looking along +y; predator_2 watches from behind
    state = env.core.get_state()
    state["pos"] = torch.tensor([[[0.0, 0.78], [-1.2, 1.2], [0.0, -1.0], [0.0, 0.5]]])
    state["vel"], state["yaw"] = torch.zeros(1, 4, 2), torch.zeros(1, 4)
    env.core.set_state(state)
    obs, rew, term, trunc, _ = env.step({a: 0 for a in env.agents})
    assert all(term.values()) and env.agents == [] and rew["prey_0"] == -10.0

    def green(image):
        r, g, b = image.astype(np.int32).transpose(2, 0, 1)
        return int(((g - r > 40) & (g - b > 30)).sum())

    assert green(obs["predator_2"]) > 0
    frame = env.render()
    overview = frame[:, -env.core.overview_resolution[1]:]
    assert green(overview) > 0
    env.close()


@pytest.mark.parametrize("name", ["cartpole", "spread"])
def test_continuous_actions_are_checked_as_given(name):
    # Issue 9: int arrays were accepted (the core refuses them) and float64 1.00000001 was
    # rounded to float32 1.0 before the range check.
    env = make(name, continuous=True, seed=0)
    env.reset(seed=0)
    d = env.core.action_dim
    others = {a: np.zeros(d, np.float32) for a in env.agents[1:]}
    first = env.agents[0]
    before = env.core.get_state()
    cases = [(np.ones(d, np.int64), ActionTypeError, "int64"), (np.zeros(d, np.int32), ActionTypeError, "int32"),
             (torch.zeros(d, dtype=torch.int64), ActionTypeError, "torch.int64"),
             (np.full(d, 1.00000001), ValueError, r"clip them first"),
             (np.full(d, -1 - 1e-12), ValueError, r"clip them first"),
             (torch.full((d,), 1.00000001, dtype=torch.float64), ValueError, r"clip them first"),
             (1, ActionTypeError, "got 1")]
    for action, error, message in cases:
        with pytest.raises(error, match=rf"actions\['{first}'\] must be a float array.*{message}"):
            env.step({first: action, **others})
        assert states_equal(before, env.core.get_state())
    # exactly the bounds, in any float precision, are fine
    for action in (np.ones(d), np.full(d, -1.0, np.float16), torch.ones(d, dtype=torch.bfloat16)):
        env.step({first: action, **others})
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
    env = make("spread", unknown_options="raise")
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
    with pytest.raises(ValueError, match=r"render_mode must be None or one of \['human', 'rgb_array'\], got 'ansi'"):
        make("spread", render_mode="ansi")
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

    # Agents leaving: torchrl's wrapper sends an action for every agent (departed ones too); they
    # are ignored by default. done_on_any=False keeps the episode going until every agent is done.
    env = PettingZooWrapper(env=departing(max_steps=5), use_mask=True, done_on_any=False)
    td = env.rollout(4, break_when_any_done=False)
    assert td["next", "prey", "mask"].tolist() == [[True, True], [False, True], [False, False], [False, False]]
    assert td["next", "prey", "terminated"][1].squeeze(-1).tolist() == [True, False]
    assert td["next", "done"].squeeze(-1).tolist() == [False, False, False, False]
    env.close()
    # With torchrl's default (done_on_any=True for parallel envs) the first agent to leave ends the episode.
    env = PettingZooWrapper(env=departing(max_steps=5), use_mask=True)
    td = env.rollout(4, break_when_any_done=False)
    assert td["next", "done"].squeeze(-1).tolist() == [False, True, False, True]
    env.close()
    env = PettingZooWrapper(env=departing(max_steps=5, departed_actions="raise"), use_mask=True, done_on_any=False)
    with pytest.raises(KeyError, match="left the episode.*departed_actions='raise'"):
        env.rollout(4, break_when_any_done=False)
    env.close()


def test_tag_through_torchrl_pettingzoo_wrapper_recipe():
    # docs/pettingzoo.md's recipe, on tag with two prey: the first catch removes one prey, the episode goes on.
    from torchrl.envs import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    pz = make_parallel_env("tag", num_prey=2, num_obstacles=0, resolution=RES, max_steps=10, seed=0)
    env = PettingZooWrapper(pz, use_mask=True, done_on_any=False)
    check_env_specs(env)
    td = env.reset()
    # predator_0 within a catch of prey_0 (centres 0.28 m apart), everybody else far apart; all stay put
    state = pz.core.get_state()
    state["pos"] = torch.tensor([[[0.0, 0.78], [-1.2, -1.2], [1.2, -1.2], [0.0, 0.5], [1.2, 1.2]]])
    state["vel"] = torch.zeros(1, 5, 2)
    pz.core.set_state(state)
    noop = lambda td: td.update(env.full_action_spec.zero())  # noqa: E731
    td = env.rollout(3, noop, auto_reset=False, tensordict=td, break_when_any_done=False)
    assert td["next", "prey", "mask"].tolist() == [[False, True]] * 3
    assert td["next", "prey", "terminated"][0].squeeze(-1).tolist() == [True, False]
    assert td["next", "prey", "reward"][0].squeeze(-1).tolist() == [-10.0, 0.0]
    assert td["next", "predator", "reward"][0].squeeze(-1).tolist() == [10.0] * 3
    assert not td["next", "done"].any() and pz.agents == pz.possible_agents[:3] + ["prey_1"]
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


# ----------------------------------------------------------- supersuit's vector env (docs/pettingzoo.md's recipe)
@pytest.mark.parametrize("name", ENVS)
def test_supersuit_vector_recipe_runs_through_catches_and_time_limits(name):
    """docs/pettingzoo.md's supersuit recipe (black_death=True + pettingzoo_env_to_vec_env_v1 +
    concat_vec_envs_v1) runs a few hundred steps on every env: through time-limit ends and, in
    tag, a prey caught mid-episode (before, supersuit's black_death_v3 never saw a time-limit end
    and the next step raised "the episode is over")."""
    ss = pytest.importorskip("supersuit")
    kwargs = dict(num_prey=2) if name == "tag" else {}
    env = make_parallel_env(name, resolution=16, max_steps=40, black_death=True, seed=0, episode_end=False, **kwargs)
    venv = ss.concat_vec_envs_v1(ss.pettingzoo_env_to_vec_env_v1(env), 2, num_cpus=0, base_class="gymnasium")
    A = len(env.possible_agents)
    venv.reset(seed=0)
    venv.action_space.seed(0)
    first = venv.vec_envs[0].par_env  # the copy the recipe made (PettingZoo envs pickle as their configuration)
    ends = 0
    for step in range(120):
        if name == "tag" and step == 5:  # prey_1 (entry 4) right beside predator_0: caught in the next step
            state = first.core.get_state()
            state["pos"][0, 4] = state["pos"][0, 0] + torch.tensor([0.2, 0.0])
            state["vel"][:] = 0
            first.core.set_state(state)
        obs, rewards, terminations, truncations, infos = venv.step(
            np.array([venv.action_space.sample() for _ in range(venv.num_envs)]))
        if first.core.vector_obs:  # a Dict: the pixels and the task's vectors (matrix's inventory)
            assert obs["inventory"].shape == (2 * A, first.core.vector_obs["inventory"].width)
            obs = obs["pixels"]
        assert obs.shape == (2 * A, 16, 16, first.core.pixel_channels) and rewards.shape == (2 * A,)
        done = terminations | truncations
        assert done[:A].all() == done[:A].any() and done[A:].all() == done[A:].any()  # a world ends as a whole
        ends += int(done[:A].all())
        if name == "tag" and 6 <= step < 39:  # caught at step 5: black, reward 0, not done until the time limit
            assert not obs[4].any() and rewards[4] == 0 and not done[4] and obs[3].any()
        if name == "tag" and step == 39:  # the time limit: the caught prey terminated, the others truncated
            assert terminations[:A].tolist() == [0, 0, 0, 0, 1] and truncations[:A].tolist() == [1, 1, 1, 1, 0]
            assert obs[4].any()  # already the new episode's first frame (supersuit resets in the same step)
    assert ends == 3  # time limits at steps 39, 79 and 119
    venv.close()
