"""The trainer on issue 41's tasks: a tiny run of each from pixels and from the state, end to end, and
the task's own vector observations (Scenario.vector_obs: matrix's inventory) in the actor and the critic,
in a saved run and in the view ablation (which takes the pixels away, never the inventory)."""
import json
import math

import pytest
import torch

from marl_render.baselines import ablate, run
from marl_render.baselines.ppo import MAPPO, minibatch_indices
from marl_render.baselines.published import RUNS
from marl_render.baselines.settings import STEP_BUDGETS, Hyperparameters
from marl_render.envs import make_env
from marl_render.envs.evaluation import evaluate
from marl_render.populations.networks import Actor
from marl_render.populations.policies import load_policy

NEW_TASKS = ("clean_up", "cooking", "coop_mining", "matrix", "territory")
# One update of 2 worlds x 4 decisions, no checkpoint, one evaluation episode of 10 steps.
TINY = ["--env-steps", "8", "--worlds", "2", "--resolution", "12", "--rollout", "4", "--episodes", "1",
        "--checkpoint-every", "0", "--env-option", "max_steps=10"]


@pytest.mark.parametrize("obs", ["pixels", "state"])
@pytest.mark.parametrize("task", NEW_TASKS)
def test_a_tiny_run_of_each_new_task_trains_saves_and_loads(task, obs, tmp_path):
    out = tmp_path / task
    assert run.main(["--env", task, "--obs", obs, "--out", str(out), *TINY]) == 0
    result = json.loads((out / "result.json").read_text())
    assert (result["env"], result["obs"], result["env_steps"], result["updates"]) == (task, obs, 8, 1)
    vectors = list(make_env(task, num_worlds=1, resolution=8).vector_obs)
    assert result.get("vector_obs", []) == vectors
    policy = load_policy(str(out))
    assert policy.vector_keys == tuple(vectors) and policy.needs >= {obs, "action_mask", *vectors}
    # The saved actor is the one scored: it plays the run's own evaluation episode return for return.
    score = evaluate(task, policy, episodes=1, seed=result["seeds"]["evaluation"], **policy.env_kwargs,
                     max_steps=10)
    assert score["per_episode"] == result["evaluation"]["policy"]["per_episode"]


def test_matrix_runs_feed_the_inventory_to_the_actor_and_every_agents_to_the_critic():
    hp = Hyperparameters(worlds=2, resolution=12, rollout=4, epochs=1, minibatches=1, hidden=16)
    trainer = MAPPO("matrix", hp, "pixels", 0, {"max_steps": 10})
    env, A, K = trainer.env, trainer.env.num_agents, 2  # prisoner's dilemma: two kinds
    assert trainer.vector_keys == ("inventory",) and trainer.actor_net.vector_dim == K
    features = trainer.actor_net.encoder.features
    assert trainer.actor_net.head[0].in_features == features + K + A
    assert trainer.critic_net.norm.mean.shape == (A * (env.state_dim + K),)
    samples, _ = trainer.collect()
    assert samples["vector"].shape == (len(samples["action"]), K)
    assert set(trainer.update(samples)) >= {"loss_objective", "loss_critic"}
    trainer.close()


def test_the_actor_reads_its_vector_and_refuses_a_missing_or_wrong_one():
    torch.manual_seed(0)
    actor = Actor("state", (6,), 3, 4, 16, init="orthogonal", vector_dim=2)
    actor.vector_norm.update(torch.tensor([[0.0, 0.0], [4.0, 2.0]]))
    observation, agent, mask = torch.zeros(1, 6), torch.eye(3)[:1], torch.ones(1, 4, dtype=torch.bool)
    empty = actor(observation, agent, mask, torch.zeros(1, 2))
    full = actor(observation, agent, mask, torch.tensor([[4.0, 2.0]]))
    assert not torch.equal(empty, full)  # the same view, another inventory: other logits
    with pytest.raises(ValueError, match=r"vector must be the agent's vector observations \[N, 2\].*got None"):
        actor(observation, agent, mask)
    with pytest.raises(ValueError, match=r"vector must .*\[N, 2\].*got \[\.\.\., 3\]"):
        actor(observation, agent, mask, torch.zeros(1, 3))
    with pytest.raises(ValueError, match=r"vector must .*\[N, 0\].*got \[\.\.\., 2\]"):
        Actor("state", (6,), 3, 4, 16)(observation, agent, mask, torch.zeros(1, 2))
    with pytest.raises(ValueError, match="vector_dim must be an int >= 0, got -1"):
        Actor("state", (6,), 3, 4, 16, vector_dim=-1)


