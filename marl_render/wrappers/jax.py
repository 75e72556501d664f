"""JAX front end: the batched core (envs/core.py) with JAX arrays in and out, without copies.

    import jax
    from marl_render.envs import make_jax_env
    env = make_jax_env("cartpole", num_worlds=64, resolution=32)
    obs = env.reset(seed=0)                      # obs["pixels"]: jax uint8 [W, A, H, Wpx, 3]
    actions = jax.random.randint(jax.random.key(0), (64, 1), 0, env.num_actions)
    obs, reward, terminated, truncated, info = env.step(actions)

``step``, ``reset`` and ``reset_worlds`` mirror the core's: the same arguments, the same
returns (an obs dict, reward, terminated, truncated, info), the same keys, shapes and
semantics (see envs/core.py), with every tensor turned into a ``jax.Array``.

The step boundary: the renderer (OpenGL through Panda3D) and the env physics (torch) run
outside JAX, so observations are produced outside ``jax.jit``. A policy may be jitted (it
reads the JAX observations and returns JAX actions), the env step may not: call ``step``
from Python, not inside ``jit``, ``vmap`` or ``lax.scan``. A traced ``actions`` raises
TypeError before anything changes.

Zero-copy: every tensor the core returns reaches JAX through DLPack, so the JAX array
reads the tensor's memory. This is safe because the core hands out fresh tensors that the
caller owns (nothing writes to them after the call returns). XLA's CPU client aliases a
buffer only if it is 64-byte aligned (jaxlib 0.10.2 copies at 16- and 32-byte offsets;
with ``copy=False`` it says "not aligned to 64 bytes") and densely strided (it refuses
strided slices). torch's CPU allocator aligns every
allocation to 64 bytes and the core returns contiguous tensors, so pixels, depth, state,
action_mask, reward, terminated, truncated and 32-bit info entries arrive without a copy;
``to_jax`` copies any other tensor once into a fresh one. 64-bit tensors (``info
["step_count"]`` and some envs' info counters, all [W]) follow JAX's dtype rules: unless
``jax_enable_x64`` is on, JAX converts them to 32 bits, which is a copy.

Actions (and ``reset_worlds`` masks) go the other way, JAX -> torch by DLPack, also
without a copy, and are then checked by the core's ``check_actions``: the same
TypeError / ValueError naming ``actions``, the expected and the given, and a rejected
call changes nothing. Actions sharded over several devices (``jax.sharding``) are
gathered into host memory first, a copy. numpy arrays, lists and torch tensors are passed
to the core as they are.

GL and a second LLVM: Mesa's llvmpipe links its own LLVM and jaxlib bundles XLA's. Both
import orders (jax before the GL context, or after it, then jitting and rendering in
turn) run correctly here: tests/test_jax.py checks both in fresh processes.

Device: a CPU core (``device="cpu"``, the default) with JAX's CPU backend. A CUDA core
needs a JAX with a GPU backend; without one ``make_jax_env`` raises ValueError.
"""
from __future__ import annotations

import numpy as np
import torch

from marl_render.envs.registry import make_env
from marl_render.extras import needs_extra
from marl_render.wrappers.common import check_core, closed_on_error, refuse_num_processes

with needs_extra("jax", "make_jax_env"):
    import jax

XLA_CPU_ALIGNMENT = 64  # bytes: XLA's CPU client copies DLPack buffers aligned less than this

# Descriptive attributes copied from the core (see BatchedEnv's docstring).
CORE_ATTRIBUTES = ("name", "num_worlds", "num_agents", "agent_names", "groups", "resolution", "continuous",
                   "num_actions", "action_dim", "action_meanings", "obs_keys", "state_dim", "max_steps", "dt",
                   "autoreset", "device")


def make_jax_env(name: str, num_worlds: int = 1, **kwargs) -> JaxEnv:
    """A JAX front end over the batched core of environment `name` with `num_worlds` worlds.

    kwargs go to ``marl_render.envs.make_env`` (resolution, num_agents, max_steps, continuous,
    state_obs, depth, seed, autoreset, device and the env's own arguments)."""
    refuse_num_processes("make_jax_env", kwargs)
    with closed_on_error(make_env(name, num_worlds=num_worlds, **kwargs)) as core:
        return JaxEnv(core)


def to_jax(tensor: torch.Tensor) -> jax.Array:
    """`tensor` as a jax.Array sharing its memory (DLPack); a tensor that XLA cannot alias
    (not contiguous, or on CPU at an address not aligned to XLA_CPU_ALIGNMENT) is copied once
    into a fresh, aligned one first."""
    tensor = tensor.detach()
    misaligned = tensor.device.type == "cpu" and tensor.data_ptr() % XLA_CPU_ALIGNMENT != 0
    if misaligned or not tensor.is_contiguous():
        tensor = tensor.clone(memory_format=torch.contiguous_format)  # torch aligns allocations to 64 bytes
    return jax.dlpack.from_dlpack(tensor)


