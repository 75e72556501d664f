"""The TorchRL front end (marl_render/wrappers/torchrl.py): specs of every registered env,
group maps, partial resets, agents leaving, seeding, bad input, ParallelEnv (spawned
workers, one GL context each) and a data collector."""
from __future__ import annotations

import functools

import pytest
import torch
from torchrl.envs import (
    CatFrames,
    Compose,
    GrayScale,
    ParallelEnv,
    RewardSum,
    StepCounter,
    ToTensorImage,
    TransformedEnv,
)
from torchrl.envs.transforms.functional import rgb_to_grayscale
from torchrl.envs.utils import MarlGroupMapType, check_env_specs, step_mdp

from departing_env import Departing
from marl_render.envs import list_envs, make_env
from marl_render.wrappers.torchrl import MarlRenderTorchRLEnv, make_torchrl_env

try:  # torchrl >= 0.11 renamed SyncDataCollector to Collector
    from torchrl.collectors import Collector
except ImportError:  # pragma: no cover - older torchrl
    from torchrl.collectors import SyncDataCollector as Collector

W = 2
RES = 32
ENVS = list_envs()


pytestmark = pytest.mark.usefixtures("single_torch_thread")


def make(name, **kw):
    kw.setdefault("num_worlds", W)
    kw.setdefault("resolution", RES)
    kw.setdefault("episode_end", False)  # fixed ends: these contracts count steps (random: test_episodes.py)
    return make_torchrl_env(name, **kw)


def departing(max_steps=5, group_map="team"):
    return MarlRenderTorchRLEnv(make_env(Departing, num_worlds=W, resolution=RES, max_steps=max_steps, seed=0),
                                group_map=group_map)


# ---------------------------------------------------------------------- specs
@pytest.mark.parametrize("name", ENVS)
@pytest.mark.parametrize("variant", [{}, {"continuous": True, "depth": True, "state_obs": True}])
def test_check_env_specs_and_random_rollout(name, variant):
    env = make(name, max_steps=4, **variant)
    env.set_seed(0)
    check_env_specs(env)
    td = env.rollout(6, break_when_any_done=False)  # crosses an episode end: auto partial reset
    core = env.core
    H, Wpx = core.resolution
    assert td.batch_size == (W, 6)
    for group, names in env.group_map.items():
        N = len(names)
        assert td["next", group, "pixels"].shape == (W, 6, N, H, Wpx, 3)
        assert td["next", group, "pixels"].dtype == torch.uint8
        assert td["next", group, "reward"].shape == (W, 6, N, 1)
        for key in ("done", "terminated", "truncated"):
            assert td["next", group, key].shape == (W, 6, N, 1)
        if core.continuous:
            assert td[group, "action"].shape == (W, 6, N, core.action_dim)
            assert td["next", group, "depth"].shape == (W, 6, N, H, Wpx)
            assert td["next", group, "state"].shape == (W, 6, N, core.state_dim)
        else:
            assert td[group, "action"].dtype == torch.int64 and td[group, "action"].shape == (W, 6, N)
            assert td["next", group, "action_mask"].shape == (W, 6, N, core.num_actions)
    assert td["next", "done"].shape == (W, 6, 1)
    assert td["next", "truncated"][:, 3].all() and not td["next", "done"][:, [0, 1, 2, 4, 5]].any()
    assert td["next", "terminated"].sum() == 0
    env.close()


def test_spec_types():
    from torchrl.data import Bounded, Categorical, Unbounded

    env = make("spread", state_obs=True, depth=True)
    obs = env.observation_spec["agents"]
    assert isinstance(obs["pixels"], Bounded) and obs["pixels"].dtype == torch.uint8
    assert isinstance(obs["depth"], Bounded) and isinstance(obs["state"], Unbounded)
    assert isinstance(obs["action_mask"], Categorical) and obs["action_mask"].dtype == torch.bool
    assert isinstance(env.full_action_spec["agents", "action"], Categorical)
    assert env.full_action_spec["agents", "action"].space.n == 5
    assert env.full_done_spec["done"].shape == (W, 1)
    env.close()
    env = make("cartpole", continuous=True)
    action = env.full_action_spec["agents", "action"]
    assert isinstance(action, Bounded) and action.shape == (W, 1, 1)
    assert action.space.low.min() == -1 and action.space.high.max() == 1
    env.close()


