"""The batched environment core (envs/core.py) and the registry, on the real environments
and on a small toy environment that exercises agents leaving the episode."""
from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch

import marl_render as mr
from marl_render.envs import BatchedEnv, Layout, Scenario, list_envs, make_env, register_env, registry

W = 3
RES = 32
ENVS = list_envs()  # every registered environment meets the same contract


def random_actions(env, generator=None):
    """The env's own sampler, with a fixed default seed so that twins get the same actions."""
    return env.random_actions(generator or torch.Generator().manual_seed(123))


def make(name, **kw):
    kw.setdefault("num_worlds", W)
    kw.setdefault("resolution", RES)
    kw.setdefault("seed", 0)
    kw.setdefault("episode_end", False)  # fixed ends: these contracts count steps (random: test_episodes.py)
    return make_env(name, **kw)


def assert_state_equal(a: dict, b: dict):
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


# ---------------------------------------------------------------------- registry
def test_registry_lists_and_makes():
    names = list_envs()
    assert {"cartpole", "spread"} <= set(names)
    assert names == sorted(names)
    env = make_env("spread", num_worlds=1, resolution=16)
    assert isinstance(env, BatchedEnv) and env.name == "spread"
    env.close()


@pytest.mark.parametrize("name", ENVS)
def test_team_names_are_the_agent_name_prefixes(name):
    """One naming convention (docs/authoring.md): agents are <team>_<i>, i = 0, 1, ... per team, as
    TorchRL's VMAS and PettingZoo wrappers group them; a task with one team calls it "agents" (TorchRL's
    one-group name) and its agents agent_<i>. push's teams were once team_a / team_b."""
    cls = registry.env_class(name)
    teams = cls(cls.Params(), Layout(1, cls.default_num_agents, False, torch.device("cpu"))).teams
    for team, names in teams.items():
        prefix = "agent" if team == "agents" and len(teams) == 1 else team
        assert names == [f"{prefix}_{i}" for i in range(len(names))], (team, names)


def test_registry_unknown_name_lists_known():
    with pytest.raises(ValueError, match="known environments.*cartpole.*spread"):
        make_env("no_such_env")


def test_registry_unknown_kwarg_is_named():
    with pytest.raises(TypeError, match="colour_scheme"):
        make_env("cartpole", colour_scheme=3)
    with pytest.raises(TypeError, match="num_landmark"):
        make_env("spread", num_landmark=3)  # typo of num_landmarks


def test_register_refuses_duplicates_and_bad_entries():
    with pytest.raises(ValueError, match="already registered"):
        register_env("cartpole", ToyScenario)
    with pytest.raises(TypeError, match="scenario must be a Scenario subclass"):
        register_env("broken", 42)
    with pytest.raises(TypeError, match="scenario must be a Scenario subclass"):
        register_env("broken", BatchedEnv)
    register_env("toy_for_test", ToyScenario, overwrite=True)
    try:
        assert "toy_for_test" in list_envs()
        env = make_env("toy_for_test", num_worlds=2)
        assert isinstance(env.scenario, ToyScenario) and env.name == "toy"
        env.close()
    finally:
        registry._REGISTRY.pop("toy_for_test")


# ---------------------------------------------------------------------- constructor checks
@pytest.mark.parametrize("kwargs, error, words", [
    (dict(num_worlds=0), ValueError, "num_worlds"),
    (dict(num_worlds=1.5), TypeError, "num_worlds"),
    (dict(resolution="big"), TypeError, "resolution"),
    (dict(resolution=(0, 32)), ValueError, "resolution"),
    (dict(max_steps=0), ValueError, "max_steps"),
    (dict(continuous=1), TypeError, "continuous"),
    (dict(state_obs="yes"), TypeError, "state_obs"),
    (dict(depth=None), TypeError, "depth"),
    (dict(autoreset=0), TypeError, "autoreset"),
    (dict(seed=-1), ValueError, "seed"),
    (dict(seed=1.0), TypeError, "seed"),
    (dict(device="not_a_device"), ValueError, "device"),
    (dict(num_agents=2), ValueError, "num_agents"),
    (dict(num_agents=True), TypeError, "num_agents"),
])
def test_constructor_rejects_bad_arguments(kwargs, error, words):
    with pytest.raises(error, match=words):
        make("cartpole", **kwargs)


def test_spread_num_agents_range():
    with pytest.raises(ValueError, match=r"num_agents.*\[1, 12\].*13"):
        make("spread", num_agents=13)


