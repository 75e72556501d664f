"""Action masks: advice by default (documented), refused by the driver with enforce_action_mask=True
(envs/masking.py), through the core, PettingZoo and TorchRL."""
import pytest
import torch
from pettingzoo.test import parallel_api_test
from torchrl.envs.utils import check_env_specs

from marl_render.envs import ArenaScenario, make_env, make_parallel_env, make_torchrl_env

FORWARD = 1


class Gate(ArenaScenario):
    """Two agents; the mask lets agent 0 ("held_0") only noop and turn left, agent 1 anything."""

    name = "gate"
    default_num_agents = 2
    agent_range = (2, 2)
    default_max_steps = 3
    physics_terms = frozenset({"walls", "drag"})

    def setup(self):
        self.setup_arena({"held": ["held_0"], "free": ["free_0"]}, state_dim=0, radius=0.15, max_speed=2.0)

    def initial_state(self):
        W = self.num_worlds
        return self.at_rest(torch.tensor([[-0.5, 0.0], [0.5, 0.0]]).expand(W, 2, 2), torch.zeros(W, 2))

    def spawn(self, generator):
        return self.initial_state()

    def action_mask(self, state, alive):
        mask = torch.ones(self.num_worlds, 2, self.num_actions, dtype=torch.bool, device=self.device)
        mask[:, 0] = torch.tensor([True, False, True, False, False])
        return mask

    def rules(self, before, moved, actions, alive, generator):
        return moved, torch.zeros_like(alive, dtype=torch.float32), torch.zeros_like(alive), {}


