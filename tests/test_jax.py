"""The JAX front end (marl_render/wrappers/jax.py): zero-copy both ways, the step boundary,
action checks that leave the state unchanged, ownership of returned arrays, random-policy
rollouts, both import orders of jax and the GL context, and the policy-gradient example."""
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402

from marl_render.envs import list_envs, make_env, make_jax_env  # noqa: E402
from marl_render.wrappers.jax import XLA_CPU_ALIGNMENT, JaxEnv, to_jax, to_torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
W, RES = 3, 16


def pointer(array) -> int:
    return array.unsafe_buffer_pointer()


def assert_state_equal(a: dict, b: dict):
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def recording(env: JaxEnv) -> list:
    """Makes env.core.step / reset append what the core returned (torch) to the list returned."""
    calls = []
    for method in ("step", "reset"):
        original = getattr(env.core, method)

        def record(*args, _original=original, **kwargs):
            calls.append(_original(*args, **kwargs))
            return calls[-1]

        setattr(env.core, method, record)
    return calls


@pytest.fixture
def cartpole():
    env = make_jax_env("cartpole", num_worlds=W, resolution=RES, seed=0)
    yield env
    env.close()


@pytest.fixture
def spread():
    env = make_jax_env("spread", num_worlds=W, resolution=RES, seed=0, continuous=True, state_obs=True, depth=True)
    yield env
    env.close()


# ---------------------------------------------------------------------- DLPack, both ways
@pytest.mark.parametrize("dtype", [torch.uint8, torch.bool, torch.int32, torch.float32])
def test_to_jax_shares_the_tensors_memory(dtype):
    tensor = torch.zeros(4, 5, 3, dtype=dtype)
    array = to_jax(tensor)
    assert pointer(array) == tensor.data_ptr()
    assert array.shape == (4, 5, 3) and array.dtype == np.dtype(str(dtype).removeprefix("torch."))
    tensor[1, 2, 0] = 1  # a write to the tensor shows through: same memory
    assert bool(array[1, 2, 0]) and int(jnp.count_nonzero(array)) == 1


def test_to_jax_copies_what_xla_cannot_alias_and_keeps_the_values():
    base = torch.arange(200, dtype=torch.uint8)
    misaligned = base[1:129]  # contiguous, 1 byte past a 64-byte boundary
    assert misaligned.data_ptr() % XLA_CPU_ALIGNMENT == 1
    array = to_jax(misaligned)
    assert pointer(array) % XLA_CPU_ALIGNMENT == 0 and pointer(array) != misaligned.data_ptr()
    np.testing.assert_array_equal(np.asarray(array), np.arange(1, 129))
    strided = torch.arange(24, dtype=torch.float32).reshape(4, 6)[:, :3]  # XLA refuses these strides
    np.testing.assert_array_equal(np.asarray(to_jax(strided)), strided.numpy())


def test_to_torch_shares_the_arrays_memory():
    array = jnp.arange(6, dtype=jnp.int32).reshape(2, 3)
    tensor = to_torch("actions", array)
    assert tensor.data_ptr() == pointer(array)
    assert tensor.dtype == torch.int32 and tensor.tolist() == [[0, 1, 2], [3, 4, 5]]
    plain = np.zeros(3)
    assert to_torch("actions", plain) is plain  # non-JAX values go to the core's checks as they are


# ---------------------------------------------------------------------- the front end
def test_make_jax_env_mirrors_the_core(cartpole):
    assert isinstance(cartpole, JaxEnv)
    assert (cartpole.num_worlds, cartpole.num_agents, cartpole.num_actions, cartpole.resolution) == (W, 1, 5, (16, 16))
    assert cartpole.obs_keys == ("pixels", "action_mask")
    core = make_env("cartpole", num_worlds=W, resolution=RES, seed=0)
    try:
        obs = cartpole.reset(seed=7)
        expected = core.reset(seed=7)
        assert list(obs) == list(expected)  # the same keys in the same order
        for key in obs:
            np.testing.assert_array_equal(np.asarray(obs[key]), expected[key].numpy())
        actions = jnp.array([[0], [2], [4]])
        got = cartpole.step(actions)
        want = core.step(torch.tensor([[0], [2], [4]]))
        np.testing.assert_array_equal(np.asarray(got[0]["pixels"]), want[0]["pixels"].numpy())
        for g, w in zip(got[1:4], want[1:4], strict=True):
            np.testing.assert_array_equal(np.asarray(g), w.numpy())
        assert list(got[4]) == list(want[4]) == ["step_count", "done_worlds"]
        np.testing.assert_array_equal(np.asarray(got[4]["step_count"]), [1, 1, 1])
    finally:
        core.close()