# ---------------------------------------------------------------------- shapes and dtypes
@pytest.mark.parametrize("name", ENVS)
@pytest.mark.parametrize("continuous", [False, True])
def test_observation_and_step_shapes(name, continuous):
    env = make(name, continuous=continuous, state_obs=True, depth=True, resolution=(24, 32))
    A = env.num_agents
    # a task's own vectors (matrix's "inventory") come after the driver's and before the action mask
    expected_keys = ("pixels", "depth", "state") + tuple(env.vector_obs) + (() if continuous else ("action_mask",))
    assert env.obs_keys == expected_keys
    assert len(env.agent_names) == A and sum(map(len, env.groups.values())) == A
    assert env.resolution == (24, 32)
    obs = env.reset()
    for o in (obs, env.step(random_actions(env))[0]):
        assert tuple(o.keys()) == expected_keys
        assert o["pixels"].shape == (W, A, 24, 32, 3) and o["pixels"].dtype == torch.uint8
        assert o["depth"].shape == (W, A, 24, 32) and o["depth"].dtype == torch.float32
        assert bool(torch.isfinite(o["depth"]).all()) and float(o["depth"].min()) > 0
        assert o["state"].shape == (W, A, env.state_dim) and o["state"].dtype == torch.float32
        for key, entry in env.vector_obs.items():
            assert o[key].shape == (W, A, entry.width) and o[key].dtype == torch.float32
        if not continuous:
            assert o["action_mask"].shape == (W, A, env.num_actions) and o["action_mask"].dtype == torch.bool
    _, reward, terminated, truncated, info = env.step(random_actions(env))
    assert reward.shape == (W, A) and reward.dtype == torch.float32
    assert terminated.shape == (W, A) and terminated.dtype == torch.bool
    assert truncated.shape == (W, A) and truncated.dtype == torch.bool
    assert info["step_count"].tolist() == [2] * W
    assert info["done_worlds"].shape == (W,)
    if continuous:
        assert env.num_actions is None and env.action_dim >= 1
    else:
        assert env.action_dim is None and env.num_actions >= 2
    env.close()


@pytest.mark.parametrize("name", ["spread", "tag", "forage", "push"])
def test_arena_envs_share_the_egocentric_action_set(name):
    from marl_render.envs import egomotion

    env = make(name, num_worlds=1, resolution=8)
    assert env.action_meanings == egomotion.ACTION_MEANINGS and env.num_actions == 5
    env.close()
    env = make(name, num_worlds=1, resolution=8, continuous=True)
    assert env.action_meanings is None and env.action_dim == 2
    env.close()


@pytest.mark.parametrize("name", ["spread", "tag", "forage", "push"])
def test_every_agent_sees_its_own_view(name):
    env = make(name)
    pixels = env.reset(seed=2)["pixels"]
    for w in range(env.num_worlds):
        for i in range(env.num_agents):
            for j in range(i):
                assert not torch.equal(pixels[w, i], pixels[w, j]), (w, i, j)
    env.close()


@pytest.mark.parametrize("name", ENVS)
def test_minimal_obs_keys(name):
    env = make(name)
    assert env.obs_keys == ("pixels", *env.vector_obs, "action_mask")
    obs = env.reset()
    assert set(obs) == {"pixels", "action_mask", *env.vector_obs}
    mask = obs["action_mask"]
    assert mask.dtype == torch.bool and mask.shape == (W, env.num_agents, env.num_actions)
    assert bool(mask[..., 0].all())  # action 0 (noop, or the first force level) is valid at the start
    env.close()
    env = make(name, continuous=True)
    assert set(env.reset()) == {"pixels", *env.vector_obs}
    env.close()


@pytest.mark.parametrize("name", ENVS)
def test_pixels_are_not_constant_and_owned_by_caller(name):
    env = make(name)
    first = env.reset()["pixels"]
    assert int(first.max()) - int(first.min()) > 50
    kept = first.clone()
    # cartpole: full force; the arena tasks: backward (a task's own last action, cooking's interact, may do nothing)
    meanings = env.action_meanings
    push = meanings.index("backward") if "backward" in meanings else env.num_actions - 1
    push = torch.full((W, env.num_agents), push)
    for _ in range(20):
        later = env.step(push)[0]["pixels"]
    assert torch.equal(first, kept), "a later render overwrote earlier observations"
    assert not torch.equal(first, later)
    env.close()


# ---------------------------------------------------------------------- lifecycle
@pytest.mark.parametrize("name", ENVS)
def test_use_before_reset_raises(name):
    env = make(name)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(random_actions(env))
    with pytest.raises(RuntimeError, match="reset"):
        env.reset_worlds(torch.ones(W, dtype=torch.bool))
    with pytest.raises(RuntimeError, match="reset"):
        env.render_overview()
    env.close()


