"""Reference results: every task trained from pixels, one command per task::

    python -m marl_render.baselines --env spread                  # the task's step budget, out/baselines/spread/
    python -m marl_render.baselines --env cartpole --env-steps 2000000 --out docs/baselines/cartpole
    python -m marl_render.baselines.published                     # every published command (make baselines runs them)
    python -m marl_render.baselines.report                        # docs/baselines.md from docs/baselines/*/

or from Python, on any registered task: ``train("spread", env_steps=200_000)`` (training.py).

The learner is MAPPO (PPO with a centralised critic) in plain torch: the clipped PPO loss
(TorchRL's ClipPPOLoss written out on tensors, ppo.py) and GAE (TorchRL's arithmetic,
advantage.py; tests hold both equal to TorchRL's), without importing TorchRL. One actor shared by
the trained agents (an agent one-hot tells them apart) sees only the agent's own egocentric pixels
(``--obs state``: its state observation instead); the critic sees the state observations of all
agents of the world. The learned greedy policy is measured with
``marl_render.envs.evaluation.evaluate``, the same evaluation as the task's uniform random and
scripted heuristic policies (docs/reference_returns.json).

Modules: settings (hyperparameters; a task's own defaults and step budget are on its class,
``Scenario.training``), ppo (rollouts and updates), training (``train``: the loop, its budget and
checkpoints), policy (the greedy policy handed to evaluate), selfplay (the pool of frozen
snapshots behind --self-play), curve (curve.png), run (the command line), records (what a run
writes: result.json, snapshots, versions), published (the published runs as data, ``make
baselines``), report (docs/baselines.md) with figures (its pictures) and marl_eval (the runs in
marl-eval's JSON layout, as BenchMARL writes them). The actor and critic networks and the
statistics across seeds (interquartile mean, stratified bootstrap intervals, as rliable) are the
populations layer's (marl_render/populations/networks.py, stats.py), which loads and scores runs.
"""
from .selfplay import SelfPlay
from .settings import EVALUATION_SETS, STEP_BUDGETS, TASK_DEFAULTS, Hyperparameters, task_hyperparameters
from .training import TrainingRun, train

__all__ = ["EVALUATION_SETS", "Hyperparameters", "STEP_BUDGETS", "SelfPlay", "TASK_DEFAULTS", "TrainingRun",
           "task_hyperparameters", "train"]
