"""REINFORCE in JAX on cartpole from pixels, through make_jax_env (needs the jax extra).

The policy (a small CNN on the frame and its difference from the previous one, which carries
the velocities) is jitted; the env step renders with OpenGL outside jit, and its pixels reach
JAX without a copy (DLPack). Each iteration plays one episode of --horizon steps in every world,
then takes one Adam step on -mean(log pi(a|x) * normalised return-to-go). Writes OUT/result.json
(the mean episode return per iteration) and OUT/curve.png.

    python examples/jax_policy_gradient.py [--worlds 16] [--resolution 32] [--steps 6000] [--out out/jax_pg]
"""
import argparse
import json
import os
import time


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help keeps the docstring's layout and shows every option's default."""


parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=HelpFormatter)
parser.add_argument("--out", default="out/jax_pg", help="folder for result.json and curve.png")
parser.add_argument("--worlds", type=int, default=16, help="worlds played side by side")
parser.add_argument("--resolution", type=int, default=32, help="pixels per side")
parser.add_argument("--steps", type=int, default=6000, help="env steps per world in all")
parser.add_argument("--horizon", type=int, default=100, help="steps per episode")
parser.add_argument("--seed", type=int, default=0, help="seed of the env and the policy")
args = parser.parse_args()  # before importing jax: --help works without the extra

from marl_render.extras import command_needs_extra  # noqa: E402

with command_needs_extra("jax", "examples/jax_policy_gradient.py"):
    import jax
    import jax.numpy as jnp
    from jax.example_libraries import optimizers, stax

    from marl_render.envs import make_jax_env
with command_needs_extra("plots", "examples/jax_policy_gradient.py"):  # before training, not after it
    from matplotlib.figure import Figure  # no pyplot: no GUI backend is chosen

GAMMA = 0.98
env = make_jax_env("cartpole", num_worlds=args.worlds, resolution=args.resolution, max_steps=args.horizon,
                   seed=args.seed)
init_net, net = stax.serial(stax.Conv(16, (4, 4), (2, 2)), stax.Relu, stax.Conv(16, (3, 3), (2, 2)), stax.Relu,
                            stax.Flatten, stax.Dense(64), stax.Relu, stax.Dense(env.num_actions))
opt_init, opt_update, get_params = optimizers.adam(1e-3)


def features(frame, previous):  # uint8 [..., H, W, 3] x 2 -> float [..., H, W, 6]
    frame, previous = frame.astype(jnp.float32) / 255, previous.astype(jnp.float32) / 255
    return jnp.concatenate([frame, frame - previous], axis=-1)


@jax.jit
def act(params, key, frame, previous):  # [W, 1, H, W, 3] -> actions [W, 1]
    logits = net(params, features(frame[:, 0], previous[:, 0]))
    return jax.random.categorical(key, logits)[:, None]


def loss(params, frames, previous, actions, rewards):  # [T, W, ...]
    def discount(later, reward):
        return reward + GAMMA * later, reward + GAMMA * later
    _, returns = jax.lax.scan(discount, jnp.zeros(rewards.shape[1]), rewards, reverse=True)
    advantage = (returns - returns.mean()) / (returns.std() + 1e-6)
    logits = net(params, features(frames, previous).reshape(-1, *frames.shape[2:-1], 6))
    log_pi = jax.nn.log_softmax(logits)[jnp.arange(actions.size), actions.reshape(-1)]
    return -(log_pi * advantage.reshape(-1)).mean()


@jax.jit
def update(i, state, frames, previous, actions, rewards):
    grads = jax.grad(loss)(get_params(state), frames, previous, actions, rewards)
    return opt_update(i, grads, state)


key = jax.random.key(args.seed)
key, init_key = jax.random.split(key)
state = opt_init(init_net(init_key, (-1, args.resolution, args.resolution, 6))[1])
returns, start = [], time.perf_counter()
for iteration in range(max(1, args.steps // args.horizon)):
    obs = env.reset(seed=args.seed + iteration)
    previous, frames, before, actions, rewards = obs["pixels"], [], [], [], []
    for _ in range(args.horizon):  # the env steps in Python: the renderer runs outside jit
        key, sub = jax.random.split(key)
        action = act(get_params(state), sub, obs["pixels"], previous)
        frames.append(obs["pixels"][:, 0]), before.append(previous[:, 0]), actions.append(action[:, 0])
        previous = obs["pixels"]
        obs, reward, terminated, truncated, info = env.step(action)
        rewards.append(reward[:, 0])
    rewards = jnp.stack(rewards)
    state = update(iteration, state, jnp.stack(frames), jnp.stack(before), jnp.stack(actions), rewards)
    returns.append(float(rewards.sum(0).mean()))
    print(f"iteration {iteration}: mean return {returns[-1]:.2f} / {args.horizon} "
          f"({time.perf_counter() - start:.0f} s)", flush=True)
env.close()

os.makedirs(args.out, exist_ok=True)
with open(os.path.join(args.out, "result.json"), "w") as f:
    json.dump({"env": "cartpole", "worlds": args.worlds, "resolution": args.resolution, "horizon": args.horizon,
               "seconds": time.perf_counter() - start, "mean_return": returns}, f, indent=1)

figure = Figure(figsize=(5, 3), dpi=80, layout="tight")
figure.add_subplot(xlabel="iteration (one episode per world)", ylabel=f"mean return (max {args.horizon})").plot(returns)
figure.savefig(os.path.join(args.out, "curve.png"))
print(f"wrote {args.out}/result.json and curve.png")