@pytest.mark.parametrize("env_name", ["cartpole", "spread"])
def test_observations_and_results_reach_jax_without_a_copy(env_name, request):
    env = request.getfixturevalue(env_name)
    calls = recording(env)
    obs = env.reset(seed=0)
    for key, array in obs.items():
        assert pointer(array) == calls[-1][key].data_ptr(), f"reset obs[{key!r}] was copied"
    actions = (jnp.zeros((W, env.num_agents, env.action_dim), jnp.float32) if env.continuous
               else jnp.zeros((W, env.num_agents), jnp.int32))
    got = env.step(actions)
    core_obs, core_reward, core_terminated, core_truncated, core_info = calls[-1]
    assert list(got[0]) == list(env.obs_keys)
    for key, array in got[0].items():
        assert pointer(array) == core_obs[key].data_ptr(), f"obs[{key!r}] was copied"
    for name, array, tensor in zip(("reward", "terminated", "truncated"), got[1:4],
                                   (core_reward, core_terminated, core_truncated), strict=True):
        assert pointer(array) == tensor.data_ptr(), f"{name} was copied"
    for key, array in got[4].items():
        if core_info[key].element_size() <= 4:  # 64-bit entries are converted by JAX (x64 off)
            assert pointer(array) == core_info[key].data_ptr(), f"info[{key!r}] was copied"


def test_64_bit_info_follows_jax_dtype_rules(spread):
    spread.reset(seed=0)
    info = spread.step(jnp.zeros((W, spread.num_agents, 2)))[4]
    assert not jax.config.jax_enable_x64
    assert info["step_count"].dtype == jnp.int32 and info["collisions"].dtype == jnp.int32
    np.testing.assert_array_equal(np.asarray(info["step_count"]), [1, 1, 1])


@pytest.mark.parametrize("name", list_envs())
def test_returned_arrays_stay_unchanged_by_later_steps(name):
    """The core hands out fresh tensors per call: aliasing them into JAX is safe."""
    env = make_jax_env(name, num_worlds=2, resolution=24, seed=1, state_obs=True, autoreset=True, max_steps=2)
    try:
        kept = [env.reset(seed=1)]
        key = jax.random.key(1)
        for _ in range(4):
            key, sub = jax.random.split(key)
            actions = jax.random.randint(sub, (2, env.num_agents), 0, env.num_actions)
            obs, reward, terminated, truncated, info = env.step(actions)
            kept.append({**obs, "reward": reward, "terminated": terminated, "truncated": truncated,
                         **{f"info.{k}": v for k, v in info.items()}})
        copies = [{k: np.array(v) for k, v in arrays.items()} for arrays in kept]
        for _ in range(2):
            env.step(jnp.zeros((2, env.num_agents), jnp.int32))
        for arrays, snapshot in zip(kept, copies, strict=True):
            for key_name, array in arrays.items():
                np.testing.assert_array_equal(np.asarray(array), snapshot[key_name], err_msg=key_name)
        pixels = [snapshot["pixels"] for snapshot in copies]
        assert any(not np.array_equal(a, b) for a, b in itertools.pairwise(pixels))  # the check can see a change
    finally:
        env.close()


