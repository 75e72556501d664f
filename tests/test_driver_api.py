"""The driver's seams that other modules and user code use (issue 40's split of envs/core.py):
the spec's vocabulary, the batch-shape name, needs_reset, kept() and action_mask()."""
from __future__ import annotations

import pytest
import torch

import marl_render.envs as envs
from marl_render.envs import BatchedEnv, BatchShape, EnvOptions, FocalEnv, actions, make_env, options, scenario, spec
from marl_render.envs.contract import HookContract
from marl_render.envs.spread import Spread
from test_envs_core import ToyScenario


def test_batch_shape_is_the_scenarios_batch_and_layout_is_the_same_class():
    assert envs.Layout is envs.BatchShape is scenario.BatchShape is scenario.Layout
    batch = envs.BatchShape(num_worlds=2, num_agents=3, continuous=False, device=torch.device("cpu"))
    task = Spread(Spread.Params(), batch)
    assert (task.num_worlds, task.num_agents, task.continuous, task.device) == tuple(batch)


def test_the_spec_decides_the_observation_keys_and_names_the_reserved_info():
    with make_env("spread", num_worlds=1, resolution=8, state_obs=True, depth=True) as env:
        assert env.obs_keys == env.spec.obs_keys == ("pixels", "depth", "state", "action_mask")
    assert envs.OBS_KEYS is spec.OBS_KEYS
    assert spec.RESERVED_INFO == spec.DRIVER_INFO + spec.GYMNASIUM_INFO
    assert {"final_info", "episode", "step_count", "final_obs"} <= set(spec.RESERVED_INFO)


# ---------------------------------------------------------------------- needs_reset
class InPlace(ToyScenario):
    """Writes into the state it is given, then fails: a call that cannot be undone."""

    def step(self, state, actions, alive, generator):
        state.pos.add_(1)
        raise ArithmeticError("the rules failed")


def test_needs_reset_until_reset_or_set_state_and_after_an_undoable_failure():
    env = BatchedEnv(InPlace, EnvOptions(num_worlds=2, resolution=8, seed=0))
    assert env.needs_reset is True
    with pytest.raises(RuntimeError, match=r"call reset\(\) before using this InPlace environment"):
        env.step(torch.zeros(2, 2, dtype=torch.int64))
    env.reset()
    assert env.needs_reset is False
    state = env.get_state()
    with pytest.raises(RuntimeError, match=r"a hook of InPlace wrote into the env's state in place \(state\.pos\)"):
        env.step(torch.zeros(2, 2, dtype=torch.int64))
    assert env.needs_reset is True
    twin = BatchedEnv(InPlace, EnvOptions(num_worlds=2, resolution=8, seed=0))
    twin.set_state(state)  # set_state starts an env too
    assert twin.needs_reset is False
    env.close(), twin.close()


def test_focal_env_shares_the_cores_needs_reset():
    with make_env("tag", num_worlds=2, resolution=8, heldout="tag/prey_vs_interceptors") as env:
        assert isinstance(env, FocalEnv) and env.needs_reset is True
        env.reset(seed=0)
        assert env.needs_reset is env.core.needs_reset is False


# ---------------------------------------------------------------------- action_mask
def test_action_mask_is_the_current_states_mask_as_a_copy():
    with make_env("rooms", num_worlds=3, resolution=8, seed=1) as env:
        with pytest.raises(RuntimeError, match=r"call reset\(\) before"):
            env.action_mask()
        obs = env.reset()
        mask = env.action_mask()
        assert mask.dtype == torch.bool and mask.shape == (3, env.num_agents, env.num_actions)
        assert torch.equal(mask, obs["action_mask"])
        obs = env.step(env.random_actions(torch.Generator().manual_seed(0)))[0]
        assert torch.equal(env.action_mask(), obs["action_mask"])
        env.action_mask().zero_()  # a copy: the env's own mask is untouched
        assert torch.equal(env.action_mask(), obs["action_mask"])
    with make_env("spread", num_worlds=1, resolution=8, continuous=True) as env:
        env.reset(seed=0)
        with pytest.raises(ValueError, match="action_mask applies to discrete actions, and this Spread env has "
                                             "continuous=True"):
            env.action_mask()