def test_close_is_idempotent_and_final():
    env = make("cartpole")
    env.reset()
    env.close()
    env.close()
    assert env.closed
    for call in (env.reset, lambda: env.step(torch.zeros(W, 1, dtype=torch.long)), env.render_overview,
                 lambda: env.reset_worlds(torch.ones(W, dtype=torch.bool)), env.get_state):
        with pytest.raises(RuntimeError, match="closed"):
            call()


def test_context_manager_closes():
    with make("spread") as env:
        env.reset()
    assert env.closed


# ---------------------------------------------------------------------- bad actions
BAD_DISCRETE = [
    (lambda A, n: torch.zeros(W, A + 1, dtype=torch.long), ValueError, r"shape \[3, \d+\]"),
    (lambda A, n: torch.zeros(W, dtype=torch.long), ValueError, "shape"),
    (lambda A, n: torch.zeros(W, A), TypeError, "integer"),
    (lambda A, n: torch.zeros(W, A, dtype=torch.bool), TypeError, "integer"),
    (lambda A, n: torch.full((W, A), n), ValueError, r"\[0, {n}\)"),  # n: the env's number of actions
    (lambda A, n: torch.full((W, A), -1), ValueError, r"\[0, {n}\)"),
    (lambda A, n: "left", TypeError, "actions"),
]
BAD_CONTINUOUS = [
    (lambda A, D: torch.zeros(W, A), ValueError, "shape"),
    (lambda A, D: torch.zeros(W, A, D, dtype=torch.long), TypeError, "float"),
    (lambda A, D: torch.full((W, A, D), float("nan")), ValueError, "NaN"),
    (lambda A, D: torch.full((W, A, D), 1.5), ValueError, r"\[-1, 1\]"),
    (lambda A, D: torch.full((W, A, D), float("-inf")), ValueError, "non-finite"),
]


@pytest.mark.parametrize("name", ENVS)
@pytest.mark.parametrize("case", range(len(BAD_DISCRETE)))
def test_bad_discrete_actions_raise_and_change_nothing(name, case):
    make_bad, error, words = BAD_DISCRETE[case]
    env, twin = make(name), make(name)
    env.reset(), twin.reset()
    env.step(random_actions(env)), twin.step(random_actions(twin))
    before = env.get_state()
    with pytest.raises(error, match="actions") as excinfo:
        env.step(make_bad(env.num_agents, env.num_actions))
    assert excinfo.match(words.format(n=env.num_actions))
    assert_state_equal(before, env.get_state())
    # ... and the env continues exactly like one that never saw the bad call.
    a = random_actions(env)
    out, out_twin = env.step(a), twin.step(a)
    assert torch.equal(out[0]["pixels"], out_twin[0]["pixels"])
    assert torch.equal(out[1], out_twin[1])
    env.close(), twin.close()


@pytest.mark.parametrize("name", ENVS)
@pytest.mark.parametrize("case", range(len(BAD_CONTINUOUS)))
def test_bad_continuous_actions_raise_and_change_nothing(name, case):
    make_bad, error, words = BAD_CONTINUOUS[case]
    env = make(name, continuous=True)
    env.reset()
    env.step(random_actions(env))
    before = env.get_state()
    with pytest.raises(error, match="actions") as excinfo:
        env.step(make_bad(env.num_agents, env.action_dim))
    assert excinfo.match(words)
    assert_state_equal(before, env.get_state())
    env.close()


def test_actions_accept_numpy_and_lists():
    """A numpy int32 array and a nested list step exactly like the same int64 tensors."""
    env, twin = make("spread", num_worlds=2), make("spread", num_worlds=2)
    env.reset()
    twin.reset()
    for given in (np.zeros((2, 3), dtype=np.int32), [[1, 2, 3], [4, 0, 1]]):
        got, expected = env.step(given), twin.step(torch.tensor(np.asarray(given), dtype=torch.int64))
        for key in expected[0]:
            assert torch.equal(got[0][key], expected[0][key]), key
        for a, b in zip(got[1:4], expected[1:4], strict=True):
            assert torch.equal(a, b)
    env.close()
    twin.close()


@pytest.mark.parametrize("continuous", [False, True])
def test_actions_with_negative_strides_are_accepted(continuous):
    """A reversed numpy view (negative strides, which torch cannot wrap) steps like its copy."""
    env, twin = make("spread", num_worlds=2, continuous=continuous), make("spread", num_worlds=2, continuous=continuous)
    env.reset(), twin.reset()
    actions = random_actions(env).numpy()[::-1]
    if continuous:
        actions = actions[:, :, ::-1]
    assert any(stride < 0 for stride in actions.strides)
    got, expected = env.step(actions), twin.step(torch.from_numpy(actions.copy()))
    assert torch.equal(got[0]["pixels"], expected[0]["pixels"]) and torch.equal(got[1], expected[1])
    env.close(), twin.close()


