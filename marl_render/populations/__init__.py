"""The populations layer (docs/architecture.md): what plays the envs besides a learner, and how a
policy is scored against it. Above the envs, below the trainer (marl_render.baselines).

- policies.py: loading a trained run as a Policy (the protocol itself is envs/policy.py);
- networks.py: the actor and critic networks that the trainer trains and load_policy rebuilds;
- bots.py, heldout.py: each task's bots and held-out scenarios, read from the task classes;
- evaluate.py (``python -m marl_render.evaluate``), crossplay.py, pages.py, elo.py, stats.py,
  generalise.py (``python -m marl_render.generalise``): scores, matrices, ratings and their pages;
- play.py (``python -m marl_render.play``): a person plays a task.

The modules' old paths (marl_render.evaluate, marl_render.bots, ...) are these modules themselves
(moved.py).
"""