def test_focal_env_action_mask_is_the_focal_slots():
    with make_env("tag", num_worlds=2, resolution=8, heldout="tag/prey_vs_interceptors") as env:
        env.reset(seed=0)
        assert torch.equal(env.action_mask(), env.core.action_mask()[:, env.focal_slots])
        assert env.action_mask().shape == (2, env.num_agents, env.num_actions)


# ---------------------------------------------------------------------- kept
def test_kept_puts_the_env_back_when_the_block_raises_and_keeps_it_otherwise():
    with make_env("spread", num_worlds=2, resolution=8, seed=0) as env:
        env.reset()
        before = env.get_state()
        with pytest.raises(KeyError), env.kept():
            env.step(env.random_actions(torch.Generator().manual_seed(0)))
            env.reset_worlds(torch.tensor([True, False]), seed=9)
            raise KeyError("the wrapper's own part failed")
        after = env.get_state()
        assert before.keys() == after.keys()
        assert all(torch.equal(before[key], after[key]) for key in before), "kept() must undo the calls"
        assert env.seed == 0
        with env.kept():
            env.step(env.random_actions(torch.Generator().manual_seed(0)))
        assert env.step_count.tolist() == [1, 1]


# ---------------------------------------------------------------------- the parts, on their own
def test_options_resolve_to_the_settings_the_driver_publishes():
    settings = options.resolve(EnvOptions(num_worlds=2, resolution=(8, 12), grayscale=True, lidar=4), Spread,
                               Spread.Params())
    assert (settings.num_worlds, settings.num_agents, settings.resolution) == (2, Spread.default_num_agents, (8, 12))
    assert settings.pixel_channels == 1 and settings.lidar_rays == 4 and 0 <= settings.seed < 2 ** 63
    assert settings.effects == ("lighting",)
    with pytest.raises(ValueError, match=r"levels=3 needs a task whose resets draw from spawn_level"):
        options.resolve(EnvOptions(levels=3), InPlace, InPlace.Params())
    with make_env("spread", num_worlds=2, resolution=(8, 12), grayscale=True, lidar=4, seed=7) as env:
        published = {name: getattr(env, name) for name in options.PUBLISHED}
    assert published["seed"] == 7 and published["resolution"] == (8, 12) and published["pixel_channels"] == 1


def test_the_hook_contract_names_the_hook_without_an_env():
    batch = BatchShape(2, 2, False, torch.device("cpu"))
    task = ToyScenario(ToyScenario.Params(), batch)
    state = task.initial_state()
    hooks = HookContract(task, batch, state, state_obs=False)
    with pytest.raises(TypeError, match=r"ToyScenario.step must return \(state, reward, terminated, info\), got"):
        hooks.checked_step((state, None))
    with pytest.raises(ValueError, match=r"ToyScenario.step's reward must have shape \[2, 2\], a float dtype, device "
                                         r"cpu; got shape \[2\]"):
        hooks.checked_step((state, torch.zeros(2), torch.zeros(2, 2, dtype=torch.bool), {}))
    assert hooks.checked_step(task.step(state, torch.ones(2, 2, dtype=torch.int64),
                                        torch.ones(2, 2, dtype=torch.bool), None))[1].tolist() == [[1, 1], [1, 1]]


def test_actions_are_checked_against_a_spec_without_an_env():
    with make_env("spread", num_worlds=2, resolution=8) as env:
        spec_ = env.spec
    with pytest.raises(ValueError, match=r"actions must be an integer tensor of shape \[2, 3\] \(worlds, agents\) "
                                         r"with values in \[0, 5\), got values in \[0, 5\]"):
        actions.checked(torch.tensor([[0, 1, 2], [3, 4, 5]]), spec_, torch.device("cpu"))
    given = torch.tensor([[0, 1, 2], [3, 4, 4]], dtype=torch.int32)
    taken = actions.checked(given, spec_, torch.device("cpu"))
    assert taken.dtype == torch.int64 and torch.equal(taken, given.long()) and taken.data_ptr() != given.data_ptr()