# ---------------------------------------------------------------------- determinism and resets
@pytest.mark.parametrize("name", ENVS)
def test_same_seed_is_bit_identical(name):
    runs = []
    for _ in range(2):
        env = make(name, seed=7, state_obs=True)
        trace = [env.reset()]
        g = torch.Generator().manual_seed(1)
        for _ in range(4):
            trace.append(env.step(env.random_actions(g))[:2])
        runs.append(trace)
        env.close()
    first, second = runs
    for key in first[0]:
        assert torch.equal(first[0][key], second[0][key])
    for (obs_a, rew_a), (obs_b, rew_b) in zip(first[1:], second[1:], strict=True):
        assert torch.equal(rew_a, rew_b)
        for key in obs_a:
            assert torch.equal(obs_a[key], obs_b[key]), key


@pytest.mark.parametrize("name", ENVS)
def test_seeds_differ_and_reset_seed_reproduces(name):
    env = make(name, seed=1, state_obs=True)
    a = env.reset()["state"]
    b = env.reset()["state"]  # generator moved on: a new episode
    assert not torch.equal(a, b)
    c = env.reset(seed=1)["state"]  # re-seeded: the first episode again
    assert torch.equal(a, c)
    assert env.seed == 1
    other = make(name, seed=2, state_obs=True)
    assert not torch.equal(a, other.reset()["state"])
    env.close(), other.close()


# ---------------------------------------------------------------------- explicit state
def run_steps(env, actions) -> list:
    """(obs, reward, terminated, truncated, info) of each step, every tensor copied."""
    out = []
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        out.append(({k: v.clone() for k, v in obs.items()}, reward, terminated, truncated, dict(info)))
    return out


def assert_steps_equal(a: list, b: list):
    assert len(a) == len(b)
    for (obs_a, *out_a, info_a), (obs_b, *out_b, info_b) in zip(a, b, strict=True):
        assert obs_a.keys() == obs_b.keys() and info_a.keys() == info_b.keys()
        for key in obs_a:
            assert torch.equal(obs_a[key], obs_b[key]), key
        for x, y in zip(out_a, out_b, strict=True):
            assert torch.equal(x, y)
        for key in info_a:
            if isinstance(info_a[key], dict):  # same-step autoreset: info["final_obs"]
                assert info_a[key].keys() == info_b[key].keys(), key
                assert all(torch.equal(info_a[key][k], info_b[key][k]) for k in info_a[key]), key
            else:
                assert torch.equal(info_a[key], info_b[key]), key


@pytest.mark.parametrize("name", ENVS)
def test_set_state_restores_the_env_exactly(name):
    # autoreset with a short max_steps: the steps after the restore reset worlds, so the RNG counts.
    kw = dict(autoreset=True, max_steps=4, state_obs=True, depth=True)
    env = make(name, **kw)
    env.reset(seed=3)
    g = torch.Generator().manual_seed(2)
    for _ in range(2):
        env.step(env.random_actions(g))
    saved = env.get_state()
    assert {"step_count", "alive", "rng"} <= saved.keys() and saved["rng"].dtype == torch.uint8
    actions = [env.random_actions(g) for _ in range(6)]
    first = run_steps(env, actions)
    assert not torch.equal(env.get_state()["rng"], saved["rng"])  # the autoresets drew from the generator
    env.set_state(saved)
    assert_state_equal(saved, env.get_state())
    assert_steps_equal(first, run_steps(env, actions))
    # An env built with another seed and never reset continues the same way from that state.
    twin = make(name, seed=99, **kw)
    twin.set_state(saved)
    assert_steps_equal(first, run_steps(twin, actions))
    env.close(), twin.close()


def first_float_key(state: dict) -> str:
    return next(k for k, v in state.items() if v.is_floating_point())