# ---------------------------------------------------------------------- group maps
def test_group_maps_slice_the_same_data():
    maps = {"team": None, "one_group": None, "per_agent": None,
            MarlGroupMapType.ALL_IN_ONE_GROUP: None, MarlGroupMapType.ONE_GROUP_PER_AGENT: None,
            "explicit": {"odd": ["agent_1"], "even": ["agent_2", "agent_0"]}}
    pixels = {}
    for key in maps:
        group_map = maps[key] or key
        env = make("spread", group_map=group_map, seed=5)
        td = env.reset()
        pixels[key] = {name: td[group, "pixels"][:, i] for group, names in env.group_map.items()
                       for i, name in enumerate(names)}
        if key in ("one_group", MarlGroupMapType.ALL_IN_ONE_GROUP, "team"):
            assert env.group_map == {"agents": ["agent_0", "agent_1", "agent_2"]}
        if key in ("per_agent", MarlGroupMapType.ONE_GROUP_PER_AGENT):
            assert env.group_map == {f"agent_{i}": [f"agent_{i}"] for i in range(3)}
            assert td["agent_1", "pixels"].shape == (W, 1, RES, RES, 3)
        if key == "explicit":
            check_env_specs(env)
            td = env.rand_step(td)
            assert td["next", "even", "reward"].shape == (W, 2, 1)
        env.close()
    reference = pixels["one_group"]
    for key, by_agent in pixels.items():
        for name in reference:
            assert torch.equal(by_agent[name], reference[name]), (key, name)


def test_team_group_map_of_a_two_team_env():
    env = departing(group_map="team")
    assert env.group_map == {"predators": ["predator_0"], "prey": ["prey_0", "prey_1"]}
    check_env_specs(env)
    td = env.rollout(3)
    assert td["next", "prey", "pixels"].shape == (W, 3, 2, RES, RES, 3)
    assert td["next", "predators", "reward"].shape == (W, 3, 1, 1)
    env.close()
    one = departing(group_map="one_group")
    assert list(one.group_map) == ["agents"]
    one.close()


def test_bad_group_maps():
    for group_map, error, message in [
        ("teams", ValueError, "group_map must be one of"),
        ({"a": ["agent_0", "agent_1"]}, ValueError, r"missing: \['agent_2'\]"),
        ({"a": ["agent_0", "agent_1", "agent_2", "agent_9"]}, ValueError, r"unknown agent\(s\) \['agent_9'\]"),
        ({"done": ["agent_0", "agent_1", "agent_2"]}, ValueError, "clash with TorchRL's root keys"),
        ({"info": ["agent_0", "agent_1", "agent_2"]}, ValueError, r"group names \['info'\] clash"),
        ({"a": ["agent_0", "agent_1"], "b": ["agent_1", "agent_2"]}, ValueError, "agent_1"),
        ({"a": "agent_0"}, TypeError, "must be a list of agent names"),
    ]:
        with pytest.raises(error, match=message):
            make("spread", group_map=group_map)
    with pytest.raises(TypeError, match="autoreset"):
        make("spread", autoreset=True)


# ---------------------------------------------------------------------- resets
def _state(env):
    return env.core.get_state()


