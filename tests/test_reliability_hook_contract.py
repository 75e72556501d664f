"""The fresh adversarial pass of issue 24's surfaces (docs/reliability/round4-recheck.md): each test
failed before its fix. The tasks are tests/probe_task.py's Probe with one hook changed."""
from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from marl_render.baselines.networks import Actor
from marl_render.envs import make_aec_env
from marl_render.envs.planar import Obstacles
from marl_render.policies import load_policy
from probe_task import Probe, W, assert_same, probe

pytestmark = pytest.mark.usefixtures("single_torch_thread")


def test_aec_refuses_a_bad_action_when_its_agent_gives_it():
    """parallel_to_aec stored agent_0's bad action, and the last agent's turn then raised for it, every
    turn until a reset."""
    aec = make_aec_env("spread", resolution=8, max_steps=4)
    aec.reset(seed=1)
    with pytest.raises(ValueError, match=r"actions\['agent_0'\] must be an int in \[0, 5\).*got 999"):
        aec.step(999)
    assert aec.agent_selection == "agent_0"
    for agent in ("agent_0", "agent_1", "agent_2"):  # the bad action was not kept: the turn goes round
        assert aec.agent_selection == agent
        aec.step(1)
    assert aec.agent_selection == "agent_0" and aec.unwrapped.core.step_count.tolist() == [1]
    aec.close()


@pytest.mark.parametrize("key", ["_seen_sum", "final_info", "episode"])
def test_info_keys_may_not_take_gymnasium_names(key):
    """A task's "_x" replaced the vector env's mask of "x" (and vanished from the single gymnasium env);
    "final_info" and "episode" are the vector env's and RecordEpisodeStatistics' own."""
    task = type("Named", (Probe,), {"info_keys": {"seen_sum": torch.float32, key: torch.float32}})
    with pytest.raises(ValueError, match=rf"Named.info_keys names \['{key}'\], which the driver's own"):
        probe(task)


@pytest.mark.parametrize("boxes, error", [
    (lambda: Obstacles(torch.zeros(W, 1, 2), torch.full((W, 1, 2), -0.2), torch.zeros(W, 1)),
     r"half_extent must be >= 0 .*got values in \[-0.2, -0.2\]"),  # was taken as no box
    (lambda: Obstacles(torch.zeros(1, 1, 2), torch.full((1, 1, 2), 0.2), torch.zeros(1, 1)),
     r"center \[2, K, 2\].*got center: tensor of shape \(1, 1, 2\)"),  # was world 0's box in every world
])
def test_obstacles_the_physics_would_misread_are_refused(boxes, error):
    task = type("Boxed", (Probe,), {"physics_terms": frozenset({"walls", "drag", "obstacles"}),
                                    "obstacles": lambda self, state: boxes()})
    with pytest.raises(ValueError, match="Boxed.obstacles.*" + error):
        probe(task)


def test_a_state_field_that_requires_grad_is_not_kept():
    """rules returning a field that requires grad (a task's nn.Parameter) was kept as it was."""
    def rules(self, before, moved, actions, alive, generator):
        state, reward, terminated, info = Probe.rules(self, before, moved, actions, alive, generator)
        return dataclasses.replace(state, flag=state.flag.clone().requires_grad_()), reward, terminated, info
    env = probe(type("Graphed", (Probe,), {"rules": rules}))
    env.reset()
    env.step(env.random_actions())
    assert not any(value.requires_grad for value in dataclasses.asdict(env.sim).values())
    env.close()


def test_an_action_mask_that_allows_nothing_is_named():
    """With enforce_action_mask=True such a mask made every step fail on the actions (random_actions' too),
    "allowed: []", until a reset; without it, a masked policy's logits were all -inf."""
    def action_mask(self, state, alive):
        return self.everything & torch.tensor([False, True])[None, :, None]  # agent_0 may do nothing
    env = probe(type("Stuck", (Probe,), {"action_mask": action_mask}), enforce_action_mask=True)
    with pytest.raises(ValueError, match="Stuck.action_mask must allow at least one action to every agent in the "
                                         "episode, got none for 2 agent.*world 0 agent 'agent_0'"):
        env.reset()
    env.close()


@pytest.mark.parametrize("call", ["step", "reset", "close"])
def test_a_hook_that_calls_the_env_is_refused(call):
    """rules calling env.reset() was taken and then overwritten by the step's commit (silently); env.step()
    was committed under the outer step's; env.close() left the outer step to fail in the closed renderer."""
    def rules(self, before, moved, actions, alive, generator):
        env = self.env_under_test
        env.step(env.random_actions()) if call == "step" else getattr(env, call)()
        return Probe.rules(self, before, moved, actions, alive, generator)
    env = probe(type("Reentrant", (Probe,), {"rules": rules}))
    env.reset()
    env.scenario.env_under_test = env
    before = env.get_state()
    with pytest.raises(RuntimeError, match="a hook of Reentrant called the env's step, reset.*hooks must not call"):
        env.step(env.random_actions())
    assert_same(env.get_state(), before)
    env.close()


def test_a_non_finite_state_observation_is_named():
    """observation() returning NaN went out as it was, while a NaN state or reward is named."""
    def observation(self, state, alive):
        return state.seen * torch.tensor([1.0, float("nan")])[:, None, None]  # world 1's
    env = probe(type("Blind", (Probe,), {"observation": observation}), state_obs=True)
    with pytest.raises(ValueError, match=r"Blind.observation must return finite values, got NaN or Inf in world\(s\) "
                                         r"\[1\]"):
        env.reset()
    env.close()


def _run_folder(folder, hp=None, weights=None) -> str:
    """A run folder as the trainer writes it, of a tiny actor (16 px, hidden 16), with `hp` changed."""
    folder.mkdir()
    torch.manual_seed(0)
    state = Actor("pixels", (16, 16, 3), 2, 5, 16).state_dict() if weights is None else weights
    torch.save(state, folder / "actor.pt")
    hp = {"resolution": 16, "frames": 1, "hidden": 16, "encoder": "conv", "precision": "float32", **(hp or {})}
    (folder / "result.json").write_text(json.dumps({"env": "spread", "obs": "pixels", "hyperparameters": hp}))
    return str(folder)


@pytest.mark.parametrize("hp, actor, error", [
    ({}, b"PK\x03\x04 truncated", r"actor.pt is not a state_dict that torch.save wrote"),  # torch: "weights_only=False"
    ({}, "nan", r"actor.pt holds NaN or Inf weights in \['head.4.weight'\]"),  # acted on NaN logits, silently
    ({"resolution": 10 ** 6}, None, r"hyperparameters\['resolution'\] must be an int in \[1, 16384\], got 1000000"),
    ({"frames": 0}, None, r"hyperparameters\['frames'\] must be an int in \[1, 64\], got 0"),  # a raw stride error
    ({"resolution": 24}, None, r"actor.pt does not fit the actor that .*result.json describes"),
])
def test_load_policy_refuses_hostile_run_folders(tmp_path, hp, actor, error):
    folder = _run_folder(tmp_path / "run", hp)
    if isinstance(actor, bytes):
        (tmp_path / "run" / "actor.pt").write_bytes(actor)
    elif actor == "nan":
        weights = torch.load(tmp_path / "run" / "actor.pt", weights_only=True)
        weights["head.4.weight"][0, 0] = float("nan")
        torch.save(weights, tmp_path / "run" / "actor.pt")
    with pytest.raises(ValueError, match=error):
        load_policy(folder)
