"""The front ends' shared base (marl_render/wrappers/common.py) and the one sampler of random allowed
actions (envs/masking.sample_allowed): an agent whose action mask allows nothing (possible only once it
left the episode: the driver refuses such a row for an agent in it) gets action 0 on every path that
samples among allowed actions; the checks, the level guard and the reset dispatch are written once."""
from __future__ import annotations

import importlib.util
import pathlib
import re

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from marl_render.bots import Perturbed
from marl_render.envs import make_env, make_parallel_env, make_torchrl_env, make_vec_env
from marl_render.envs.evaluation import random_policy
from marl_render.envs.masking import sample_allowed, with_fallback
from marl_render.envs.tag import Tag
from marl_render.policies import heuristic_policy
from marl_render.wrappers.common import closed_on_error, reset_core
from marl_render.wrappers.gymnasium import MarlRenderVectorEnv

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = {"resolution": 8}
# Rows: agent 0 may do nothing, agent 1 only action 1, agent 2 actions 2 and 4.
MASK = torch.tensor([[[False, False, False, False, False],
                      [False, True, False, False, False],
                      [False, False, True, False, True]]])


def test_with_fallback_allows_action_0_in_rows_that_allow_nothing_and_copies():
    out = with_fallback(MASK)
    assert out.dtype == torch.bool and out.shape == MASK.shape
    assert out[0, 0].tolist() == [True, False, False, False, False]
    assert torch.equal(out[0, 1:], MASK[0, 1:])
    assert not bool(MASK[0, 0].any())  # the mask given is left as it was


def test_sample_allowed_gives_0_to_a_row_that_allows_nothing():
    for seed in range(8):
        actions = sample_allowed(MASK.expand(4, -1, -1), torch.Generator().manual_seed(seed))
        assert actions.dtype == torch.int64 and actions.shape == (4, 3)
        assert actions[:, 0].tolist() == [0] * 4 and actions[:, 1].tolist() == [1] * 4
        assert set(actions[:, 2].tolist()) <= {2, 4}


def test_random_policy_gives_0_to_a_row_that_allows_nothing():
    """envs.evaluation.random_policy had its own multinomial: an all-False row raised torch's "invalid
    multinomial distribution"."""
    env = type("Discrete", (), {"continuous": False, "num_worlds": 1, "num_agents": 3, "num_actions": 5})()
    for seed in range(8):
        actions = random_policy(env, {"action_mask": MASK}, torch.Generator().manual_seed(seed))
        assert actions.shape == (1, 3) and actions.dtype == torch.int64
        assert actions[0, :2].tolist() == [0, 1] and int(actions[0, 2]) in (2, 4)


