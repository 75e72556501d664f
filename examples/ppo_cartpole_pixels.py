"""PPO on cartpole from pixels, CleanRL-style: one file, read top to bottom.

The environment is `make_vec_env("cartpole", num_worlds=W)`: a gymnasium VectorEnv whose W
worlds are stepped by one batched core and drawn by one renderer. The policy decides every
`--action-repeat` steps (0.01 s each: between two single steps the pole moves by less
than a pixel) and sees its last `--frames` decision frames, stacked so that it can tell
velocities, through a small CNN. The vector env resets in gymnasium's next-step mode: the
step after an episode ends returns the first frame of the next one with reward 0; that
transition is left out of the loss, and a time-limit truncation is bootstrapped from the
episode's final frame.

Before and after training, the same evaluation runs: one full episode per world with
uniform random actions (drawn every step, and drawn every decision), with no force at all
(the pole then falls slowly from its nearly upright start: a strong baseline, since every
push costs reward) and with the trained policy (greedy). The script prints them, writes
`curve.png` and `result.json` to `--out`, and shows a progress bar. The curve has the
returns of the training episodes that ended (none in a run shorter than one episode of
every world, --max-steps x --worlds steps) and, after every update, the mean reward per
step of that update's rollout times --max-steps: the return an episode would get at
that rate, so that short runs show their progress on the same scale (a rate, not a return:
the worlds run in step, and the early steps of an episode, pole still up, earn more).

    python examples/ppo_cartpole_pixels.py                 # defaults: about 10 minutes on 2 cores
    python examples/ppo_cartpole_pixels.py --steps 50000   # a quick look
"""
import argparse
import json
import os
import resource
import time

import numpy as np
import torch
from torch import nn

from marl_render.envs import make_vec_env
from marl_render.envs.cartpole import FORCE_LEVELS
from marl_render.extras import command_needs_extra

with command_needs_extra("plots", "examples/ppo_cartpole_pixels.py"):  # before training, not after it
    import matplotlib
    from tqdm import tqdm

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the headless backend)

NO_FORCE = FORCE_LEVELS.index(0.0)  # the discrete action that pushes with no force


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--worlds", type=int, default=64, help="parallel worlds (vector env entries)")
    parser.add_argument("--resolution", type=int, default=48, help="pixels per side of each frame")
    parser.add_argument("--steps", type=int, default=1_000_000, help="environment steps to train for, all worlds")
    parser.add_argument("--seed", type=int, default=0, help="seed of the env and the network")
    parser.add_argument("--out", default="out/ppo_cartpole", help="folder for curve.png and result.json")
    parser.add_argument("--max-steps", type=int, default=1000, help="episode length (dm_control: 1000 = 10 s)")
    parser.add_argument("--action-repeat", type=int, default=4, help="environment steps per decision")
    parser.add_argument("--frames", type=int, default=3, help="stacked decision frames the policy sees")
    parser.add_argument("--rollout", type=int, default=32, help="decisions per world between updates")
    parser.add_argument("--epochs", type=int, default=4, help="passes over each rollout")
    parser.add_argument("--minibatches", type=int, default=4, help="minibatches per pass")
    parser.add_argument("--lr", type=float, default=3e-4, help="Adam learning rate")
    parser.add_argument("--gamma", type=float, default=0.95, help="discount per decision")
    parser.add_argument("--gae-lambda", type=float, default=0.95, help="GAE lambda")
    parser.add_argument("--clip", type=float, default=0.2, help="PPO clip range of the probability ratio")
    parser.add_argument("--ent-coef", type=float, default=0.01, help="entropy bonus weight")
    parser.add_argument("--vf-coef", type=float, default=0.5, help="value loss weight")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads for the network (the renderer has its own)")
    return parser.parse_args()


