"""compile_physics: the task's physics kernel through torch.compile (envs/compiled.py).

Compiling needs a C++ compiler and takes seconds, so one env here compiles; the rest check the
refusals and the fallback without compiling."""
from __future__ import annotations

import re
import shutil

import pytest
import torch

from marl_render.envs import compiled as compiled_kernels
from marl_render.envs import make_env

WORLDS = 16


def cartpole(**kw):
    return make_env("cartpole", num_worlds=WORLDS, resolution=16, seed=0, continuous=True, **kw)


def run(env, steps: int, seed: int = 1):
    """States [steps, W, 4] and rewards [steps, W, 1] of `steps` random steps from a fixed start
    with large angles and rates (the pole swings over and the cart hits the slider stops)."""
    env.reset(seed=0)
    qstate = env.sim.qstate.clone()
    qstate[:, 1] = torch.linspace(-3.0, 3.0, WORLDS, dtype=torch.float64)
    qstate[:, 3] = torch.linspace(-5.0, 5.0, WORLDS, dtype=torch.float64)
    env.set_state({**env.get_state(), "qstate": qstate})
    generator = torch.Generator().manual_seed(seed)
    states, rewards = [], []
    for _ in range(steps):
        _, reward, _, _, _ = env.step(torch.rand(WORLDS, 1, 1, generator=generator) * 2 - 1)
        states.append(env.sim.qstate.clone())
        rewards.append(reward)
    return torch.stack(states), torch.stack(rewards)


@pytest.mark.skipif(not any(shutil.which(c) for c in ("g++", "c++", "clang++")),
                    reason="torch.compile's CPU backend needs a C++ compiler; the fallback is tested below")
def test_compiled_cartpole_follows_the_default_path():
    from torch._dynamo.utils import counters

    graphs = counters["stats"]["unique_graphs"]
    with cartpole(compile_physics=True) as compiled, cartpole() as default:
        assert compiled.physics_compiled and not default.physics_compiled
        states, rewards = run(compiled, 600)
        assert counters["stats"]["unique_graphs"] == graphs + 1  # compiled once, as steps call it (no_grad)
        expected_states, expected_rewards = run(default, 600)
        # inductor's C++ rounds some sin/cos results differently from torch's kernels (the last
        # bit of ~0.1% of them): trajectories stay within 1e-12 (MuJoCo match of the default
        # path: tests/test_cartpole.py), float32 rewards agree.
        assert float((states - expected_states).abs().max()) < 1e-12
        assert torch.allclose(rewards, expected_rewards, rtol=0, atol=1e-6)
        assert float((states[:, :, 0].abs() - 1.8).abs().min()) == 0  # the stops were hit
        again, _ = run(compiled, 600)
        assert torch.equal(again, states)  # deterministic
        assert states.dtype == torch.float64 and states.shape == (600, WORLDS, 4)


def test_a_kernel_that_does_not_compile_leaves_the_default_path(monkeypatch):
    def broken_compile(function, **kwargs):
        def kernel(*args):
            raise RuntimeError("no working C++ compiler found")
        return kernel

    monkeypatch.setattr(torch, "compile", broken_compile)
    monkeypatch.setattr(compiled_kernels, "_COMPILED", {})  # not the kernel another test compiled
    with pytest.warns(RuntimeWarning, match=re.escape("cartpole physics for 16 worlds could not be compiled "
                                                      "(RuntimeError: no working C++ compiler found)")):
        env = cartpole(compile_physics=True)
    with env, cartpole() as default:
        assert not env.physics_compiled
        states, rewards = run(env, 50)
        expected_states, expected_rewards = run(default, 50)
        assert torch.equal(states, expected_states) and torch.equal(rewards, expected_rewards)


@pytest.mark.parametrize(("name", "value", "error", "words"), [
    ("spread", True, ValueError, "compile_physics applies to tasks with a compiled physics kernel; spread has none"),
    ("cartpole", "yes", TypeError, "compile_physics must be a bool, got"),
])
def test_compile_physics_refuses_what_it_cannot_do(name, value, error, words):
    with pytest.raises(error, match=re.escape(words)):
        make_env(name, num_worlds=2, resolution=16, compile_physics=value)
