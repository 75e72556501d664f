"""MAPPO on `spread` from pixels, with TorchRL, on a laptop CPU.

- Actor: one CNN shared by all agents, on each agent's own egocentric RGB view.
- Critic: centralised; sees the low-dimensional state of every agent of the world
  (MAPPO's global state) and outputs one value per agent.
- TorchRL pieces: the marl-render TorchRL env, a Collector, GAE and ClipPPOLoss.

Before and after training, the same evaluation is run: one episode in each of --worlds
fresh worlds (fixed seeds), played by the greedy policy and by uniform random actions.
The reported return is the true episode return: the sum of an agent's rewards over its
episode, averaged over agents and episodes. The script prints the returns and writes
OUT/curve.png (the returns of the training episodes as they end, against time, with the
evaluations) and OUT/result.json. --minutes is the budget of the whole run, evaluations
included: training stops when the next batch and the final evaluation would not fit (it
always trains at least one batch).

    python examples/train_mappo.py [--minutes 12] [--worlds 64] [--resolution 32] [--out out/mappo]
"""
import argparse
import json
import os
import time

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from marl_render.envs import make_torchrl_env
from marl_render.extras import command_needs_extra

with command_needs_extra("plots", "examples/train_mappo.py"):  # before training, not after it
    import matplotlib
    from tqdm import tqdm

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the headless backend)

GROUP = "agents"


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


class PixelActor(nn.Module):
    """Shared CNN: [..., H, W, 3] uint8 -> [..., actions] logits, any leading dims."""

    def __init__(self, resolution: int, actions: int):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(3, 16, 4, stride=2), nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2), nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            features = self.net(torch.zeros(1, 3, resolution, resolution)).shape[-1]
        self.head = nn.Sequential(nn.Linear(features, 128), nn.ReLU(), nn.Linear(128, actions))

    def forward(self, pixels):
        lead = pixels.shape[:-3]
        x = pixels.reshape(-1, *pixels.shape[-3:]).permute(0, 3, 1, 2).float() / 255.0
        return self.head(self.net(x)).reshape(*lead, -1)


class CentralCritic(nn.Module):
    """[..., N, state_dim] -> [..., N, 1]: every agent's value from all agents' states."""

    def __init__(self, agents: int, state_dim: int):
        super().__init__()
        self.agents = agents
        self.net = nn.Sequential(nn.Linear(agents * state_dim, 256), nn.Tanh(), nn.Linear(256, 256), nn.Tanh(),
                                 nn.Linear(256, agents))

    def forward(self, state):
        return self.net(state.flatten(-2)).unsqueeze(-1)


def evaluate(env, actor, seed: int, random: bool) -> tuple[float, int]:
    """(mean return, episodes): the first episode of every world of `env` from a seeded reset,
    played by `actor` (greedy) or by uniform random actions. An agent's return is the sum of
    its rewards over the episode; the mean is over agents and episodes (one per world)."""
    env.set_seed(seed)
    td = env.reset()
    worlds = env.batch_size[0]
    returns = torch.zeros(worlds)  # sum over the episode of the reward averaged over agents
    playing = torch.ones(worlds, dtype=torch.bool)  # still in its first episode
    for _ in range(env.core.max_steps):  # every episode ends by max_steps
        if random:
            td = env.rand_action(td)
        else:
            with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
                td = actor(td)
        td, next_td = env.step_and_maybe_reset(td)
        returns += torch.where(playing, td["next", GROUP, "reward"].mean(dim=(1, 2)), 0.0)
        playing &= ~td["next", "done"][:, 0]
        td = next_td
        if not playing.any():
            break
    if playing.any():
        raise RuntimeError(f"{int(playing.sum())} worlds did not finish an episode in max_steps steps")
    return float(returns.mean()), worlds


def next_batch_overruns(elapsed: float, batch_seconds: float, budget: float) -> bool:
    """The stopping rule: training that has run `elapsed` seconds, the last batch taking
    `batch_seconds`, stops when one more such batch would end past `budget` seconds."""
    return elapsed + batch_seconds > budget