BAD_STATES = [  # (change the state, error, words of the message)
    (lambda s: list(s.items()), TypeError, r"state must be a dict"),
    (lambda s: {k: v for k, v in s.items() if k != "alive"}, ValueError, r"missing \['alive'\]"),
    (lambda s: {**s, "extra": torch.zeros(3)}, ValueError, r"unknown \['extra'\]"),
    (lambda s: {**s, "step_count": s["step_count"].tolist()}, TypeError,
     r"state\['step_count'\] must be a torch.Tensor"),
    (lambda s: {**s, "step_count": s["step_count"][:-1]}, ValueError,
     r"state\['step_count'\] must have shape \[3\], got \[2\]"),
    (lambda s: {**s, "alive": s["alive"].int()}, ValueError,
     r"state\['alive'\] must have dtype torch.bool, got torch.int32"),
    (lambda s: {**s, "rng": s["rng"].to("meta")}, ValueError, r"state\['rng'\] must have device cpu, got meta"),
    (lambda s: {**s, first_float_key(s): torch.full_like(s[first_float_key(s)], float("nan"))}, ValueError,
     r"must be finite"),
    (lambda s: {**s, "step_count": s["step_count"] - 10}, ValueError, r"state\['step_count'\] must be >= 0"),
    (lambda s: {**s, "step_count": torch.full_like(s["step_count"], 2 ** 63 - 1)}, ValueError,
     r"state\['step_count'\] must be >= 0 and <= \d+"),  # without autoreset: any count a world can reach
    (lambda s: {**s, first_float_key(s): torch.full_like(s[first_float_key(s)], 3e38)}, ValueError,
     r"state\['\w+'\] must be within \["),
    (lambda s: {**s, "rng": torch.zeros_like(s["rng"])}, ValueError, r"state\['rng'\] must be a torch.Generator state"),
]


@pytest.mark.parametrize("name", ["spread", "cartpole"])  # an arena env and one with its own state
def test_set_state_rejects_bad_states_and_changes_nothing(name):
    env, twin = make(name), make(name)
    env.reset(), twin.reset()
    env.step(random_actions(env)), twin.step(random_actions(twin))
    before = env.get_state()
    for change, error, words in BAD_STATES:
        with pytest.raises(error, match=words):
            env.set_state(change(env.get_state()))
        assert_state_equal(before, env.get_state())
    # ... and the env continues exactly like one that never saw the bad calls.
    a = [random_actions(env, torch.Generator().manual_seed(s)) for s in range(2)]
    assert_steps_equal(run_steps(env, a), run_steps(twin, a))
    env.close()
    with pytest.raises(RuntimeError, match="closed"):
        env.set_state(before)
    twin.close()


@pytest.mark.parametrize("name, key, low, high", [
    ("tag", "pos", -1.5, 1.5), ("tag", "obstacle_center", -1.5, 1.5), ("spread", "landmarks", -1.5, 1.5),
    ("spread", "vel", -1e6, 1e6), ("cartpole", "qstate", -1.8, 1.8)])  # qstate[:, 0]: the cart on its rail
def test_set_state_checks_ranges_that_have_meaning(name, key, low, high):
    """Positions must be inside the walls, other floats within +-1e6, step_count within [0, max_steps]:
    values beyond them (3e38 positions, a wrapping step counter) would lose the env on its next step."""
    env = make(name)
    env.reset()
    before = env.get_state()
    bound = re.escape(f"{abs(low):g}")
    for bad in (high * 1.01, low * 1.01, 3e38):
        state = env.get_state()
        state[key][0, 0] = bad
        with pytest.raises(ValueError, match=rf"state\['{key}'\] must be within \[.*{bound}.*\], got values"):
            env.set_state(state)
        assert_state_equal(before, env.get_state())
    state = env.get_state()
    state[key][0, 0] = high  # the bounds themselves are fine
    state["step_count"][:] = env.max_steps  # a finished episode: the next step truncates
    env.set_state(state)
    _, reward, terminated, truncated, info = env.step(random_actions(env))
    assert bool(torch.isfinite(reward).all()) and bool((terminated | truncated).all())
    env.close()


def test_set_state_copies_what_it_is_given():
    env = make("spread")
    env.reset()
    state = env.get_state()
    env.set_state(state)
    state["pos"].fill_(0.5)  # the caller's tensors stay the caller's
    assert not torch.equal(env.get_state()["pos"], state["pos"])
    env.close()


@pytest.mark.parametrize("name", ENVS)
def test_partial_reset_leaves_other_worlds_identical(name):
    env = make(name, state_obs=True)
    env.reset()
    for _ in range(5):
        obs = env.step(random_actions(env))[0]
    before = env.get_state()
    mask = torch.tensor([False, True, False])
    new = env.reset_worlds(mask)
    after = env.get_state()
    keep = ~mask
    for key, value in before.items():
        if key == "rng":
            continue
        assert torch.equal(value[keep], after[key][keep]), key
    assert after["step_count"].tolist() == [5, 0, 5]
    assert torch.equal(new["pixels"][keep], obs["pixels"][keep])
    assert torch.equal(new["state"][keep], obs["state"][keep])
    assert not torch.equal(new["state"][1], obs["state"][1])
    env.close()


def test_reset_worlds_rejects_bad_mask():
    env = make("cartpole")
    env.reset()
    before = env.get_state()
    with pytest.raises(ValueError, match=r"mask.*\[3\]"):
        env.reset_worlds(torch.ones(2, dtype=torch.bool))
    with pytest.raises(TypeError, match="mask.*bool"):
        env.reset_worlds(torch.ones(3))
    assert_state_equal(before, env.get_state())
    env.close()


