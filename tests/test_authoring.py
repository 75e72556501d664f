"""Writing a task: the tutorial in docs/authoring.md runs as written, and a task defined here,
outside the package, works through every front end once registered."""
import dataclasses
import math
import pathlib
import pickle
import re

import gymnasium
import numpy as np
import pytest
import torch
from pettingzoo.test import api_test, parallel_api_test
from torchrl.envs.utils import check_env_specs

from marl_render.envs import (
    ArenaScenario,
    ArenaState,
    Prop,
    list_envs,
    make_aec_env,
    make_env,
    make_jax_env,
    make_parallel_env,
    make_sb3_env,
    make_torchrl_env,
    make_vec_env,
    numbered,
    register_env,
    registry,
)

DOC = pathlib.Path(__file__).resolve().parents[1] / "docs" / "authoring.md"


SECOND_TASK = "## 6. A second task"


def python_blocks(text: str) -> list:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def tutorial_blocks() -> list:
    """The blocks of sections 1-5 (rendezvous)."""
    text = DOC.read_text()
    assert SECOND_TASK in text
    return python_blocks(text.split(SECOND_TASK)[0])


BOTS_SECTION = "## 7. Bots and held-out scenarios"


def second_task_blocks() -> list:
    """The blocks of section 6 (hide and seek): its definitions, then its use."""
    return python_blocks(DOC.read_text().split(SECOND_TASK)[1].split(BOTS_SECTION)[0])


def bots_blocks() -> list:
    """The block of section 7: a user's bots and held-out scenario for the tutorial's task."""
    return python_blocks(DOC.read_text().split(BOTS_SECTION)[1])


@pytest.fixture(scope="module")
def tutorial():
    """The tutorial's definitions (every block but the last, which uses them), run as written."""
    namespace = {"__name__": "authoring_tutorial"}
    blocks = tutorial_blocks()
    assert len(blocks) >= 5
    exec(compile("".join(blocks[:-1]), str(DOC), "exec"), namespace)  # noqa: S102
    yield namespace
    registry._REGISTRY.pop("rendezvous", None)


@pytest.fixture(scope="module")
def hide_and_seek(tutorial):
    """Section 6's definitions, run as written after the tutorial's (whose imports they use)."""
    namespace = dict(tutorial)
    blocks = second_task_blocks()
    assert len(blocks) == 2
    exec(compile(blocks[0], str(DOC), "exec"), namespace)  # noqa: S102
    yield namespace
    registry._REGISTRY.pop("hide_and_seek", None)


def test_tutorial_usage_block_runs_as_written(tutorial):
    exec(compile(tutorial_blocks()[-1], str(DOC), "exec"), dict(tutorial))  # noqa: S102


def test_tutorial_task_passes_pettingzoo_torchrl_and_gymnasium_checks(tutorial):
    assert "rendezvous" in list_envs()
    parallel_api_test(make_parallel_env("rendezvous", resolution=16), num_cycles=30)
    api_test(make_aec_env("rendezvous", resolution=16), num_cycles=30)
    env = make_torchrl_env("rendezvous", num_worlds=3, resolution=16)
    check_env_specs(env)
    env.close()
    vec = make_vec_env("rendezvous", num_worlds=2, resolution=16)
    obs, _ = vec.reset(seed=0)
    assert vec.observation_space.contains(obs) and obs.shape == (6, 16, 16, 3)
    obs, reward, terminated, truncated, info = vec.step(vec.action_space.sample())
    assert obs.shape == (6, 16, 16, 3) and reward.shape == (6,) and reward.dtype == np.float32
    vec.close()


def test_second_task_usage_block_runs_as_written(hide_and_seek, capsys):
    exec(compile(second_task_blocks()[1], str(DOC), "exec"), dict(hide_and_seek))  # noqa: S102
    printed = capsys.readouterr().out
    assert "agent 'seeker_0' took 1 ('forward'), allowed: [0 ('noop')]" in printed