# ---------------------------------------------------------------------- action checks
def _bad_discrete():
    want = rf"actions must be an integer tensor of shape \[{W}, 1\] \(worlds, agents\) with values in \[0, 5\)"
    deleted = jnp.zeros((W, 1), jnp.int32)
    deleted.delete()
    return [
        ("wrong shape", jnp.zeros((W, 2), jnp.int32), ValueError, rf"{want}, got shape \[{W}, 2\]"),
        ("no agent dim", jnp.zeros((W,), jnp.int32), ValueError, rf"{want}, got shape \[{W}\]"),
        ("float dtype", jnp.zeros((W, 1), jnp.float32), TypeError, rf"{want}, got tensor .*dtype torch.float32"),
        ("bool dtype", jnp.zeros((W, 1), bool), TypeError, rf"{want}, got tensor .*dtype torch.bool"),
        ("too big", jnp.full((W, 1), 5), ValueError, rf"{want}, got values in \[5, 5\]"),
        ("negative", jnp.array([[0], [-1], [2]]), ValueError, rf"{want}, got values in \[-1, 2\]"),
        ("int4 (no DLPack code)", jnp.zeros((W, 1), jnp.int4), TypeError,
         r"actions must be a jax.Array of a dtype that DLPack carries .*dtype int4"),
        ("deleted", deleted, ValueError, r"actions must be a live jax.Array, got a deleted one"),
    ]


def _bad_continuous():
    want = rf"actions must be a float tensor of shape \[{W}, 3, 2\] \(worlds, agents, action_dim\) in \[-1, 1\]"
    return [
        ("wrong shape", jnp.zeros((W, 3)), ValueError, rf"{want}, got shape \[{W}, 3\]"),
        ("int dtype", jnp.zeros((W, 3, 2), jnp.int32), TypeError, rf"{want}, got tensor .*dtype torch.int32"),
        ("NaN", jnp.zeros((W, 3, 2)).at[1, 2, 0].set(jnp.nan), ValueError, rf"{want}, got non-finite values"),
        ("Inf", jnp.zeros((W, 3, 2)).at[0, 0, 1].set(-jnp.inf), ValueError, rf"{want}, got non-finite values"),
        ("out of range", jnp.full((W, 3, 2), 1.5), ValueError, rf"{want}, got values in \[1.5, 1.5\]"),
    ]


@pytest.mark.parametrize("case", _bad_discrete(), ids=lambda case: case[0])
def test_bad_discrete_jax_actions_raise_and_change_nothing(case, cartpole):
    _, actions, error, message = case
    cartpole.reset(seed=0)
    cartpole.step(jnp.full((W, 1), 4))
    before = cartpole.get_state()
    with pytest.raises(error, match=message):
        cartpole.step(actions)
    assert_state_equal(before, cartpole.get_state())
    np.testing.assert_array_equal(np.asarray(cartpole.step(jnp.ones((W, 1), jnp.int32))[4]["step_count"]), [2, 2, 2])


@pytest.mark.parametrize("case", _bad_continuous(), ids=lambda case: case[0])
def test_bad_continuous_jax_actions_raise_and_change_nothing(case, spread):
    _, actions, error, message = case
    spread.reset(seed=0)
    before = spread.get_state()
    with pytest.raises(error, match=message):
        spread.step(actions)
    assert_state_equal(before, spread.get_state())


def test_stepping_inside_jit_raises_before_anything_changes(cartpole):
    cartpole.reset(seed=0)
    before = cartpole.get_state()
    with pytest.raises(TypeError, match=r"actions must be a concrete jax.Array, got a traced value .*int32\[3,1\].*"
                                        r"outside jax.jit"):
        jax.jit(cartpole.step)(jnp.zeros((W, 1), jnp.int32))
    assert_state_equal(before, cartpole.get_state())


def test_reset_worlds_takes_a_jax_mask(cartpole):
    cartpole.reset(seed=0)
    cartpole.step(jnp.zeros((W, 1), jnp.int32))
    obs = cartpole.reset_worlds(jnp.array([False, True, False]))
    assert obs["pixels"].shape == (W, 1, 16, 16, 3)
    assert cartpole.get_state()["step_count"].tolist() == [1, 0, 1]
    with pytest.raises(TypeError, match=r"mask must have dtype torch.bool, got torch.int32"):
        cartpole.reset_worlds(jnp.array([0, 1, 0]))
    assert cartpole.get_state()["step_count"].tolist() == [1, 0, 1]