@pytest.mark.parametrize("name", ENVS)
def test_truncation_at_max_steps_without_autoreset(name):
    env = make(name, max_steps=4)
    env.reset()
    for step in range(1, 7):
        _, _, terminated, truncated, info = env.step(random_actions(env))
        assert not bool(terminated.any())
        assert bool(truncated.all()) == (step >= 4) and bool(truncated.any()) == (step >= 4)
        assert info["done_worlds"].tolist() == [step >= 4] * W
    assert env.step_count.tolist() == [6] * W  # no auto-reset by default
    env.close()


@pytest.mark.parametrize("name", ENVS)
def test_autoreset_starts_a_new_episode(name):
    env = make(name, max_steps=3, autoreset=True, state_obs=True)
    env.reset(seed=3)
    reference = make(name, max_steps=3, state_obs=True)
    reference.reset(seed=3)
    for _ in range(3):
        a = random_actions(env)
        obs, _, _, truncated, info = env.step(a)
        reference.step(a)
    assert bool(truncated.all()) and info["done_worlds"].all()
    assert env.step_count.tolist() == [0] * W
    # The returned obs are the first obs of the new episode (the same draw as reset_worlds).
    first = reference.reset_worlds(torch.ones(W, dtype=torch.bool))
    assert torch.equal(obs["state"], first["state"])
    assert torch.equal(obs["pixels"], first["pixels"])
    _, _, _, truncated, _ = env.step(random_actions(env))
    assert not bool(truncated.any())
    env.close(), reference.close()


# ---------------------------------------------------------------------- overview and physics terms
@pytest.mark.parametrize("name", ENVS)
def test_render_overview(name):
    env = make(name)
    env.reset()
    assert env.views.overview_renderer is None  # built lazily
    view = env.render_overview()
    assert view.dtype == torch.uint8 and view.shape == (W, *env.overview_resolution, 3)
    assert int(view.max()) - int(view.min()) > 50
    small = env.render_overview(resolution=(20, 30))
    assert small.shape == (W, 20, 30, 3)
    env.step(random_actions(env))
    assert env.render_overview(resolution=(20, 30)).shape == (W, 20, 30, 3)
    env.close()


# The physics terms each built-in env declares (cartpole integrates its own ODE).
DECLARED_TERMS = {
    "cartpole": set(),
    "spread": {"walls", "body_collisions", "drag"},
    "forage": {"walls", "body_collisions", "drag"},
    "push": {"walls", "body_collisions", "drag"},
    "tag": {"walls", "body_collisions", "drag", "obstacles"},
    'speaker_listener': {'body_collisions', 'walls', 'drag'},
    'rooms': {'walls', 'body_collisions', 'drag', 'obstacles'},
    "commons": {"walls", "body_collisions", "drag"},
    "capture_flag": {"walls", "body_collisions", "drag"},
    "clean_up": {"walls", "body_collisions", "drag"},
    "coop_mining": {"walls", "body_collisions", "drag"},
    "matrix": {"walls", "body_collisions", "drag"},
    "cooking": {"walls", "body_collisions", "drag", "obstacles"},
    "territory": {"walls", "body_collisions", "drag", "obstacles"},
}


@pytest.mark.parametrize("name", ENVS)
def test_only_declared_physics_terms_run(name, check_only_declared_terms):
    env = make(name)
    assert env.physics_terms == DECLARED_TERMS[name]
    check_only_declared_terms(env)
    env.close()


# ---------------------------------------------------------------------- agents leaving the episode
@dataclasses.dataclass(frozen=True)
class ToyState:
    pos: torch.Tensor  # [W, 2] the agents' places on the line