def test_partial_reset_leaves_other_worlds_untouched():
    env = make("spread", num_worlds=3, state_obs=True, seed=1)
    td = env.reset()
    for _ in range(3):
        td = step_mdp(env.rand_step(td))
    before, pixels = _state(env), td["agents", "pixels"].clone()
    td.set("_reset", torch.tensor([[False], [True], [False]]))
    td = env.reset(td)
    after = _state(env)
    keep = [0, 2]
    for key in ("pos", "vel", "yaw", "landmarks", "step_count", "alive"):
        assert torch.equal(after[key][keep], before[key][keep]), key
        assert not torch.equal(after[key][1], before[key][1]) or key == "alive", key
    assert after["step_count"].tolist() == [3, 0, 3]
    assert torch.equal(td["agents", "pixels"][keep], pixels[keep])  # same pixels, rendered again
    assert not torch.equal(td["agents", "pixels"][1], pixels[1])
    assert "_reset" not in td.keys()

    # Worlds are the unit of reset: a per-group mask is refused, not silently ignored.
    td = step_mdp(env.rand_step(td))
    before = _state(env)
    td.set(("agents", "_reset"), torch.tensor([[[False]] * 3, [[False]] * 3, [[False], [True], [False]]]))
    with pytest.raises(ValueError, match=r"\(group, '_reset'\) entries are not reset keys.*\['agents'\]"):
        env.reset(td)
    after = _state(env)
    assert all(torch.equal(after[k], before[k]) for k in after)
    env.close()


def test_one_reset_key_and_per_agent_flags():
    env = departing()
    assert env.reset_keys == ["_reset"]
    assert env.done_keys == ["done", "terminated", "truncated"]
    for group in env.group_map:
        for key in ("done", "terminated", "truncated"):
            assert env.observation_spec[group, key].dtype == torch.bool
    env.close()


def test_rollout_resets_only_the_done_world():
    env = make("spread", max_steps=4, seed=2)
    td = env.reset()
    td = step_mdp(env.rand_step(td))
    td.set("_reset", torch.tensor([[True], [False]]))  # world 0 restarts one step later than world 1
    td = env.reset(td)
    counts = []
    for _ in range(6):
        out, td = env.step_and_maybe_reset(td)
        counts.append(env.core.step_count.tolist())
        done = out["next", "done"].squeeze(-1)
        assert done.tolist() == [c == 0 for c in counts[-1]]
    assert counts == [[1, 2], [2, 3], [3, 0], [0, 1], [1, 2], [2, 3]]
    env.close()


def test_departed_agents():
    env = departing(max_steps=5)
    env.set_seed(0)
    td = env.rollout(5, break_when_any_done=True)  # only root done stops a rollout
    assert td.batch_size == (W, 5)
    prey_term = td["next", "prey", "terminated"].squeeze(-1)  # [W, T, 2]
    assert prey_term[0].tolist() == [[False, False], [True, False], [True, True], [True, True], [True, True]]
    assert not prey_term[1].any()
    reward = td["next", "prey", "reward"].squeeze(-1)
    assert (reward[0, 2:, 0] == 0).all() and (reward[0, 3:, 1] == 0).all() and (reward[1] != 0).all()
    assert not td["next", "done"][:, :4].any()
    # step 5: the predator (and world 1's prey) reach max_steps
    assert td["next", "done"][:, 4].all() and td["next", "truncated"][:, 4].all()
    assert not td["next", "terminated"].any()
    assert td["next", "predators", "truncated"][:, 4].all()
    assert td["next", "prey", "truncated"][0, 4].sum() == 0 and td["next", "prey", "truncated"][1, 4].all()
    env.close()


def test_world_terminated_when_every_agent_left():
    class AllLeave(Departing):
        def rules(self, before, moved, actions, alive, generator):
            state, reward, terminated, info = super().rules(before, moved, actions, alive, generator)
            terminated[0] |= bool(before.t[0] == 3)
            return state, reward, terminated, info

    env = MarlRenderTorchRLEnv(make_env(AllLeave, num_worlds=W, resolution=RES, max_steps=10, seed=0))
    td = env.rollout(10)
    assert td.batch_size == (W, 4)  # world 0 ends at step 4 and stops the rollout
    assert td["next", "terminated"][:, 3].squeeze(-1).tolist() == [True, False]
    assert td["next", "done"][:, 3].squeeze(-1).tolist() == [True, False]
    td = env.reset(step_mdp(td[:, -1]).set("_reset", td["next", "done"][:, -1]))
    assert env.core.alive.all() and env.core.step_count.tolist() == [0, 4]
    env.close()