def to_torch(name: str, value):
    """A concrete jax.Array as a torch tensor sharing its memory (DLPack); other values are
    returned unchanged for the core to check. Raises TypeError naming `name` for traced
    arrays (inside jit) and dtypes DLPack cannot carry."""
    if isinstance(value, jax.core.Tracer):
        raise TypeError(f"{name} must be a concrete jax.Array, got a traced value ({value.aval}): the env step "
                        f"renders with OpenGL outside JAX, so call it outside jax.jit / vmap / lax.scan "
                        f"(jit the policy, not the step)")
    if not isinstance(value, jax.Array):
        return value
    if value.is_deleted():
        raise ValueError(f"{name} must be a live jax.Array, got a deleted one (donated or deleted)")
    if len(value.sharding.device_set) > 1:  # DLPack exports one device's buffer: gather the shards (a copy)
        if not value.is_fully_addressable:
            raise ValueError(f"{name} must be addressable from this process, got a jax.Array sharded over "
                             f"devices of other processes ({value.sharding}); gather it first")
        return torch.from_numpy(np.array(value))
    try:
        return torch.from_dlpack(value)
    except Exception as exc:  # XLA raises its own error type for dtypes without a DLPack code
        raise TypeError(f"{name} must be a jax.Array of a dtype that DLPack carries (bool, int, uint, float), "
                        f"got shape {tuple(value.shape)}, dtype {value.dtype}") from exc


def _dict_to_jax(tensors: dict) -> dict:
    """Keeps the core's key order; nested dicts (same-step autoreset's info["final_obs"]) too."""
    return {key: _dict_to_jax(value) if isinstance(value, dict) else to_jax(value) for key, value in tensors.items()}


class JaxEnv:
    """JAX front end over a BatchedEnv; see the module docstring for the step boundary and
    zero-copy rules.

    ``core`` is the wrapped BatchedEnv (owned: closed by ``close()``). The core's
    descriptive attributes (CORE_ATTRIBUTES: num_worlds, num_agents, num_actions,
    action_dim, obs_keys, ...) are copied onto the front end. ``get_state()`` returns the
    core's state (torch copies), for tests and for saving.
    """

    def __init__(self, core):
        check_core(core, name="core")
        _check_jax_backend(core.device)
        if core.levels is not None and not jax.config.jax_enable_x64:
            # Level ids reach 2**62: JAX's default 32-bit conversion of info["level"] would wrap them.
            raise ValueError("levels= with the JAX front end needs 64-bit JAX (jax.config.update('jax_enable_x64', "
                             "True)): level ids are int64 and JAX would cut info['level'] to 32 bits")
        self.core = core
        for attribute in CORE_ATTRIBUTES:
            setattr(self, attribute, getattr(core, attribute))

    def reset(self, seed: int | None = None) -> dict:
        """Reset every world (see BatchedEnv.reset): obs dict of jax.Arrays."""
        return _dict_to_jax(self.core.reset(seed=seed))

    def reset_worlds(self, mask, seed: int | None = None) -> dict:
        """Reset the worlds where `mask` (bool [W], JAX or torch) is True: obs of all worlds."""
        return _dict_to_jax(self.core.reset_worlds(to_torch("mask", mask), seed=seed))

    def step(self, actions):
        """Advance all worlds one step: (obs, reward, terminated, truncated, info) as jax.Arrays.

        Not traceable: call it outside jax.jit (see the module docstring)."""
        obs, reward, terminated, truncated, info = self.core.step(to_torch("actions", actions))
        return _dict_to_jax(obs), to_jax(reward), to_jax(terminated), to_jax(truncated), _dict_to_jax(info)

    def render_overview(self, resolution=None) -> jax.Array:
        """uint8 [W, H2, W2, 3]: one camera per world that sees the whole arena, for humans."""
        return to_jax(self.core.render_overview(resolution))

    def get_state(self) -> dict:
        """The core's state: copies of its torch tensors and RNG state (BatchedEnv.get_state)."""
        return self.core.get_state()

    def close(self) -> None:
        """Release the core's renderers; safe to call twice."""
        self.core.close()

    @property
    def closed(self) -> bool:
        return self.core.closed

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self):
        return f"JaxEnv({self.core!r})"


def _check_jax_backend(device: torch.device) -> None:
    """A core on CUDA needs JAX's GPU backend to take its tensors by DLPack."""
    if device.type == "cpu":
        return
    try:
        jax.devices("gpu")
    except RuntimeError as exc:
        raise ValueError(f"device {str(device)!r} needs a JAX with a GPU backend (jax[cuda]); this JAX has "
                         f"{[d.platform for d in jax.devices()]}; use device='cpu'") from exc