class ToyScenario(Scenario):
    """Two agents on a line. Action 1 moves an agent one unit and earns 1; agent 1 leaves
    the episode (terminated) when it reaches position 2; both leave at position 3."""

    name = "toy"
    default_num_agents = 2
    agent_range = (2, 2)
    default_max_steps = 10
    default_resolution = 8

    def setup(self):
        self.teams = {"runner": ["runner_0"], "walker": ["walker_0"]}
        self.discrete_actions(("stay", "move"))
        self.continuous_actions(1)
        self.state_dim = 1

    def initial_state(self):
        return ToyState(pos=torch.zeros(self.num_worlds, 2))

    def spawn(self, generator):
        return self.initial_state()

    def step(self, state, actions, alive, generator):
        if self.continuous:
            actions = (actions[..., 0] > 0).long()
        move = (actions == 1) & alive
        pos = state.pos + move
        terminated = torch.zeros_like(alive)
        terminated[:, 1] = pos[:, 1] >= 2
        terminated |= (pos >= 3)
        # Rewarded for asking to move, alive or not: the core must zero the reward of
        # agents that had already left the episode.
        return ToyState(pos=pos), (actions == 1).float(), terminated, {}

    def build_scene(self, scene, overview):
        scene.add_static("floor", "plane", position=[0, 0, 0], scale=[10, 10, 1])
        scene.add_group("bodies", "box", capacity=2)
        if not overview:
            scene.mount_cameras("bodies", instance=[0, 1], offset=(0, 0, 0.5))

    def instances(self, state, full):
        position = torch.zeros(self.num_worlds, 2, 3)
        position[..., 0] = state.pos
        out = {"position": position}
        if full:
            out["active"] = torch.ones(self.num_worlds, 2, dtype=torch.bool)
        return {"bodies": out}

    def observation(self, state, alive):
        return state.pos[..., None]


def ToyEnv(**kwargs) -> BatchedEnv:  # noqa: N802 (reads like the class it builds)
    return make_env(ToyScenario, **kwargs)


def test_dead_agents_are_ignored_but_keep_their_slot():
    env = ToyEnv(num_worlds=2, seed=0, max_steps=10)
    assert env.groups == {"runner": ["runner_0"], "walker": ["walker_0"]}
    env.reset()
    move = torch.ones(2, 2, dtype=torch.long)
    for _ in range(2):
        obs, reward, terminated, truncated, info = env.step(move)
    assert terminated.tolist() == [[False, True]] * 2
    assert env.alive.tolist() == [[True, False]] * 2
    assert reward.tolist() == [[1.0, 1.0]] * 2  # the terminating step is still rewarded
    obs, reward, terminated, truncated, info = env.step(move)
    assert env.sim.pos.tolist() == [[3.0, 2.0]] * 2  # the dead walker's action was ignored
    assert reward.tolist() == [[1.0, 0.0]] * 2
    assert terminated.tolist() == [[True, True]] * 2  # runner reached 3, walker stays terminated
    assert info["done_worlds"].tolist() == [True, True]
    assert obs["pixels"].shape == (2, 2, 8, 8, 3)
    env.reset_worlds(torch.tensor([True, False]))
    assert env.alive.tolist() == [[True, True], [False, False]]
    env.close()


def test_truncation_only_for_agents_still_alive():
    env = ToyEnv(num_worlds=1, seed=0, max_steps=3)
    env.reset()
    env.step(torch.tensor([[0, 1]]))
    env.step(torch.tensor([[0, 1]]))  # walker leaves at 2
    _, _, terminated, truncated, info = env.step(torch.tensor([[0, 1]]))
    assert terminated.tolist() == [[False, True]]
    assert truncated.tolist() == [[True, False]]
    assert info["done_worlds"].tolist() == [True]
    env.close()


def test_autoreset_when_all_agents_left():
    env = ToyEnv(num_worlds=2, seed=0, autoreset=True)
    env.reset()
    env.step(torch.tensor([[1, 1], [0, 0]]))
    env.step(torch.tensor([[1, 1], [0, 0]]))
    _, _, terminated, _, info = env.step(torch.tensor([[1, 1], [0, 0]]))
    assert terminated.tolist() == [[True, True], [False, False]]
    assert info["done_worlds"].tolist() == [True, False]
    assert env.sim.pos.tolist() == [[0.0, 0.0], [0.0, 0.0]]
    assert env.alive.tolist() == [[True, True], [True, True]]
    assert env.step_count.tolist() == [0, 3]
    env.close()


def test_scenery_yaw_and_heading_agree_with_renderer_convention():
    from marl_render.envs import scenery
    from marl_render.transforms import quat_rotate

    yaw = torch.tensor([0.0, 0.5, -2.0, 3.0])
    forward = quat_rotate(scenery.yaw_quat(yaw).double(), torch.tensor([0.0, 1.0, 0.0]).double().expand(4, 3))
    assert torch.allclose(forward[:, :2].float(), scenery.heading(yaw), atol=1e-6)
    assert torch.allclose(scenery.yaw_quat(yaw), mr.quat_from_yaw_pitch_roll(yaw), atol=1e-6)


def test_torch_threads_inside_calls_and_restored(monkeypatch):
    seen = []
    env = make("cartpole", torch_threads=1)
    original = env.scenario.step
    monkeypatch.setattr(env.scenario, "step", lambda *a: seen.append(torch.get_num_threads()) or original(*a))
    saved = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        env.reset()
        env.step(torch.zeros(W, 1, dtype=torch.long))
        assert seen == [1] and torch.get_num_threads() == 2
        with pytest.raises(ValueError, match="actions"):
            env.step(torch.full((W, 1), 99))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(saved)
        env.close()
    with pytest.raises(ValueError, match="torch_threads"):
        make("cartpole", torch_threads=0)


