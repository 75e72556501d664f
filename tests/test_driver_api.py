"""The driver's seams that other modules and user code use (issue 40's split of envs/core.py):
the spec's vocabulary, the batch-shape name, needs_reset, kept() and action_mask()."""
from __future__ import annotations

import torch

import marl_render.envs as envs
from marl_render.envs import make_env, scenario, spec
from marl_render.envs.spread import Spread


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
