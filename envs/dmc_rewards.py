"""DeepMind Control Suite's reward functions in torch: ``tolerance`` and the cart-pole balance rewards.

``tolerance`` has the semantics of dm_control.utils.rewards.tolerance (1 inside the bounds,
falling off with the distance to them over a margin, by a chosen sigmoid); the balance
rewards are those of dm_control's cartpole ``balance`` and ``balance_sparse`` tasks.
"""
from __future__ import annotations

import math

from torch import Tensor

from . import array_ops
from .array_ops import TorchOps


def _bad(name: str, expected: str, got) -> ValueError:
    return ValueError(f"{name} must be {expected}, got {got!r}")


def _sigmoid(x, value_at_1: float, sigmoid: str, ops):
    if sigmoid in ("cosine", "linear", "quadratic"):
        if not 0 <= value_at_1 < 1:
            raise _bad("value_at_margin", "in [0, 1)", value_at_1)
    elif not 0 < value_at_1 < 1:
        raise _bad("value_at_margin", "strictly between 0 and 1", value_at_1)
    zero = ops.zeros_like(x)
    if sigmoid == "gaussian":
        scale = math.sqrt(-2.0 * math.log(value_at_1))
        return ops.exp(-0.5 * (x * scale) ** 2)
    if sigmoid == "hyperbolic":
        scale = math.acosh(1.0 / value_at_1)
        return 1.0 / ops.cosh(x * scale)
    if sigmoid == "long_tail":
        scale = math.sqrt(1.0 / value_at_1 - 1.0)
        return 1.0 / ((x * scale) ** 2 + 1.0)
    if sigmoid == "reciprocal":
        scale = 1.0 / value_at_1 - 1.0
        return 1.0 / (ops.abs(x) * scale + 1.0)
    if sigmoid == "cosine":
        sx = x * (math.acos(2.0 * value_at_1 - 1.0) / math.pi)
        return ops.where(ops.abs(sx) < 1, (1.0 + ops.cos(math.pi * sx)) / 2.0, zero)
    if sigmoid == "linear":
        sx = x * (1.0 - value_at_1)
        return ops.where(ops.abs(sx) < 1, 1.0 - sx, zero)
    if sigmoid == "quadratic":
        sx = x * math.sqrt(1.0 - value_at_1)
        return ops.where(ops.abs(sx) < 1, 1.0 - sx * sx, zero)
    if sigmoid == "tanh_squared":
        scale = math.atanh(math.sqrt(1.0 - value_at_1))
        return 1.0 - ops.tanh(x * scale) ** 2
    raise _bad("sigmoid", "a known sigmoid type", sigmoid)


def tolerance(x, bounds=(0.0, 0.0), margin: float = 0.0, sigmoid: str = "gaussian",
              value_at_margin: float = 0.1, ops=TorchOps):
    """1 inside ``bounds``, decaying with the distance to them over ``margin``.

    Same semantics as dm_control.utils.rewards.tolerance: at distance
    ``margin`` from the nearest bound the value is ``value_at_margin``;
    ``margin == 0`` gives a hard 0/1 indicator. Tensors, or the arrays of `ops`
    (envs/array_ops.py).
    """
    lower, upper = bounds
    if lower > upper:
        raise _bad("bounds", "(lower, upper) with lower <= upper", bounds)
    if margin < 0:
        raise _bad("margin", ">= 0", margin)
    in_bounds = (lower <= x) & (x <= upper)
    one = ops.ones_like(x)
    if margin == 0:
        return ops.where(in_bounds, one, ops.zeros_like(x))
    d = ops.where(x < lower, lower - x, x - upper) / margin
    return ops.where(in_bounds, one, _sigmoid(d, value_at_margin, sigmoid, ops))


def dmc_balance_reward(state: Tensor, action: Tensor) -> Tensor:
    """dm_control cartpole Balance._get_reward (smooth), per world [W].

    upright * small_control * small_velocity * centered, with
    upright = (cos(theta) + 1) / 2, centered = (1 + tol(x, margin=2)) / 2,
    small_control = (4 + tol(u, margin=1, value_at_margin=0, quadratic)) / 5,
    small_velocity = (1 + tol(theta_dot, margin=5)) / 2.
    ``action`` is used as given (dm_control reads physics.control(), the
    unclipped ctrl).
    """
    action = action.to(state.dtype)
    ops = array_ops.for_tensors(state, action)
    with ops.quiet():
        return array_ops.to_tensor(balance_reward(ops, array_ops.to_ops(ops, state), array_ops.to_ops(ops, action)))


def balance_reward(ops, state, action):
    """dmc_balance_reward on the arrays of `ops`, `action` of the state's dtype."""
    x, theta, thetadot = state[..., 0], state[..., 1], state[..., 3]
    upright = (ops.cos(theta) + 1.0) / 2.0
    centered = (1.0 + tolerance(x, margin=2.0, ops=ops)) / 2.0
    small_control = (4.0 + tolerance(action, margin=1.0, value_at_margin=0.0, sigmoid="quadratic", ops=ops)) / 5.0
    small_velocity = (1.0 + tolerance(thetadot, margin=5.0, ops=ops)) / 2.0
    return upright * small_control * small_velocity * centered


def dmc_balance_sparse_reward(state: Tensor) -> Tensor:
    """dm_control cartpole balance_sparse: cart in (-.25, .25) and cos(theta) in (.995, 1)."""
    cart_in_bounds = tolerance(state[..., 0], (-0.25, 0.25))
    angle_in_bounds = tolerance(state[..., 1].cos(), (0.995, 1.0))
    return cart_in_bounds * angle_in_bounds