def test_wrapping_something_else_raises():
    with pytest.raises(TypeError, match=r"core must be a marl_render BatchedEnv .*got 'cartpole'"):
        JaxEnv("cartpole")


def test_closed_env_raises(cartpole):
    cartpole.close()
    assert cartpole.closed
    with pytest.raises(RuntimeError, match="closed"):
        cartpole.reset()


# ---------------------------------------------------------------------- rollouts
def test_random_policy_rollout_discrete_with_autoreset():
    env = make_jax_env("cartpole", num_worlds=W, resolution=RES, seed=3, max_steps=3, autoreset=True)
    policy = jax.jit(lambda key, pixels: jax.random.randint(key, pixels.shape[:2], 0, env.num_actions))
    try:
        obs = env.reset(seed=3)
        key = jax.random.key(0)
        counts = []
        for _ in range(5):
            key, sub = jax.random.split(key)
            obs, reward, terminated, truncated, info = env.step(policy(sub, obs["pixels"]))
            assert (obs["pixels"].shape, obs["pixels"].dtype) == ((W, 1, 16, 16, 3), jnp.uint8)
            assert (obs["action_mask"].shape, obs["action_mask"].dtype) == ((W, 1, 5), jnp.bool_)
            assert (reward.shape, reward.dtype) == ((W, 1), jnp.float32)
            assert (terminated.shape, terminated.dtype) == ((W, 1), jnp.bool_)
            assert (truncated.shape, truncated.dtype) == ((W, 1), jnp.bool_)
            assert (info["step_count"].shape, info["step_count"].dtype) == ((W,), jnp.int32)
            assert (info["done_worlds"].shape, info["done_worlds"].dtype) == ((W,), jnp.bool_)
            assert all(isinstance(a, jax.Array) for a in (*obs.values(), reward, terminated, truncated))
            assert float(reward.min()) >= 0 and float(reward.max()) <= 1
            counts.append(np.asarray(info["step_count"]).tolist())
            np.testing.assert_array_equal(np.asarray(truncated[:, 0]), np.asarray(info["step_count"]) == 3)
        assert counts == [[1] * W, [2] * W, [3] * W, [1] * W, [2] * W]  # autoreset after max_steps
    finally:
        env.close()


def test_random_policy_rollout_continuous_multi_agent(spread):
    obs = spread.reset(seed=0)
    key = jax.random.key(1)
    for step in range(1, 4):
        key, sub = jax.random.split(key)
        actions = jax.random.uniform(sub, (W, 3, 2), minval=-1.0, maxval=1.0)
        obs, reward, terminated, truncated, info = spread.step(actions)
        assert (obs["pixels"].shape, obs["pixels"].dtype) == ((W, 3, 16, 16, 3), jnp.uint8)
        assert (obs["depth"].shape, obs["depth"].dtype) == ((W, 3, 16, 16), jnp.float32)
        assert (obs["state"].shape, obs["state"].dtype) == ((W, 3, spread.state_dim), jnp.float32)
        assert (reward.shape, reward.dtype) == ((W, 3), jnp.float32)
        assert (terminated.dtype, truncated.dtype) == (jnp.bool_, jnp.bool_) and terminated.shape == (W, 3)
        assert (info["coverage"].shape, info["coverage"].dtype) == ((W,), jnp.float32)
        np.testing.assert_array_equal(np.asarray(info["step_count"]), [step] * W)
        assert float(obs["depth"].min()) > 0 and float(obs["depth"].max()) <= spread.core.far


# ---------------------------------------------------------------------- process-level checks
ORDER_SCRIPT = """
import json, sys
jax_first = sys.argv[1] == "jax_first"
if jax_first:
    import jax, jax.numpy as jnp
import marl_render, marl_render.wrappers
from marl_render.envs import make_env
env = make_env("cartpole", num_worlds=2, resolution=24, seed=0)
first = env.reset(seed=0)["pixels"]
suite = {"jax_after_the_suite": "jax" in sys.modules}  # gl_first: importing and using the suite imports no jax
from marl_render.envs import make_jax_env
suite["jax_after_make_jax_env"] = "jax" in sys.modules
if not jax_first:
    import jax, jax.numpy as jnp
# a convolution makes XLA compile real code with its LLVM, then GL draws again
image = jnp.from_dlpack(first).astype(jnp.float32).reshape(2, 24, 24, 3)
kernel = jnp.ones((3, 3, 3, 4), jnp.float32)
conv = jax.jit(lambda x: jax.lax.conv_general_dilated(x, kernel, (1, 1), "SAME",
                                                       dimension_numbers=("NHWC", "HWIO", "NHWC")).sum())
total = float(conv(image))
second = env.step(env.random_actions(__import__("torch").Generator().manual_seed(0)))[0]["pixels"]
print(json.dumps({"conv": total, "first": int(first.sum()), "second": int(second.sum()), "suite": suite}))
"""