def test_distributed_example_policy_gives_0_to_a_row_that_allows_nothing():
    """examples/distributed_collect.py's LogitsRandomPolicy masked its logits to all -inf for such a row,
    and torch's Categorical refused the NaN probabilities."""
    spec = importlib.util.spec_from_file_location("distributed_collect", ROOT / "examples" / "distributed_collect.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    policy = example.LogitsRandomPolicy(["agents"], 5)
    torch.manual_seed(0)  # Categorical.sample draws from torch's global generator
    for _ in range(8):
        td = policy(TensorDict({("agents", "action_mask"): MASK.expand(2, -1, -1)}, batch_size=[2]))
        actions = td["agents", "action"]
        assert actions[:, 0].tolist() == [0, 0] and actions[:, 1].tolist() == [1, 1]
        assert set(actions[:, 2].tolist()) <= {2, 4}


class NoNoopWhenGone(Tag):
    """tag, whose caught prey may do nothing at all (the built-in tag allows them noop)."""

    def action_mask(self, state, alive):
        return alive[:, :, None].expand(-1, -1, self.num_actions).clone()


@pytest.fixture(scope="module")
def caught():
    """A tag env (enforce_action_mask) whose prey of world 0 has left the episode: its mask row is all False."""
    env = make_env(NoNoopWhenGone, num_worlds=2, enforce_action_mask=True, **TINY)
    env.reset(seed=0)
    state = env.get_state()
    prey = env.agent_names.index(env.groups["prey"][0])
    state["alive"][0, prey] = False
    env.set_state(state)
    yield env, prey
    env.close()


def test_random_actions_give_0_to_an_agent_that_may_do_nothing(caught):
    env, prey = caught
    mask = env.scenario.action_mask(env.sim, env.alive)
    assert not bool(mask[0, prey].any()) and bool(mask[1, prey].any())
    for seed in range(6):
        actions = env.random_actions(torch.Generator().manual_seed(seed))
        assert int(actions[0, prey]) == 0
        assert bool(mask.gather(-1, actions[..., None])[..., 0][env.alive].all())
    state = env.get_state()
    env.step(actions)  # allowed for every agent in the episode: nothing is refused
    env.set_state(state)


def test_a_noisy_bot_gives_0_to_an_agent_that_may_do_nothing(caught):
    env, prey = caught
    A = env.num_agents
    worlds, slots = torch.arange(2).repeat_interleave(A), torch.arange(A).repeat(2)
    for seed in range(6):
        bot = Perturbed(heuristic_policy(), 1.0, "noisy", seed=seed)  # always the random action
        actions = bot.act(env, {}, worlds, slots).reshape(2, A)
        assert int(actions[0, prey]) == 0


# ---------------------------------------------------------------------- the shared base
class Closable:
    closed = False

    def close(self):
        self.closed = True


def test_closed_on_error_closes_only_when_the_block_raises():
    kept, dropped = Closable(), Closable()
    with closed_on_error(kept) as env:
        assert env is kept
    assert not kept.closed
    with pytest.raises(KeyError), closed_on_error(dropped):
        raise KeyError("wrapping failed")
    assert dropped.closed


def test_a_wrapper_refusing_its_core_closes_it():
    with pytest.raises(ValueError, match=r"action_mask=True needs a discrete env \(continuous=False\); continuous "
                                         r"actions have no mask"):
        make_vec_env("cartpole", 1, action_mask=True, continuous=True, **TINY)
    core = make_env("cartpole", num_worlds=1, continuous=True, **TINY)
    with pytest.raises(ValueError, match="action_mask=True needs a discrete env"):
        MarlRenderVectorEnv(core, action_mask=True)
    assert not core.closed  # a core the caller built is the caller's to close
    core.close()
    with pytest.raises(ValueError, match=r"^env is closed$"):
        MarlRenderVectorEnv(core)


def test_the_jax_front_end_refuses_a_closed_core():
    """It checked only the core's type; a closed core failed later, in the renderer."""
    from marl_render.wrappers.jax import JaxEnv

    core = make_env("cartpole", num_worlds=1, **TINY)
    core.close()
    with pytest.raises(ValueError, match=r"^core is closed$"):
        JaxEnv(core)


LEVEL_GUARD = r"needs an env built with levels= \(envs/levels.py\), and this 'cartpole' env has levels=None"


def test_every_front_end_names_a_level_option_without_levels_the_same_way():
    env = make_parallel_env("cartpole", **TINY)
    with pytest.raises(ValueError, match=rf"^options\['level'\] {LEVEL_GUARD}$"):
        env.reset(options={"level": 3})
    env.close()
    envs = make_vec_env("cartpole", 2, **TINY)
    with pytest.raises(ValueError, match=rf"^options\['level_ids'\] {LEVEL_GUARD}$"):
        envs.reset(options={"level_ids": np.array([1, 2])})
    envs.close()
    env = make_torchrl_env("cartpole", num_worlds=2, **TINY)
    with pytest.raises(ValueError, match=rf"^a 'level_ids' reset entry {LEVEL_GUARD}$"):
        env.reset(TensorDict({"level_ids": torch.tensor([1, 2])}, batch_size=[2]))
    env.close()


def test_a_first_gymnasium_reset_with_a_reset_mask_resets_every_world():
    """A first reset is a full one on every front end (TorchRL's already was); the gymnasium vector env
    sent a first reset_mask to the driver's reset_worlds, which refused it ("call reset() before ...")."""
    envs = make_vec_env("cartpole", 3, autoreset_mode="Disabled", **TINY)
    first, _ = envs.reset(seed=5, options={"reset_mask": np.array([True, False, True])})
    again, _ = envs.reset(seed=5)
    assert first.shape == (3, 8, 8, 3) and np.array_equal(first, again)
    envs.close()


def test_reset_core_dispatches_to_the_driver():
    """The one dispatch: which of reset / reset_worlds / reset_to_level runs, with which arguments."""
    calls = []

    class Core:
        num_worlds = 2

        def reset(self, seed=None):
            calls.append(("reset", seed))

        def reset_worlds(self, mask, seed=None):
            calls.append(("reset_worlds", mask.tolist(), seed))

        def reset_to_level(self, mask, levels, seed=None):
            calls.append(("reset_to_level", mask.tolist(), levels.tolist(), seed))

    core, some, levels = Core(), torch.tensor([True, False]), torch.tensor([4, 0])
    reset_core(core, 1, full=True)
    reset_core(core, 2, worlds=some, levels=levels, full=True)
    reset_core(core, 3, levels=levels, full=False)
    reset_core(core, 4, worlds=some, full=False)
    reset_core(core, 5, full=False)
    assert calls == [("reset", 1),
                     ("reset", 2), ("reset_to_level", [True, False], [4, 0], None),
                     ("reset_to_level", [True, True], [4, 0], 3),
                     ("reset_worlds", [True, False], 4),
                     ("reset", 5)]


# The checks issue 40 found repeated across the front ends: each is written only in common.py now.
REPEATED = {
    "a hand-written close on failure": r"except BaseException",
    "the core-type check": r"must be a marl_render BatchedEnv",
    "the closed-core check": r"is closed\"\)",
    "the bool check": r"must be a bool, got",
    "the render_mode check": r"render_mode must be None or one of",
    "the num_processes refusal": r"does not accept 'num_processes'",
    "the level guard": r"needs an env built with levels=",
    "the observation-key choice": r"k != \"action_mask\" or action_mask",
    "the action-mask conversion": r"astype\(np\.int8\)",
    "the reset dispatch": r"\.reset_to_level\(",
}


@pytest.mark.parametrize("what", sorted(REPEATED))
def test_no_front_end_repeats_a_shared_check(what):
    wrappers = ROOT / "marl_render" / "wrappers"
    found = [path.name for path in sorted(wrappers.glob("*.py"))
             if path.name != "common.py" and re.search(REPEATED[what], path.read_text())]
    assert found == [], f"{what} is written again in {found}; use marl_render/wrappers/common.py"


def test_the_level_guard_is_written_once_in_the_whole_package():
    """The driver, the multi-process env and the front ends all call envs/levels.require_levels."""
    sources = sorted([*(ROOT / "marl_render").rglob("*.py"), *(ROOT / "envs").rglob("*.py")])
    found = [str(path.relative_to(ROOT)) for path in sources if "needs an env built with levels=" in path.read_text()]
    assert found == ["envs/levels.py"]