def test_second_task_freezes_the_seeker_and_rewards_sight(hide_and_seek):
    env = make_env("hide_and_seek", num_worlds=2, resolution=16, seed=0)
    obs = env.reset()
    assert obs["action_mask"][:, 0].tolist() == [[True, False, False, False, False]] * 2  # advice only
    # The hider (at rest) sits right in front of the frozen seeker: forward for both. The seeker does not
    # move although its mask is not enforced here and the hider is driven into it.
    state = env.get_state()
    state["pos"][:, :2] = torch.tensor([[0.0, -1.2], [0.0, -0.85]])
    state["yaw"][:] = torch.tensor([0.0, math.pi])
    env.set_state(state)
    for _ in range(3):
        env.step(torch.ones(2, 2, dtype=torch.long))
    assert torch.equal(env.sim.pos[:, 0], torch.tensor([[0.0, -1.2]] * 2)) and torch.equal(env.sim.yaw[:, 0],
                                                                                           torch.zeros(2))
    assert bool((env.sim.vel[:, 0] == 0).all())
    assert bool((env.sim.pos[:, 1, 1] < -0.85).all()) and bool((env.sim.pos[:, 1, 1] > -1.2 + 0.3 - 0.01).all())
    # After the hiding phase it turns and moves; it sees the hider in world 0 (in the open), not in
    # world 1 (behind the wall, turned across the line between them).
    state = env.get_state()
    state["clock"][:] = hide_and_seek["HIDE_STEPS"]
    state["pos"][:, :2] = torch.tensor([[0.0, -1.2], [0.0, 1.2]])
    state["vel"].zero_()
    state["yaw"][:] = 0.0
    state["wall"][:] = torch.tensor([[[1.0, 0.0]], [[0.0, 0.0]]])
    state["wall_angle"][:] = 0.0
    env.set_state(state)
    obs, reward, terminated, truncated, info = env.step(torch.tensor([[2, 0], [2, 0]]))
    assert env.sim.yaw[:, 0].tolist() == pytest.approx([0.3, 0.3])
    assert info["seen"].tolist() == [1, 0] and reward.tolist() == [[1.0, -1.0], [0.0, 0.0]]
    assert terminated.tolist() == [[True, True], [False, False]]
    env.close()


def test_tutorial_rules_reward_gathering(tutorial):
    env = make_env("rendezvous", num_worlds=2, resolution=8, state_obs=True, seed=0)
    env.reset()
    state = env.get_state()
    state["pos"][0] = state["pad"][0, 0] + torch.tensor([[0.05, 0.0], [-0.05, 0.0], [0.0, 0.1]])
    state["vel"].zero_()
    env.set_state(state)
    obs, reward, terminated, truncated, info = env.step(torch.zeros(2, 3, dtype=torch.long))
    assert reward[0].tolist() == [1.0, 1.0, 1.0] and info["on_pad"][0] == 3 and info["together"][0] == 1
    assert obs["state"].shape == (2, 3, 6 + 2 + 4)
    env.close()


# ---------------------------------------------------------------------- a task defined outside the package
@dataclasses.dataclass(frozen=True)
class BeaconState(ArenaState):
    beacon: torch.Tensor  # [W, 1, 2]


class Beacon(ArenaScenario):
    """Each agent earns 1 per step on the beacon; defined in this test file, not in the package."""

    name = "beacon"
    State = BeaconState
    default_num_agents = 2
    agent_range = (1, 4)
    default_max_steps = 20
    physics_terms = frozenset({"walls", "drag"})
    info_keys = {"on_beacon": torch.int64}

    def setup(self):
        self.setup_arena({"scouts": numbered("scout", self.num_agents)}, state_dim=8, radius=0.15, max_speed=2.0)

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self.at_rest(torch.zeros(W, N, 2), torch.zeros(W, N), beacon=torch.zeros(W, 1, 2))

    def props(self):
        return [Prop("beacon", "box", count=1, position="beacon", height=0.2, scale=(0.3, 0.3, 0.4),
                     color=(1.0, 0.2, 0.8), moves=False)]

    def spawn(self, generator):
        W, N = self.num_worlds, self.num_agents
        pos = (torch.rand(W, N, 2, generator=generator) * 2 - 1)
        return self.at_rest(pos, torch.zeros(W, N), beacon=torch.rand(W, 1, 2, generator=generator) - 0.5)

    def rules(self, before, moved, actions, alive, generator):
        on = (moved.pos - moved.beacon).norm(dim=-1) < 0.3
        return moved, on.float(), torch.zeros_like(alive), {"on_beacon": on.sum(-1)}

    def observation(self, state, alive):
        return torch.cat((self.own_obs(state), self.relative(state, state.beacon)[:, :, 0]), -1)


@pytest.fixture
def beacon():
    register_env("beacon", Beacon, overwrite=True)
    yield
    registry._REGISTRY.pop("beacon", None)