@pytest.fixture(scope="module")
def import_orders() -> dict:
    """ORDER_SCRIPT's output in a fresh process for each order: {order: its JSON}."""
    results = {}
    for order in ("jax_first", "gl_first"):
        done = subprocess.run([sys.executable, "-c", ORDER_SCRIPT, order], capture_output=True, text=True,
                              timeout=240, env=dict(os.environ, PYTHONWARNINGS="ignore"))
        assert done.returncode == 0, f"{order}: rc {done.returncode}\n{done.stderr[-3000:]}"
        results[order] = json.loads(done.stdout.strip().splitlines()[-1])
    return results


def test_jax_and_gl_work_in_either_import_order(import_orders):
    results = {order: {k: v for k, v in result.items() if k != "suite"} for order, result in import_orders.items()}
    assert results["jax_first"] == results["gl_first"]
    assert results["gl_first"]["first"] > 0 and results["gl_first"]["conv"] > 0


def test_importing_the_suite_does_not_import_jax(import_orders):
    # The gl_first child (a fresh process) imported marl_render, its envs and wrappers and stepped an env.
    assert import_orders["gl_first"]["suite"] == {"jax_after_the_suite": False, "jax_after_make_jax_env": True}


def test_policy_gradient_example_runs_and_writes_its_results(tmp_path):
    done = subprocess.run([sys.executable, str(ROOT / "examples" / "jax_policy_gradient.py"), "--out", tmp_path,
                           "--worlds", "4", "--resolution", "12", "--steps", "40", "--horizon", "10"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path,
                          env=dict(os.environ, PYTHONWARNINGS="ignore"))
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["worlds"] == 4 and result["resolution"] == 12 and result["horizon"] == 10
    assert len(result["mean_return"]) == 4  # 40 steps / 10 per episode
    assert all(0 <= r <= 10 for r in result["mean_return"])  # cartpole rewards are in [0, 1]
    from PIL import Image
    with Image.open(tmp_path / "curve.png") as image:
        assert image.format == "PNG" and image.size[0] > 100


SHARDED_SCRIPT = """
import json
import jax, jax.numpy as jnp, numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from marl_render.envs import make_jax_env
mesh = Mesh(np.array(jax.devices()), ("worlds",))
results = {"devices": len(jax.devices())}
for continuous in (False, True):
    env, twin = (make_jax_env("spread", num_worlds=2, resolution=16, seed=0, continuous=continuous) for _ in range(2))
    env.reset(seed=0), twin.reset(seed=0)
    plain = jnp.full((2, 3, 2), 0.5) if continuous else jnp.arange(6).reshape(2, 3) % 5
    sharded = jax.device_put(plain, NamedSharding(mesh, PartitionSpec("worlds")))
    got, want = env.step(sharded), twin.step(plain)
    results[str(continuous)] = [len(sharded.sharding.device_set), bool((got[0]["pixels"] == want[0]["pixels"]).all()),
                                bool((got[1] == want[1]).all())]
print(json.dumps(results))
"""


def test_actions_sharded_over_two_devices_are_gathered():
    """Actions sharded over 2 (forced host) devices step like the same unsharded actions."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", PYTHONWARNINGS="ignore")
    done = subprocess.run([sys.executable, "-c", SHARDED_SCRIPT], capture_output=True, text=True, timeout=240,
                          env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads(done.stdout.strip().splitlines()[-1])
    assert results == {"devices": 2, "False": [2, True, True], "True": [2, True, True]}