def test_an_actor_without_vectors_is_the_one_built_before():
    """vector_dim=0 adds no parameter, buffer or random draw: the weights of a seed are unchanged."""
    torch.manual_seed(3)
    before = Actor("pixels", (16, 16, 3), 3, 5, 32, encoder="patch", init="orthogonal").state_dict()
    torch.manual_seed(3)
    after = Actor("pixels", (16, 16, 3), 3, 5, 32, encoder="patch", init="orthogonal", vector_dim=0).state_dict()
    assert list(before) == list(after) and all(torch.equal(before[k], after[k]) for k in before)
    assert not any(key.startswith("vector_norm") for key in before)


class RecordingActor(Actor):
    """An actor that keeps the inputs of its last forward."""

    def forward(self, observation, agent, mask, vector=None):
        self.seen = (observation.clone(), None if vector is None else vector.clone())
        return super().forward(observation, agent, mask, vector)


def test_the_view_ablation_takes_the_pixels_away_and_keeps_the_inventory():
    env = make_env("matrix", num_worlds=2, resolution=12, max_steps=10)
    obs = env.reset(seed=0)
    obs["inventory"] = torch.arange(2 * env.num_agents * 2, dtype=torch.float32).reshape(2, env.num_agents, 2)
    actor = RecordingActor("pixels", (12, 12, 3), env.num_agents, env.num_actions, 16, encoder="patch", vector_dim=2)
    policy = ablate.AblatedPolicy(actor, 1, 1, "zeros", ("inventory",))
    assert policy.needs == {"pixels", "action_mask", "inventory"}
    policy(env, obs, torch.Generator())
    observation, vector = actor.seen
    assert not bool(observation.any())  # the view is gone
    assert torch.equal(vector, obs["inventory"].flatten(0, 1))  # the inventory is not
    env.close()


def test_a_run_whose_result_and_actor_disagree_about_vectors_is_refused(tmp_path):
    out = tmp_path / "matrix"
    assert run.main(["--env", "matrix", "--out", str(out), *TINY]) == 0
    found = ablate.view_ablation(out, views=("none", "zeros"))
    assert found["reproduces_run"] is True
    result = json.loads((out / "result.json").read_text())
    del result["vector_obs"]
    (out / "result.json").write_text(json.dumps(result))
    with pytest.raises(ValueError, match=r"vector_obs \[\] does not fit the actor, which reads vector observations"):
        load_policy(str(out))


@pytest.mark.parametrize("task", NEW_TASKS)
def test_the_new_tasks_have_published_entries_and_step_budgets(task):
    budget = STEP_BUDGETS[task]
    assert set(budget) == {"pixels", "state"} and all(isinstance(n, int) and n > 0 for n in budget.values())
    assert {obs: RUNS[task][obs].env_steps for obs in ("pixels", "state")} == budget


def test_a_lone_last_sample_joins_the_minibatch_before_it():
    """Territory removes trained agents, whose samples are left out: a rollout of 4k + 1 samples made a
    last minibatch of one sample, a NaN advantage standard deviation and NaN weights."""
    assert [c.tolist() for c in minibatch_indices(torch.arange(9), 4)] == [[0, 1, 2, 3], [4, 5, 6, 7, 8]]
    assert [c.tolist() for c in minibatch_indices(torch.arange(10), 4)] == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9]]
    assert [c.tolist() for c in minibatch_indices(torch.arange(8), 4)] == [[0, 1, 2, 3], [4, 5, 6, 7]]
    hp = Hyperparameters(worlds=2, resolution=8, rollout=4, epochs=1, minibatches=4, hidden=16, overlap=False)
    trainer = MAPPO("spread", hp, "state", 0, {})
    samples, _ = trainer.collect()
    trainer.close()
    size = len(samples["action"])  # 2 worlds x 4 decisions x 3 agents: 24
    kept = torch.arange(size - 3)  # 21 = 4 x 5 + 1: as if three samples were of removed agents
    samples = {k: (v if k == "norms" else v.index_select(0, kept)) for k, v in samples.items()}
    terms = trainer.update(samples)
    assert all(math.isfinite(value) for value in terms.values())
    assert all(bool(p.isfinite().all()) for p in trainer.parameters)