class Agent(nn.Module):
    """A small CNN on the stacked frames [N, frames * 3, H, W] (uint8), actor and critic heads."""

    def __init__(self, frames: int, resolution: int, actions: int):
        super().__init__()
        self.body = nn.Sequential(  # small on purpose: the whole run must fit 2 CPU cores
            nn.Conv2d(3 * frames, 16, 4, stride=2), nn.ReLU(),
            nn.Conv2d(16, 16, 3, stride=2), nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            features = self.body(torch.zeros(1, 3 * frames, resolution, resolution)).shape[1]
        self.trunk = nn.Sequential(nn.Linear(features, 128), nn.ReLU())
        self.actor = nn.Linear(128, actions)
        self.critic = nn.Linear(128, 1)
        nn.init.orthogonal_(self.actor.weight, 0.01)
        nn.init.zeros_(self.actor.bias)

    def forward(self, frames):
        hidden = self.trunk(self.body(frames.float() / 255.0))
        return torch.distributions.Categorical(logits=self.actor(hidden)), self.critic(hidden)[:, 0]


class FrameStack:
    """The last `frames` observations of every entry as uint8 [N, frames * 3, H, W]."""

    def __init__(self, frames: int):
        self.frames = frames
        self.stack = None

    def reset(self, obs: np.ndarray) -> torch.Tensor:
        first = torch.from_numpy(obs).permute(0, 3, 1, 2)
        self.stack = first.repeat(1, self.frames, 1, 1)
        return self.stack

    def push(self, obs: np.ndarray, restarted: torch.Tensor) -> torch.Tensor:
        """Add a frame; entries whose episode restarted with it start from it alone."""
        frame = torch.from_numpy(obs).permute(0, 3, 1, 2)
        self.stack = torch.cat((self.stack[:, 3:], frame), 1)
        if bool(restarted.any()):
            self.stack[restarted] = frame[restarted].repeat(1, self.frames, 1, 1)
        return self.stack


def act(envs, actions: np.ndarray, repeat: int):
    """Hold `actions` for up to `repeat` steps: (last obs, summed rewards, terminated,
    truncated, steps taken). Stops early when an episode ends, so that the last obs is then
    its final frame. Cartpole's worlds all start together and end only at max_steps, so
    they stay in step with each other."""
    total = np.zeros(envs.num_envs, dtype=np.float32)
    for taken in range(1, repeat + 1):  # noqa: B007 (returned below: the steps taken)
        obs, reward, terminated, truncated, _ = envs.step(actions)
        total += reward
        if (terminated | truncated).any():
            break
    return obs, total, terminated, truncated, taken


def evaluate(envs, agent, args, seed: int, policy: str):
    """Return of one full episode per entry (all worlds start together, all end at max_steps).

    policy: "trained" (greedy), "random" (a uniform action every decision, held for
    action_repeat steps), "random_each_step" or "no_force". Also returns how often each
    action was chosen."""
    repeat = 1 if policy == "random_each_step" else args.action_repeat
    stack = FrameStack(args.frames)
    obs, _ = envs.reset(seed=seed)
    frames_now = stack.reset(obs)
    returns = np.zeros(envs.num_envs)
    done = np.zeros(envs.num_envs, dtype=bool)
    generator = np.random.default_rng(seed)
    chosen = np.zeros(envs.single_action_space.n, dtype=np.int64)
    while not done.all():
        if policy == "trained":
            with torch.no_grad():
                distribution, _ = agent(frames_now)
            actions = distribution.probs.argmax(1).numpy()
        elif policy == "no_force":
            actions = np.full(envs.num_envs, NO_FORCE)
        else:
            actions = generator.integers(0, envs.single_action_space.n, envs.num_envs)
        obs, reward, terminated, truncated, _ = act(envs, actions, repeat)
        chosen += np.bincount(actions, minlength=len(chosen))
        returns += np.where(done, 0.0, reward)
        done |= terminated | truncated
        frames_now = stack.push(obs, torch.zeros(envs.num_envs, dtype=torch.bool))
    return returns, chosen / chosen.sum()


def plot(curve, rollouts, levels: dict, args):
    """curve.png: training episode returns and rollout reward rates against environment
    steps, and horizontal levels."""
    figure, axes = plt.subplots(figsize=(6, 3.6))
    if rollouts:
        axes.plot(*zip(*rollouts, strict=True), color="tab:purple", alpha=0.6,
                  label=f"training rollouts: reward per step x {args.max_steps}")
    if curve:
        axes.plot(*zip(*curve, strict=True), marker="o", label="training episodes (sampled actions)")
    styles = (("grey", "--"), ("orange", "-."), ("green", ":"))  # one per level
    for (label, level), (color, style) in zip(levels.items(), styles, strict=True):
        axes.axhline(level, color=color, linestyle=style, label=label)
    axes.set_xlabel("environment steps (all worlds)")
    axes.set_ylabel(f"episode return ({args.max_steps} steps)")
    axes.set_title(f"PPO, cartpole from {args.resolution}x{args.resolution} pixels, {args.worlds} worlds")
    axes.legend(loc="center right", fontsize=8)
    figure.tight_layout()
    figure.savefig(os.path.join(args.out, "curve.png"), dpi=120)


def main():
    args = parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    os.makedirs(args.out, exist_ok=True)
    started, cpu_started = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)

    envs = make_vec_env("cartpole", num_worlds=args.worlds, resolution=args.resolution,
                        max_steps=args.max_steps, seed=args.seed)
    N = envs.num_envs
    agent = Agent(args.frames, args.resolution, envs.single_action_space.n)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.lr, eps=1e-5)

    random_each_step, _ = evaluate(envs, agent, args, args.seed + 1, "random_each_step")
    random_returns, _ = evaluate(envs, agent, args, args.seed + 1, "random")
    no_force, _ = evaluate(envs, agent, args, args.seed + 1, "no_force")
    print(f"random policy: return {random_returns.mean():.1f} +- {random_returns.std():.1f} (a new action every "
          f"{args.action_repeat} steps), {random_each_step.mean():.1f} +- {random_each_step.std():.1f} (every step); "
          f"no force: {no_force.mean():.1f}; over {N} episodes of {args.max_steps} steps")

    # Values are learnt on a return scale of about 1 (rewards are up to 1 per step): large
    # value errors would otherwise swamp the policy's gradient in the shared network.
    reward_scale = (1 - args.gamma) / args.action_repeat
    # Rollout storage: decision t sees frames[t], does actions[t], gets rewards[t].
    T = args.rollout
    frames = torch.zeros((T, N, 3 * args.frames, args.resolution, args.resolution), dtype=torch.uint8)
    actions = torch.zeros((T, N), dtype=torch.long)
    logprobs, values, rewards = (torch.zeros((T, N)) for _ in range(3))
    terminated, truncated, restarted = (torch.zeros((T, N), dtype=torch.bool) for _ in range(3))

    stack = FrameStack(args.frames)
    obs, _ = envs.reset(seed=args.seed)
    frames_now = stack.reset(obs)
    restart_now = torch.zeros(N, dtype=torch.bool)  # this step is a next-step autoreset step
    episode_return = np.zeros(N)
    curve = []  # (env steps, mean return of the episodes that ended in this rollout)
    rollouts = []  # (env steps, mean reward per step of this rollout x max_steps)
    steps_per_update = T * N * args.action_repeat  # at most: blocks end early at episode ends
    updates = args.steps // steps_per_update
    env_steps = 0
    progress = tqdm(range(updates), desc="PPO cartpole", unit="update")
    for _ in progress:
        ended = []
        rollout_reward, rollout_steps = 0.0, 0
        for t in range(T):
            with torch.no_grad():
                distribution, value = agent(frames_now)
                action = distribution.sample()
            frames[t], actions[t], logprobs[t], values[t] = frames_now, action, distribution.log_prob(action), value
            restarted[t] = restart_now
            # A next-step autoreset is one step of its own (actions ignored, reward 0, first frame).
            repeat = 1 if bool(restart_now.any()) else args.action_repeat
            obs, reward, term, trunc, taken = act(envs, action.numpy(), repeat)
            env_steps += taken * N
            rollout_reward, rollout_steps = rollout_reward + float(reward.sum()), rollout_steps + taken * N
            rewards[t] = torch.from_numpy(reward) * reward_scale
            terminated[t], truncated[t] = torch.from_numpy(term), torch.from_numpy(trunc)
            episode_return += reward
            done = term | trunc
            ended += episode_return[done].tolist()
            episode_return[done] = 0.0
            frames_now = stack.push(obs, restart_now)
            restart_now = torch.from_numpy(done)

        # GAE. A truncated episode is bootstrapped from its final frame (the next frames);
        # advantages do not flow across an episode's end; autoreset steps get no loss.
        with torch.no_grad():
            next_value = agent(frames_now)[1]
            advantages = torch.zeros((T, N))
            last = torch.zeros(N)
            for t in reversed(range(T)):
                following = next_value if t == T - 1 else values[t + 1]
                delta = rewards[t] + args.gamma * following * ~terminated[t] - values[t]
                last = delta + args.gamma * args.gae_lambda * ~(terminated[t] | truncated[t]) * last
                advantages[t] = last
            returns = advantages + values
        valid = ~restarted.reshape(-1)
        b_frames = frames.reshape(T * N, *frames.shape[2:])[valid]
        b_actions, b_logprobs = actions.reshape(-1)[valid], logprobs.reshape(-1)[valid]
        b_advantages, b_returns = advantages.reshape(-1)[valid], returns.reshape(-1)[valid]

        size = len(b_actions)
        minibatch = size // args.minibatches
        for _ in range(args.epochs):
            order = torch.randperm(size)
            for start in range(0, size - minibatch + 1, minibatch):
                index = order[start:start + minibatch]
                distribution, value = agent(b_frames[index])
                ratio = (distribution.log_prob(b_actions[index]) - b_logprobs[index]).exp()
                advantage = b_advantages[index]
                advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
                policy_loss = torch.max(-advantage * ratio,
                                        -advantage * ratio.clamp(1 - args.clip, 1 + args.clip)).mean()
                value_loss = 0.5 * (value - b_returns[index]).pow(2).mean()
                loss = policy_loss + args.vf_coef * value_loss - args.ent_coef * distribution.entropy().mean()
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
                optimizer.step()
        rollouts.append((env_steps, rollout_reward / rollout_steps * args.max_steps))
        progress.set_postfix_str(f"rollout reward per step x {args.max_steps}: {rollouts[-1][1]:.1f}")
        if ended:
            curve.append((env_steps, float(np.mean(ended))))
            tqdm.write(f"steps {curve[-1][0]:>8}: episode return {curve[-1][1]:7.1f}")

    train_seconds = time.perf_counter() - started
    trained_returns, trained_actions = evaluate(envs, agent, args, args.seed + 1, "trained")
    envs.close()
    wall = time.perf_counter() - started
    usage = resource.getrusage(resource.RUSAGE_SELF)
    cpu = usage.ru_utime + usage.ru_stime - cpu_started.ru_utime - cpu_started.ru_stime
    print(f"trained policy: return {trained_returns.mean():.1f} +- {trained_returns.std():.1f} "
          f"(random {random_returns.mean():.1f}, no force {no_force.mean():.1f}); greedy action shares "
          f"{np.round(trained_actions, 3).tolist()}; {wall:.0f} s wall, {cpu:.0f} s CPU, "
          f"load average {os.getloadavg()[0]:.1f}")

    if not curve:
        print(f"no training episode ended in {env_steps} steps (one episode of every world takes "
              f"{args.max_steps * N}): curve.png shows the rollouts' reward per step x {args.max_steps}")
    plot(curve, rollouts, {"random policy": random_returns.mean(), "no force": no_force.mean(),
                 "trained policy (greedy)": trained_returns.mean()}, args)
    result = {"random_return_mean": float(random_returns.mean()), "random_return_std": float(random_returns.std()),
              "random_each_step_return_mean": float(random_each_step.mean()),
              "no_force_return_mean": float(no_force.mean()),
              "trained_greedy_action_shares": trained_actions.tolist(),
              "trained_return_mean": float(trained_returns.mean()),
              "trained_return_std": float(trained_returns.std()), "episodes_per_evaluation": N,
              "curve": curve, "rollout_curve": rollouts,
              "rollout_curve_is": f"(env steps, mean reward per step of the update's rollout x {args.max_steps})",
              "train_seconds": train_seconds, "wall_seconds": wall, "cpu_seconds": cpu,
              "load_average_1min_at_end": os.getloadavg()[0], "cpu_count": os.cpu_count(), "args": vars(args)}
    with open(os.path.join(args.out, "result.json"), "w") as f:
        json.dump(result, f, indent=1)
    print(f"wrote {os.path.join(args.out, 'curve.png')} and result.json")


if __name__ == "__main__":
    main()