def test_action_mask_reaches_the_action_spec():
    class Masked(Departing):
        def action_mask(self, state, alive):
            mask = super().action_mask(state, alive).clone()
            mask[..., 0] = False  # never noop
            mask[0, 1] = torch.tensor([False, False, False, True, False])  # world 0's prey_0: only action 3
            return mask

    env = MarlRenderTorchRLEnv(make_env(Masked, num_worlds=W, resolution=RES, max_steps=10, seed=0),
                               group_map="one_group")
    check_env_specs(env)
    td = env.rollout(20, break_when_any_done=False)
    assert td["agents", "action_mask"][0, :, 1].tolist() == [[False, False, False, True, False]] * 20
    actions = td["agents", "action"]
    assert (actions != 0).all() and (actions[0, :, 1] == 3).all()  # rand_action honours the mask
    env.close()


# ---------------------------------------------------------------------- transforms as users write them
def _drive(env, steps=6):
    """Reset, step once, reset world 0 alone (so the worlds' episodes are out of phase), then
    step_and_maybe_reset with actions from a fixed generator; returns the root tensordicts."""
    generator = torch.Generator().manual_seed(0)

    def act(td):
        return td.set(("agents", "action"), torch.randint(5, (W, 3), generator=generator))

    env.set_seed(4)
    td = env.reset()
    seen = [td.clone()]
    td = step_mdp(env.step(act(td)))
    td = env.reset(td.set("_reset", torch.tensor([[True], [False]])))
    seen.append(td.clone())
    for _ in range(steps):
        _, td = env.step_and_maybe_reset(act(td))
        seen.append(td.clone())
    return seen


def test_frame_stacking_chain_with_default_arguments():
    key = ("agents", "pixels")
    raw = make("spread", max_steps=3)
    stacked = TransformedEnv(make("spread", max_steps=3), Compose(
        ToTensorImage(in_keys=[key]), GrayScale(in_keys=[key]), CatFrames(N=3, dim=-3, in_keys=[key]),
        RewardSum(), StepCounter()))
    check_env_specs(stacked)
    assert stacked.observation_spec[key].shape == (W, 3, 3, RES, RES)

    frames = [rgb_to_grayscale(td[key].permute(0, 1, 4, 2, 3) / 255) for td in _drive(raw)]  # [W, 3, 1, H, Wpx]
    seen = _drive(stacked)
    steps = [td["step_count"][:, 0].tolist() for td in seen]
    outputs = [td[key] for td in seen]
    # Expected stack per world: restarted (the first frame repeated) where its episode starts.
    stack = torch.cat([frames[0]] * 3, dim=2)
    for t, (frame, out) in enumerate(zip(frames, outputs, strict=True)):
        if t:
            restart = torch.tensor([count == 0 for count in steps[t]])
            rolled = torch.cat((stack[:, :, 1:], frame), dim=2)
            stack = torch.where(restart[:, None, None, None, None], torch.cat([frame] * 3, dim=2), rolled)
        assert out.dtype == torch.float32 and out.shape == (W, 3, 3, RES, RES)
        torch.testing.assert_close(out, stack, rtol=0, atol=1e-6, msg=f"step {t}")
    assert steps[1] == [0, 1] and steps[4] == [0, 1]  # world 0 restarted at 1 and 4, world 1 at 3
    assert steps[3] == [2, 0]
    raw.close()
    stacked.close()