@pytest.mark.parametrize("name", ENVS)
@pytest.mark.parametrize("continuous", [False, True])
def test_random_actions_are_valid_and_seeded(name, continuous):
    env = make(name, continuous=continuous)
    a = env.random_actions(torch.Generator().manual_seed(5))
    b = env.random_actions(torch.Generator().manual_seed(5))
    assert torch.equal(a, b)
    if continuous:
        assert a.shape == (env.num_worlds, env.num_agents, env.action_dim) and a.dtype == torch.float32
        assert (a.abs() <= 1).all()
    else:
        assert a.shape == (env.num_worlds, env.num_agents) and a.dtype == torch.int64
        assert ((a >= 0) & (a < env.num_actions)).all()
    assert torch.equal(env.check_actions(a), a.to(env.check_actions(a).dtype))
    env.close()


# ---------------------------------------------------------------------- accuracy options
def edges(pixels):
    """[..., H, W] bool: pixels with a 4-neighbour of another colour."""
    edge = torch.zeros(pixels.shape[:-1], dtype=torch.bool)
    step = (pixels[..., 1:, :, :] != pixels[..., :-1, :, :]).any(-1)
    edge[..., 1:, :] |= step
    edge[..., :-1, :] |= step
    step = (pixels[..., :, 1:, :] != pixels[..., :, :-1, :]).any(-1)
    edge[..., :, 1:] |= step
    edge[..., :, :-1] |= step
    return edge


def test_multisamples_smooth_edges_of_the_same_scene():
    plain, msaa = make("spread"), make("spread", multisamples=4)
    a, b = plain.reset()["pixels"], msaa.reset()["pixels"]
    assert b.shape == a.shape and b.dtype == torch.uint8
    assert msaa.renderer.granted_multisamples == 4 and plain.renderer.granted_multisamples == 0
    differ = (a != b).any(-1)
    # Only pixels at edges change (a sub-pixel object that only the extra samples hit makes an edge
    # in the MSAA image): a small share, each with a neighbour of another colour in one of the two.
    assert 0 < differ.float().mean() < 0.2
    assert bool((differ <= (edges(a) | edges(b))).all())
    plain.close(), msaa.close()


def test_supersample_keeps_shapes_and_changes_only_edges():
    plain, ss = make("forage"), make("forage", supersample=2)
    a, b = plain.reset()["pixels"], ss.reset()["pixels"]
    assert b.shape == a.shape and b.dtype == torch.uint8
    assert 0 < (a != b).any(-1).float().mean() < 0.3
    plain.close(), ss.close()


def test_physics_substeps_change_the_dynamics_not_the_rest():
    default, fine = make("spread"), make("spread", physics_substeps=8)
    assert (default.physics.substeps, fine.physics.substeps) == (2, 8)
    assert fine.physics.dt == default.physics.dt
    default.reset(), fine.reset()
    assert_state_equal(default.get_state(), fine.get_state())  # the same episode starts
    for _ in range(5):
        actions = random_actions(default)
        default.step(actions), fine.step(actions)
    pos_a, pos_b = default.get_state()["pos"], fine.get_state()["pos"]
    assert not torch.equal(pos_a, pos_b) and float((pos_a - pos_b).abs().max()) < 0.05
    default.close(), fine.close()


@pytest.mark.parametrize(("name", "kwargs", "error", "words"), [
    ("spread", dict(physics_substeps=1), ValueError, "physics_substeps=1 is too coarse for spread"),
    ("spread", dict(physics_substeps=0), ValueError, "physics_substeps must be an int >= 1, got 0"),
    ("spread", dict(physics_substeps=2.0), TypeError, "physics_substeps"),
    ("spread", dict(physics_substeps=10 ** 9), ValueError, "physics_substeps must be an int in [1, 1024], got"),
    ("spread", dict(multisamples=64), mr.backend.GLUnavailableError, "and 64 MSAA samples (multisamples"),
    ("cartpole", dict(physics_substeps=4), ValueError, "cartpole has none"),
    ("spread", dict(multisamples=4, depth=True), ValueError, "multisamples cannot be combined with the depth"),
    ("spread", dict(multisamples=-1), ValueError, "multisamples must be an int >= 0"),
    ("spread", dict(supersample=0), ValueError, "supersample"),
])
def test_accuracy_options_refuse_bad_values(name, kwargs, error, words):
    with pytest.raises(error, match=re.escape(words)):
        make(name, **kwargs)
