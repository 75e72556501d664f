"""A focal-only env's bots (envs/focal.py, marl_render/bots.py): they act among the allowed actions,
re-seed with the env, are sampled per level, leave the env as it was when their reset raises, and
their bad output is named as theirs; the keywords that build such an env refuse what they cannot mean."""
from __future__ import annotations

import pytest
import torch

from marl_render.bots import Perturbed
from marl_render.envs import Population, make_env
from marl_render.policies import Policy, RandomPolicy, heuristic_policy

TINY = {"resolution": 8, "state_obs": True}


def same_state(a: dict, b: dict) -> bool:
    """Two focal states (get_state()) equal in every entry, the bots' generators included."""
    def equal(x, y):
        if isinstance(x, list):
            return len(x) == len(y) and all(equal(u, v) for u, v in zip(x, y, strict=True))
        return x is None and y is None or isinstance(x, torch.Tensor) and torch.equal(x, y)
    return a.keys() == b.keys() and all(equal(a[key], b[key]) for key in a)


class Scripted(Policy):
    """A bot that plays the task's heuristic, or returns `output` (a fixed bad answer) when given one,
    and whose reset raises while `failing` is set."""

    needs = frozenset({"sim"})

    def __init__(self, name="scripted", output=None):
        self.name, self.output, self.failing = name, output, False

    def act(self, env, obs, worlds, slots):
        if self.output is not None:
            return self.output(len(worlds))
        return env.scenario.heuristic(env.sim, env.alive)[worlds, slots]

    def reset(self, env, worlds):
        if self.failing:
            raise RuntimeError("the bot's reset failed")


# ---------------------------------------------------------------------------- 1. the action mask
def test_noisy_bots_take_only_allowed_actions():
    """speaker_listener's speaker may only show a colour: a noisy speaker with enforce_action_mask=True
    plays 12 steps without a refusal, and every random action it takes is allowed."""
    with make_env("speaker_listener", heldout="speaker_listener/noisy_speaker", num_worlds=16,
                  enforce_action_mask=True, **TINY) as env:
        env.reset(seed=0)
        for _ in range(12):
            env.step(env.random_actions())
        core = env.core
        bot = Perturbed(heuristic_policy(), 1.0, "noisy", seed=1)  # always random
        worlds = torch.arange(16).repeat_interleave(2)
        slots = torch.arange(2).repeat(16)
        actions = bot.act(core, {}, worlds, slots)
        mask = core.scenario.action_mask(core.sim, core.alive)[worlds, slots]
        assert actions.dtype == torch.int64 and actions.shape == (32,)
        assert bool(mask.gather(1, actions[:, None]).all())
        assert len(set(actions[slots == 0].tolist())) > 1  # random among the speaker's colours


# ---------------------------------------------------------------------------- 2. reset(seed=) and the bots
@pytest.mark.parametrize("name", ["forage/one_among_noisy", "spread/two_with_nearest"])
def test_a_seeded_reset_reseeds_the_bots_own_generators(name):
    """Two episodes after reset(seed=5) with the same focal actions: the same background rewards, and
    the same bots' generators as an env built with another seed then reset with seed 5."""
    task = name.partition("/")[0]
    with make_env(task, heldout=name, num_worlds=4, seed=0, **TINY) as env, \
            make_env(task, heldout=name, num_worlds=4, seed=9, **TINY) as other:
        actions = torch.Generator().manual_seed(0)
        focal = [env.random_actions(actions) for _ in range(8)]
        episodes = []
        for _ in range(2):
            env.reset(seed=5)
            episodes.append(torch.stack([env.step(a)[4]["background_reward"] for a in focal]))
        assert torch.equal(*episodes)
        env.reset(seed=5)
        other.reset(seed=5)
        assert same_state(env.get_state(), other.get_state())


# ---------------------------------------------------------------------------- 3. bots per level
def test_a_level_samples_the_same_bots_in_any_world_slot_and_batch():
    levels = [3, 7, 11, 19, 23, 42]
    with make_env("forage", heldout="forage/one_among_noisy", num_worlds=1, levels="train", **TINY) as one, \
            make_env("forage", heldout="forage/one_among_noisy", num_worlds=3, levels="train", **TINY) as three:
        one.reset(seed=0)
        three.reset(seed=1)
        alone = []
        for level in levels:
            one.reset_to_level(torch.tensor([True]), torch.tensor([level]))
            alone.append(one.sampled_bots()[0])
        for slot in range(3):
            for level, bots in zip(levels, alone, strict=True):
                mask = torch.arange(3) == slot
                three.reset_to_level(mask, torch.full((3,), level))
                assert three.sampled_bots()[slot] == bots, (level, slot)
        assert len({tuple(bots) for bots in alone}) > 1  # the levels do not all draw the same bots