def test_resize_needs_torchvision():
    try:
        import torchvision  # noqa: F401
    except ImportError:
        pytest.skip("torchvision is not installed: no torchvision wheel for the pinned CPU torch is on the "
                    "package index (PyPI's are CUDA builds); torchrl's Resize cannot run without it")
    except RuntimeError as exc:  # PyPI's CUDA build next to the CPU torch fails while registering its ops
        pytest.skip(f"torchvision is installed but does not import with this torch ({exc})")
    from torchrl.envs import Resize

    key = ("agents", "pixels")
    env = TransformedEnv(make("spread"), Compose(ToTensorImage(in_keys=[key]), Resize(16, in_keys=[key])))
    check_env_specs(env)
    td = env.reset()
    assert td[key].shape == (W, 3, 3, 16, 16) and td[key].dtype == torch.float32
    env.close()


# ---------------------------------------------------------------------- episode statistics
@pytest.mark.parametrize("name", ENVS)
def test_episode_statistics_match_the_core(name):
    env = make(name, max_steps=3, seed=6)
    core = make_torchrl_env(name, num_worlds=W, resolution=RES, max_steps=3, seed=6,
                            episode_end=False).core  # as make()
    declared = env.core.info_keys
    if declared:
        assert set(env.observation_spec["info"].keys()) == set(declared)
    else:
        assert "info" not in env.observation_spec.keys()
    generator = torch.Generator().manual_seed(1)
    td = env.reset()
    core.reset()
    for name_, dtype in declared.items():
        assert td["info", name_].dtype == dtype and not td["info", name_].any()  # no step taken yet
    for _ in range(3):
        actions = core.random_actions(generator)
        for group, names in env.group_map.items():
            index = [env.agent_names.index(n) for n in names]
            td.set((group, "action"), actions[:, index])
        td = env.step(td)
        *_, info = core.step(actions)
        assert set(info) == {"step_count", "done_worlds", *declared}
        for name_, dtype in declared.items():
            assert info[name_].dtype == dtype and info[name_].shape == (W,)
            assert torch.equal(td["next", "info", name_], info[name_]), name_
        td = step_mdp(td)
    core.close()
    env.close()


def test_episode_statistics_have_meaning():
    # spread: coverage is the distance term of the reward; forage: team_score sums the rewards.
    env = make("spread", seed=2)
    td = env.rollout(3, break_when_any_done=False)
    info = td["next", "info"]
    reward = td["next", "agents", "reward"][:, :, 0, 0]
    torch.testing.assert_close(reward, -info["coverage"] - info["collisions"].float())
    env.close()
    env = make("forage", seed=2)
    td = env.rollout(20, break_when_any_done=False)
    team = td["next", "agents", "reward"][..., 0].sum(-1).cumsum(1)  # [W, T]
    torch.testing.assert_close(td["next", "info", "team_score"], team)
    env.close()


# ---------------------------------------------------------------------- seeding and bad input
def test_set_seed_is_reproducible():
    def run(seed):
        env = make("spread", max_steps=3)
        env.set_seed(seed)
        torch.manual_seed(0)  # rand_action uses torch's global RNG
        td = env.rollout(5, break_when_any_done=False)
        env.close()
        return td

    a, b, c = run(3), run(3), run(4)
    assert torch.equal(a["next", "agents", "pixels"], b["next", "agents", "pixels"])
    assert torch.equal(a["next", "agents", "reward"], b["next", "agents", "reward"])
    assert not torch.equal(a["agents", "pixels"][:, 0], c["agents", "pixels"][:, 0])
    env = make("spread")
    with pytest.raises(ValueError, match="seed"):
        env.set_seed(-1)
    env.close()