def same_state(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_masks_are_advice_by_default():
    # What docs/authoring.md says: a masked action is still taken unless the mask is enforced.
    env = make_env(Gate, num_worlds=2, resolution=8, seed=0)
    obs = env.reset()
    assert obs["action_mask"][:, 0, FORWARD].tolist() == [False, False]
    env.step(torch.full((2, 2), FORWARD))
    assert bool((env.sim.pos[:, 0, 1] > 0).all())  # held_0 moved forward (+y) although its mask forbids it
    env.close()


def test_enforced_masks_refuse_forbidden_actions_and_change_nothing():
    env = make_env(Gate, num_worlds=3, resolution=8, seed=0, enforce_action_mask=True)
    env.reset()
    env.step(torch.tensor([[2, 1]] * 3))  # held_0 turns left (allowed), free_0 goes forward
    before = env.get_state()
    actions = torch.tensor([[0, 1], [1, 4], [4, 0]])
    with pytest.raises(ValueError) as refused:
        env.step(actions)
    message = str(refused.value)
    assert ("got 2 forbidden: world 1 agent 'held_0' took 1 ('forward'), allowed: [0 ('noop'), 2 ('turn_left')]; "
            "world 2 agent 'held_0' took 4 ('backward'), allowed: [0 ('noop'), 2 ('turn_left')]") in message
    assert "enforce_action_mask=True" in message
    assert same_state(env.get_state(), before)  # positions, counters and the generator as they were
    obs, reward, terminated, truncated, info = env.step(torch.tensor([[0, 1], [2, 4], [0, 0]]))
    assert info["step_count"].tolist() == [2, 2, 2] and obs["action_mask"].shape == (3, 2, 5)
    env.close()


def test_enforced_masks_ignore_agents_and_worlds_whose_actions_are_ignored():
    # tag: a caught prey has left the episode (its mask allows only noop); its action is ignored, so
    # it is not checked either.
    env = make_env("tag", num_worlds=2, resolution=8, seed=0, enforce_action_mask=True)
    env.reset()
    state = env.get_state()
    prey = env.agent_names.index("prey_0")
    state["alive"][0, prey] = False
    env.set_state(state)
    mask = env.scenario.action_mask(env.sim, env.alive)
    assert not bool(mask[0, prey, FORWARD]) and bool(mask[env.alive, FORWARD].all())
    env.step(torch.full((2, env.num_agents), FORWARD))  # the departed prey's forward is not refused
    env.close()
    # next_step autoreset: a world whose episode ended restarts on the next step, its actions ignored.
    env = make_env(Gate, num_worlds=2, resolution=8, seed=0, enforce_action_mask=True, autoreset="next_step")
    env.reset()
    for _ in range(3):
        env.step(torch.zeros(2, 2, dtype=torch.long))
    assert env.episode_over().tolist() == [True, True]
    obs, *_, info = env.step(torch.full((2, 2), FORWARD))  # restarts both worlds: nothing refused
    assert info["autoreset_worlds"].tolist() == [True, True]
    with pytest.raises(ValueError, match="world 0 agent 'held_0' took 1"):
        env.step(torch.full((2, 2), FORWARD))
    env.close()


def test_random_actions_are_allowed_ones_when_masks_are_enforced():
    env = make_env(Gate, num_worlds=64, resolution=8, seed=0, enforce_action_mask=True)
    env.reset()
    actions = torch.stack([env.random_actions(torch.Generator().manual_seed(i)) for i in range(8)])  # [8, 64, 2]
    assert set(actions[..., 0].unique().tolist()) == {0, 2}  # only noop and turn_left for held_0
    assert set(actions[..., 1].unique().tolist()) == {0, 1, 2, 3, 4}
    env.step(env.random_actions())
    env.close()


def test_enforce_action_mask_is_checked():
    with pytest.raises(TypeError, match="enforce_action_mask must be a bool, got 1"):
        make_env("spread", resolution=8, enforce_action_mask=1)
    with pytest.raises(ValueError, match="enforce_action_mask applies to discrete actions"):
        make_env("spread", resolution=8, enforce_action_mask=True, continuous=True)


def test_builtin_heuristics_obey_their_masks():
    # commons masks tagged agents to noop, tag departed prey: with half the agents zapping and running
    # at random (among allowed actions) and the others on the heuristic, no step is refused.
    for name in ("commons", "tag", "speaker_listener"):
        env = make_env(name, num_worlds=4, resolution=8, seed=0, enforce_action_mask=True, max_steps=40)
        env.reset()
        scripted = torch.arange(env.num_agents) % 2 == 0
        generator = torch.Generator().manual_seed(0)
        limited = 0
        for _ in range(40):
            limited += int(((~env.scenario.action_mask(env.sim, env.alive)).any(-1) & env.alive).sum())
            actions = torch.where(scripted, env.heuristic_actions(), env.random_actions(generator))
            env.step(actions)
        if name == "commons":
            assert limited > 0  # someone was tagged: the mask of an agent in play was not all True
        env.close()


def test_pettingzoo_refuses_forbidden_actions_when_enforced():
    env = make_parallel_env(Gate, resolution=8, action_mask=True, enforce_action_mask=True)
    parallel_api_test(env, num_cycles=10)  # samples with the mask, as PettingZoo's test does
    env.reset(seed=0)
    before = env.core.get_state()
    with pytest.raises(ValueError, match=r"world 0 agent 'held_0' took 1 \('forward'\)"):
        env.step({"held_0": FORWARD, "free_0": FORWARD})
    assert same_state(env.core.get_state(), before)
    _, _, _, _, infos = env.step({"held_0": 2, "free_0": FORWARD})
    assert set(infos) == {"held_0", "free_0"}
    env.close()


def test_torchrl_refuses_forbidden_actions_when_enforced():
    env = make_torchrl_env(Gate, num_worlds=2, resolution=8, enforce_action_mask=True, group_map="one_group")
    check_env_specs(env)
    td = env.rollout(5)  # rand_action samples from the masked spec: nothing is refused
    assert set(td["agents", "action"][:, :, 0].unique().tolist()) <= {0, 2}
    td = env.reset()
    before = env.core.get_state()
    td["agents", "action"] = torch.full((2, 2), FORWARD)
    with pytest.raises(ValueError, match=r"world 0 agent 'held_0' took 1 \('forward'\)"):
        env.step(td)
    assert same_state(env.core.get_state(), before)
    env.close()