def test_reset_to_level_with_no_world_chosen_changes_nothing():
    with make_env("forage", heldout="forage/one_among_noisy", num_worlds=3, levels="train", **TINY) as env:
        env.reset(seed=0)
        before = env.get_state()
        env.reset_to_level(torch.zeros(3, dtype=torch.bool), torch.zeros(3, dtype=torch.int64))
        assert same_state(env.get_state(), before)


# ---------------------------------------------------------------------------- 4. a bot's reset that raises
@pytest.mark.parametrize("call", ["reset", "reset_worlds", "reset_to_level", "autoreset"])
def test_a_bot_reset_that_raises_leaves_the_env_as_it_was(call):
    """pos, yaw, obstacles, step_count, alive, rng, background_rng, the bots and their generators:
    all as before the failed call, and the env goes on as if it had never been made."""
    failing = Scripted()
    noisy = Perturbed(heuristic_policy(), 0.5, "noisy", seed=4)
    background = Population({"agents": [failing, noisy]}, focal=["agent_0"])
    kwargs = dict(num_worlds=4, seed=2, autoreset="same_step", max_steps=2, levels="train", **TINY)
    with make_env("forage", background=background, **kwargs) as env:
        env.reset(seed=2)
        env.step(env.heuristic_actions())  # the next step ends the episodes, and autoresets
        before = env.get_state()
        failing.failing = True
        with pytest.raises(RuntimeError, match="the bot's reset failed"):
            if call == "reset":
                env.reset(seed=7)
            elif call == "reset_worlds":
                env.reset_worlds(torch.tensor([True, False, True, False]), seed=7)
            elif call == "reset_to_level":
                env.reset_to_level(torch.tensor([True, False, True, False]), torch.full((4,), 99))
            else:
                env.step(env.heuristic_actions())
        assert same_state(env.get_state(), before)
        failing.failing = False
        # the same step as a twin that never failed
        twin_background = Population({"agents": [Scripted(), Perturbed(heuristic_policy(), 0.5, "noisy", seed=4)]},
                                     focal=["agent_0"])
        with make_env("forage", background=twin_background, **kwargs) as twin:
            twin.reset(seed=2)
            twin.step(twin.heuristic_actions())
            got, want = env.step(env.heuristic_actions()), twin.step(twin.heuristic_actions())
            assert torch.equal(got[0]["pixels"], want[0]["pixels"]) and torch.equal(got[1], want[1])
            assert same_state(env.get_state(), twin.get_state())


def test_a_bot_without_reset_is_refused_when_the_population_is_made():
    class ActOnly:
        name = "act_only"

        def act(self, env, obs, worlds, slots):
            return torch.zeros(len(worlds), dtype=torch.int64)

    with pytest.raises(TypeError, match=r"bots_by_role\['agents'\]\[1\] \(ActOnly 'act_only'\) must be a policy "
                                        r"with act and reset \(marl_render.policies.Policy\); it lacks \['reset'\]"):
        Population({"agents": [heuristic_policy(), ActOnly()]})


# ---------------------------------------------------------------------------- 5. appearance_ids is a copy
def test_appearance_ids_are_the_callers_copy():
    with make_env("spread", heldout="spread/two_with_nearest", num_worlds=2, appearance="train", **TINY) as env:
        env.reset(seed=0)
        state = env.get_state()
        ids = env.appearance_ids
        ids += 1
        core_ids = env.core.appearance_ids
        core_ids.zero_()
        assert same_state(env.get_state(), state)
        assert not torch.equal(env.appearance_ids, ids) and not torch.equal(env.appearance_ids, core_ids)


# ---------------------------------------------------------------------------- 9. heldout and difficulty
def test_heldout_refuses_a_difficulty_whose_team_size_it_would_override():
    with pytest.raises(ValueError, match=r"heldout 'capture_flag/red_vs_attackers' fixes \['num_agents'\] to \[16\]; "
                                         r"difficulty='hard' sets \[32\]"):
        make_env("capture_flag", heldout="capture_flag/red_vs_attackers", difficulty="hard", num_worlds=1)
    # a preset that leaves the team size alone, or sets the scenario's own, is fine
    with make_env("capture_flag", heldout="capture_flag/duel_red_vs_attackers", difficulty="easy", num_worlds=1,
                  resolution=8) as env:
        assert env.core.num_agents == 4
    with make_env("capture_flag", heldout="capture_flag/red_vs_attackers", difficulty="medium", num_worlds=1,
                  resolution=8) as env:
        assert env.core.num_agents == 16