def test_bad_actions_raise_and_change_nothing():
    env = make("spread", group_map={"a": ["agent_0"], "b": ["agent_1", "agent_2"]})
    td = env.reset()
    before = _state(env)
    bad = [
        (torch.full((W, 1), 7), ValueError, r"values in \[0, 5\)"),
        (torch.zeros(W, 1, dtype=torch.float32), ValueError, r"\('a', 'action'\) must be an integer tensor"),
        (torch.zeros(W, 1, 3, dtype=torch.long), ValueError, r"\('a', 'action'\).*shape \[2, 1\]"),
    ]
    for action, error, message in bad:
        td_bad = env.rand_action(td.clone())
        td_bad.set(("a", "action"), action)
        with pytest.raises(error, match=message):
            env.step(td_bad)
        s = _state(env)
        assert all(torch.equal(s[k], before[k]) for k in s)
    env.close()
    env = make("cartpole", continuous=True)
    td = env.reset()
    td.set(("agents", "action"), torch.full((W, 1, 1), float("nan")))
    with pytest.raises(ValueError, match="non-finite"):
        env.step(td)
    env.close()


def test_render_overview_and_close():
    env = make("spread")
    env.reset()
    image = env.render_overview(resolution=(24, 40))
    assert image.shape == (W, 24, 40, 3) and image.dtype == torch.uint8
    env.close()
    assert env.is_closed and env.core.closed
    with pytest.raises(RuntimeError, match="closed"):
        env.reset()


# ---------------------------------------------------------------------- ParallelEnv and collectors
def test_parallel_env_spawned_workers():
    # functools.partial pickles as is; a lambda works too but torchrl then builds one env in
    # this process first to read its specs.
    create = functools.partial(make_torchrl_env, "spread", num_worlds=W, resolution=RES, max_steps=3)
    env = ParallelEnv(2, create, mp_start_method="spawn")
    try:
        env.set_seed(0)
        td = env.rollout(4, break_when_any_done=False)
        assert td.batch_size == (2, W, 4)
        assert td["next", "agents", "pixels"].shape == (2, W, 4, 3, RES, RES, 3)
        assert td["next", "done"][..., 2, 0].all() and not td["next", "done"][..., [0, 1, 3], 0].any()
        # differently seeded workers render different worlds
        assert not torch.equal(td["agents", "pixels"][0, :, 0], td["agents", "pixels"][1, :, 0])
    finally:
        env.close()


def test_collector_with_random_policy():
    env = make("spread", max_steps=4)
    collector = Collector(env, policy=None, frames_per_batch=W * 6, total_frames=W * 12)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch.batch_size == (W, 6)
        assert batch["next", "agents", "pixels"].shape == (W, 6, 3, RES, RES, 3)
        assert batch["next", "agents", "reward"].shape == (W, 6, 3, 1)
    done = torch.cat([b["next", "done"] for b in batches], 1).squeeze(-1)
    assert done.sum() == W * 3  # episodes of 4 steps in 12 steps per world
    env.close()


@pytest.mark.parametrize("reset, error, message", [
    (torch.ones(W, 1), TypeError, r"'_reset' must be a bool tensor of shape \[2, 1\].*float32"),
    (torch.ones(W, 1, dtype=torch.int64), TypeError, r"'_reset' must be a bool tensor of shape \[2, 1\].*int64"),
    (torch.ones(W, dtype=torch.bool), ValueError, r"'_reset' must be a bool tensor of shape \[2, 1\].*\(2,\)"),
    (torch.ones(W, 3, dtype=torch.bool), ValueError, r"'_reset' must be a bool tensor of shape \[2, 1\].*\(2, 3\)"),
])
def test_bad_reset_mask_raises_and_changes_nothing(reset, error, message):
    env = make("spread", seed=3)
    td = env.reset()
    td = step_mdp(env.rand_step(td))
    before = _state(env)
    env.set_seed(9)  # pending until the next reset that succeeds
    with pytest.raises(error, match=message):
        env.reset(td.clone().set("_reset", reset))
    after = _state(env)
    assert all(torch.equal(after[k], before[k]) for k in after)
    fresh = make("spread")
    fresh.set_seed(9)
    assert torch.equal(env.reset()["agents", "pixels"], fresh.reset()["agents", "pixels"])
    fresh.close()
    env.close()