def test_a_task_from_outside_the_package_works_through_every_front_end(beacon):
    core = make_env("beacon", num_worlds=3, resolution=16, seed=1, state_obs=True)
    obs = core.reset()
    assert obs["pixels"].shape == (3, 2, 16, 16, 3) and obs["state"].shape == (3, 2, 8)
    assert core.spec.observations["state"].shape == (8,) and core.spec.info == {"on_beacon": torch.int64}
    core.close()

    pz = make_parallel_env("beacon", resolution=16)
    parallel_api_test(pz, num_cycles=25)
    clone = pickle.loads(pickle.dumps(pz))  # by class (this module), not by the registered name
    assert clone.possible_agents == ["scout_0", "scout_1"]
    clone.close()

    trl = make_torchrl_env("beacon", num_worlds=2, resolution=16)
    check_env_specs(trl)
    assert trl.group_map == {"scouts": ["scout_0", "scout_1"]}
    trl.close()

    vec = make_vec_env("beacon", num_worlds=2, resolution=16)
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (4, 16, 16, 3)
    vec.close()

    sb3 = make_sb3_env("beacon", num_worlds=2, resolution=16)
    assert sb3.reset().shape == (4, 16, 16, 3)
    sb3.close()

    made = gymnasium.make_vec("marl_render/beacon-v0", num_envs=4, resolution=16)  # register_env made the id
    assert made.num_envs == 4 and made.reset(seed=0)[0].shape == (4, 16, 16, 3)
    made.close()

    aec = make_aec_env("beacon", resolution=16)
    api_test(aec, num_cycles=20)
    aec.close()

    jax_env = make_jax_env("beacon", num_worlds=2, resolution=16)
    obs = jax_env.reset(seed=0)
    assert tuple(obs["pixels"].shape) == (2, 2, 16, 16, 3)
    jax_env.close()


def test_register_env_checks_its_arguments():
    with pytest.raises(TypeError, match="name must be a non-empty str"):
        register_env("", Beacon)
    with pytest.raises(TypeError, match="scenario must be a Scenario subclass"):
        register_env("beacon2", "no_colon_here")
    with pytest.raises(ValueError, match="already registered"):
        register_env("spread", Beacon)


# ---------------------------------------------------------------------- hooks that break the contract
class WrongRewardShape(Beacon):
    def rules(self, before, moved, actions, alive, generator):
        state, reward, terminated, info = super().rules(before, moved, actions, alive, generator)
        return state, reward.sum(-1), terminated, info  # [W] instead of [W, A]


class WrongInfoDtype(Beacon):
    def rules(self, before, moved, actions, alive, generator):
        state, reward, terminated, info = super().rules(before, moved, actions, alive, generator)
        return state, reward, terminated, {"on_beacon": info["on_beacon"].float()}


class WrongObservation(Beacon):
    def observation(self, state, alive):
        return super().observation(state, alive)[..., :5]


class WrongSpawn(Beacon):
    def spawn(self, generator):
        return dataclasses.replace(super().spawn(generator), beacon=torch.zeros(self.num_worlds, 2, 2))


class WrongFrozen(Beacon):
    def frozen(self, state):
        return torch.zeros(self.num_worlds, dtype=torch.bool)  # [W] instead of [W, A]


@pytest.mark.parametrize("task, words", [
    (WrongFrozen, r"WrongFrozen\.frozen must return None or a bool tensor of shape \[2, 2\] on cpu, got tensor of "
                  r"shape \(2,\)"),
    (WrongRewardShape, r"WrongRewardShape\.rules's reward must have shape \[2, 2\].*got shape \[2\]"),
    (WrongInfoDtype, r"WrongInfoDtype\.rules's info\['on_beacon'\] must have shape \[2\], torch\.int64"),
    (WrongObservation, r"WrongObservation\.observation must have shape \[2, 2, 8\].*got shape \[2, 2, 5\]"),
    (WrongSpawn, r"WrongSpawn\.spawn's state\.beacon must have shape \[2, 1, 2\].*got shape \[2, 2, 2\]"),
])
def test_a_hook_that_breaks_its_contract_is_named(task, words):
    env = make_env(task, num_worlds=2, resolution=8, state_obs=True)
    try:
        with pytest.raises((TypeError, ValueError), match=words):
            env.reset()
            env.step(torch.zeros(2, 2, dtype=torch.long))
    finally:
        env.close()


def test_bots_and_held_out_scenarios_of_the_tutorial_task_run_as_written(tutorial, capsys, registries):
    from marl_render import bots, heldout

    blocks = bots_blocks()
    assert len(blocks) == 1
    exec(compile(blocks[0], str(DOC), "exec"), dict(tutorial))  # noqa: S102
    assert heldout.list_heldout("rendezvous") == ["rendezvous/meet_the_stubborn"]
    assert bots.POPULATIONS["rendezvous"] == {"train": ("heuristic",), "test": ("stayer", "lazy0.5")}
    printed = capsys.readouterr().out
    assert "stayer" in printed or "lazy0.5" in printed  # bots_sampled names the bots that played