# ---------------------------------------------------------------------------- a bot's bad output is the bot's
@pytest.mark.parametrize(("output", "error", "words"), [
    (lambda n: torch.zeros(n + 1, dtype=torch.int64), ValueError, r"must return actions of shape \[4\], got \[5\]"),
    (lambda n: torch.full((n,), 99), ValueError, r"must return actions in \[0, 5\), got values in \[99, 99\]"),
    (lambda n: torch.full((n,), float("nan")), TypeError, r"must return integer actions, got .*float32"),
    (lambda n: torch.full((n,), 2.7), TypeError, r"must return integer actions, got .*float32"),
    (lambda n: [1] * n, TypeError, r"must return a torch.Tensor of actions, got \[1, 1"),
])
def test_a_bots_bad_output_is_named_as_the_bots(output, error, words):
    bad = Scripted("clumsy", output)
    with make_env("forage", background=Population({"agents": [bad]}, focal="agent_0"), num_worlds=2, **TINY) as env:
        env.reset(seed=0)
        before = env.get_state()
        with pytest.raises(error, match=rf"^background bot 'clumsy' \(team 'agents'\) {words}"):
            env.step(env.heuristic_actions())
        assert same_state(env.get_state(), before)


def test_a_bots_forbidden_action_is_named_as_the_bots():
    pushy = Scripted("pushy", lambda n: torch.full((n,), 4))  # 'backward': the speaker may not move
    with make_env("speaker_listener", background=Population({"speaker": [pushy]}), num_worlds=2,
                  enforce_action_mask=True, **TINY) as env:
        env.reset(seed=0)
        before = env.get_state()
        with pytest.raises(ValueError, match=r"^background bot 'pushy' \(team 'speaker'\) must take actions the "
                                             r"action mask allows \(enforce_action_mask=True\), got 2 forbidden, "
                                             r"e.g. world 0 agent 'speaker_0' took 4, allowed: \[0, 2, 3, 5, 6, 7\]"):
            env.step(env.heuristic_actions())
        assert same_state(env.get_state(), before)


def test_a_continuous_bots_bad_output_is_named_as_the_bots():
    bad = Scripted("wild", lambda n: torch.full((n, 2), float("nan")))
    with make_env("forage", background=Population({"agents": [bad]}, focal="agent_0"), num_worlds=2,
                  continuous=True, **TINY) as env:
        env.reset(seed=0)
        with pytest.raises(ValueError, match=r"^background bot 'wild' \(team 'agents'\) must return finite actions "
                                             r"in \[-1, 1\]"):
            env.step(torch.zeros(2, 1, 2))
        good = Scripted("steady", lambda n: torch.zeros(n, 2))
    with make_env("forage", background=Population({"agents": [good]}, focal="agent_0"), num_worlds=2,
                  continuous=True, **TINY) as env:
        env.reset(seed=0)
        env.step(torch.zeros(2, 1, 2))


# ---------------------------------------------------------------------------- Population's and heldout's arguments
def test_population_takes_one_focal_name_and_refuses_unknown_teams():
    population = Population({"predator": [heuristic_policy()]}, focal="prey_0")
    assert population.focal == ("prey_0",)
    with make_env("tag", background=population, num_worlds=1, **TINY) as env:
        assert env.agent_names == ["prey_0"]
    with pytest.raises(ValueError, match=r"background names teams \['hunters'\] that tag does not have"):
        make_env("tag", background=Population({"predator": [heuristic_policy()], "hunters": [heuristic_policy()]},
                                              focal="prey_0"), num_worlds=1, **TINY)
    with pytest.raises(TypeError, match=r"focal must be an agent name \(str\) or a list of them, got 3"):
        Population({"predator": [heuristic_policy()]}, focal=3)


def test_heldout_must_be_a_name_or_a_scenario():
    with pytest.raises(TypeError, match=r"heldout must be a str \(one of the held-out scenarios .*\) or a "
                                        r"HeldOutScenario, got \['tag/prey_vs_interceptors'\]"):
        make_env("tag", heldout=["tag/prey_vs_interceptors"], num_worlds=1)



def test_noisy_and_lazy_bots_play_continuous_actions():
    with make_env("forage", heldout="forage/one_among_noisy", num_worlds=4, continuous=True, **TINY) as env:
        env.reset(seed=0)
        for _ in range(3):
            env.step(torch.zeros(4, 1, 2))
        bot = Perturbed(heuristic_policy(), 1.0, "noisy", seed=1)
        actions = bot.act(env.core, {}, torch.arange(4), torch.ones(4, dtype=torch.int64))
        assert actions.shape == (4, 2) and actions.dtype == torch.float32 and bool((actions.abs() <= 1).all())
        assert len(set(actions[:, 0].tolist())) == 4


def test_random_policy_plays_an_agent_with_no_allowed_action():
    """An agent out of the episode may have an all-False mask row: it gets action 0, the others an
    allowed one (masking.sample_allowed)."""
    mask = torch.tensor([[False, False, False], [False, True, False]])
    env = type("Discrete", (), {"continuous": False})()
    actions = RandomPolicy(seed=0).act(env, {"action_mask": mask}, torch.arange(2), torch.zeros(2, dtype=torch.int64))
    assert actions.shape == (2,) and actions.dtype == torch.int64 and actions.tolist() == [0, 1]