def completed_episodes(batch, running: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Returns of the episodes that ended in a collector batch [worlds, steps], and the running
    returns of the episodes still going. `running` [worlds] carries them from batch to batch;
    a return is the sum over the episode of the reward averaged over agents."""
    reward = batch["next", GROUP, "reward"].mean(dim=(-2, -1))  # [worlds, steps]
    done = batch["next", "done"][..., 0]
    ended = []
    for step in range(reward.shape[1]):  # over time; all worlds at once
        running = running + reward[:, step]
        ended.append(running[done[:, step]])
        running = torch.where(done[:, step], 0.0, running)
    return torch.cat(ended), running


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--minutes", type=float, default=12.0, help="wall-clock budget, evaluations included")
    parser.add_argument("--worlds", type=int, default=64, help="worlds stepped together")
    parser.add_argument("--agents", type=int, default=3, help="agents per world")
    parser.add_argument("--resolution", type=int, default=32, help="pixels per side of each view")
    parser.add_argument("--max-steps", type=int, default=100, help="episode length (spread's default)")
    parser.add_argument("--rollout", type=int, default=32, help="steps per world per batch")
    parser.add_argument("--epochs", type=int, default=4, help="passes over each batch")
    parser.add_argument("--minibatch", type=int, default=512, help="(world, step) samples per minibatch")
    parser.add_argument("--lr", type=float, default=5e-4, help="Adam learning rate")
    parser.add_argument("--seed", type=int, default=0, help="seed of the env and the networks")
    parser.add_argument("--out", default="out/mappo", help="folder for curve.png and result.json")
    args = parser.parse_args()
    started = time.perf_counter()
    deadline = started + args.minutes * 60
    torch.manual_seed(args.seed)

    env_kwargs = dict(num_agents=args.agents, resolution=args.resolution, max_steps=args.max_steps, state_obs=True)
    env = make_torchrl_env("spread", num_worlds=args.worlds, seed=args.seed, **env_kwargs)
    eval_env = make_torchrl_env("spread", num_worlds=args.worlds, seed=10_000, **env_kwargs)
    actions = env.action_spec[GROUP, "action"].space.n
    state_dim = env.observation_spec[GROUP, "state"].shape[-1]

    actor = ProbabilisticActor(
        TensorDictModule(PixelActor(args.resolution, actions), in_keys=[(GROUP, "pixels")],
                         out_keys=[(GROUP, "logits")]),
        in_keys=[(GROUP, "logits")], out_keys=[(GROUP, "action")], distribution_class=torch.distributions.Categorical,
        return_log_prob=True, log_prob_key=(GROUP, "sample_log_prob"), spec=env.full_action_spec[GROUP, "action"])
    critic = TensorDictModule(CentralCritic(args.agents, state_dim), in_keys=[(GROUP, "state")],
                              out_keys=[(GROUP, "state_value")])

    loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_coeff=0.01, normalize_advantage=True,
                       normalize_advantage_exclude_dims=(-2,))  # each agent normalised on its own
    loss.set_keys(reward=(GROUP, "reward"), action=(GROUP, "action"), sample_log_prob=(GROUP, "sample_log_prob"),
                  value=(GROUP, "state_value"), done=(GROUP, "done"), terminated=(GROUP, "terminated"))
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.97, lmbda=0.95)
    optimizer = torch.optim.Adam(loss.parameters(), lr=args.lr)

    print(f"evaluating the untrained and the random policy on {args.worlds} episodes ...", flush=True)
    random_return, episodes = evaluate(eval_env, actor, 123, random=True)
    before = time.perf_counter()
    untrained_return, _ = evaluate(eval_env, actor, 123, random=False)
    eval_seconds = time.perf_counter() - before  # the final evaluation is the same one
    print(f"episode return per agent: random policy {random_return:.2f}, untrained greedy {untrained_return:.2f}",
          flush=True)

    frames_per_batch = args.worlds * args.rollout
    collector = Collector(env, actor, frames_per_batch=frames_per_batch, total_frames=-1)
    start = time.perf_counter()
    budget = max(deadline - eval_seconds - start, 0.0)  # seconds for training
    curve = []  # (seconds, agent-frames, mean reward per agent-step, mean return of the episodes ended or None)
    progress = tqdm(total=int(budget), unit="s", desc="training",
                    bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt}s {postfix}")
    agent_frames, running, last_return = 0, torch.zeros(args.worlds), None
    last_elapsed = 0.0
    for batch in collector:
        ended, running = completed_episodes(batch, running)
        batch = batch.reshape(-1)  # [worlds * rollout] samples, each with its N agents
        with torch.no_grad():
            loss.value_estimator(batch, params=loss.critic_network_params,
                                 target_params=loss.target_critic_network_params)
        for _ in range(args.epochs):
            for index in torch.randperm(len(batch)).split(args.minibatch):
                terms = loss(batch[index])
                total = terms["loss_objective"] + terms["loss_critic"] + terms["loss_entropy"]
                optimizer.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 1.0)
                optimizer.step()
        collector.update_policy_weights_()
        agent_frames += frames_per_batch * args.agents
        elapsed = time.perf_counter() - start  # the curve's time and the stopping rule's: one reading
        batch_seconds, last_elapsed = elapsed - last_elapsed, elapsed
        reward = float(batch["next", GROUP, "reward"].mean())
        episode_return = float(ended.mean()) if len(ended) else None
        last_return = last_return if episode_return is None else episode_return
        curve.append((elapsed, agent_frames, reward, episode_return))
        progress.n = min(int(elapsed), int(budget))
        # Until an episode ends there is no episode return to show: show the return so far.
        shown = "-" if last_return is None else f"{last_return:.1f}"
        progress.set_postfix_str(f"episode return {shown} (running episodes so far {float(running.mean()):.1f}), "
                                 f"{agent_frames / elapsed:,.0f} agent-frames/s")
        progress.refresh()
        if next_batch_overruns(elapsed, batch_seconds, budget):  # it would eat into the final evaluation
            break
    progress.close()
    collector.shutdown()

    trained_at = time.perf_counter()
    trained_return, _ = evaluate(eval_env, actor, 123, random=False)
    result = {"random_return": random_return, "untrained_return": untrained_return, "trained_return": trained_return,
              "return": "sum of an agent's rewards over its episode, mean over agents and episodes",
              "eval_episodes": episodes, "episode_steps": eval_env.core.max_steps,
              "minutes": (time.perf_counter() - started) / 60, "budget_minutes": args.minutes,
              "eval_seconds": eval_seconds, "train_started_seconds": start - started, "train_budget_seconds": budget,
              "train_minutes": (trained_at - start) / 60, "agent_frames": agent_frames,
              "worlds": args.worlds, "agents": args.agents, "resolution": args.resolution}
    print(f"return per agent and episode ({episodes} episodes): random {random_return:.2f} -> trained "
          f"{trained_return:.2f}")
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "result.json"), "w") as f:
        json.dump({**result, "curve": curve}, f, indent=2)
    plot(curve, result, os.path.join(args.out, "curve.png"))
    env.close()
    eval_env.close()


def plot(curve, result, path):
    ended = [(seconds / 60, episode_return) for seconds, _, _, episode_return in curve if episode_return is not None]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot([m for m, _ in ended], [r for _, r in ended], marker=".", label="training episodes (sampled actions)")
    ax.axhline(result["random_return"], color="gray", linestyle="--",
               label=f"random policy ({result['random_return']:.1f})")
    ax.axhline(result["trained_return"], color="green", linestyle=":",
               label=f"trained, greedy ({result['trained_return']:.1f})")
    ax.set_xlabel("minutes of training (2 CPU cores)")
    ax.set_ylabel("episode return per agent")
    ax.set_title(f"MAPPO on spread from {result['resolution']}x{result['resolution']} pixels, "
                 f"{result['worlds']} worlds x {result['agents']} agents", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
