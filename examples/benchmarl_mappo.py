"""MAPPO from pixels with BenchMARL: a CNN policy and critic on a marl_render env, a few iterations.

BenchMARL pins torchrl<0.12, so it lives in its own venv: `make test-benchmarl` builds
.venv-benchmarl (BenchMARL, its torchrl, the CPU torch) and runs its tests; then

    .venv-benchmarl/bin/python examples/benchmarl_mappo.py --env spread --iters 3

Logs (CSV) go under --out; the episode statistics of the env appear there as
collection_info_<name>.csv (spread: coverage, collisions).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from marl_render.envs import list_envs


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--env", default="spread", choices=list_envs(), help="environment")
    parser.add_argument("--worlds", type=int, default=8, help="worlds stepped together while collecting")
    parser.add_argument("--resolution", type=int, default=32, help="pixels per side of each view")
    parser.add_argument("--steps", type=int, default=50, help="steps per episode (max_steps)")
    parser.add_argument("--iters", type=int, default=3, help="collect + train iterations")
    parser.add_argument("--seed", type=int, default=0, help="experiment seed")
    parser.add_argument("--out", default="out/benchmarl", help="folder for BenchMARL's logs")
    args = parser.parse_args()
    try:  # imported here so that --help works without BenchMARL
        from benchmarl.algorithms import MappoConfig
        from benchmarl.experiment import Experiment, ExperimentConfig
        from benchmarl.models import CnnConfig
    except ImportError as exc:
        parser.exit(2, f"{exc}: this example needs BenchMARL; `make test-benchmarl` builds .venv-benchmarl "
                       f"with it, then run .venv-benchmarl/bin/python {parser.prog}\n")
    from marl_render.wrappers.benchmarl import MarlRenderTask

    task = getattr(MarlRenderTask, args.env.upper()).get_task(
        config={"resolution": args.resolution, "max_steps": args.steps})

    config = ExperimentConfig.get_from_yaml()  # BenchMARL's defaults, made small enough for a CPU
    config.loggers = ["csv"]
    config.save_folder = str(Path(args.out).absolute())
    Path(config.save_folder).mkdir(parents=True, exist_ok=True)
    config.max_n_iters = args.iters
    config.on_policy_n_envs_per_worker = args.worlds
    config.on_policy_collected_frames_per_batch = args.worlds * args.steps  # one episode per world
    config.on_policy_n_minibatch_iters = 4
    config.on_policy_minibatch_size = min(256, args.worlds * args.steps)
    config.evaluation_interval = args.worlds * args.steps * args.iters  # evaluate once, at the end
    config.evaluation_episodes = 4

    experiment = Experiment(task=task, algorithm_config=MappoConfig.get_from_yaml(),
                            model_config=CnnConfig.get_from_yaml(), critic_model_config=CnnConfig.get_from_yaml(),
                            seed=args.seed, config=config)
    experiment.run()
    print(f"{experiment.n_iters_performed} iterations, {experiment.total_frames} frames; "
          f"logs in {experiment.folder_name}")


if __name__ == "__main__":
    main()
