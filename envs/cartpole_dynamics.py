"""The DeepMind Control Suite cart-pole as a batched ODE in torch: [W, 4] states stepped side by side.

State (x, theta, x_dot, theta_dot): the cart's position on the rail (m), the pole's angle
(theta = 0 upright, > 0 tilts towards +x) and their rates. ``cartpole_step`` integrates one
control step (RK4 by default, as dm_control), ``slider_limit`` stops the cart at the end of
the rail, ``cartpole_energy`` gives the mechanical energy (a check of the integrators).
dtype and device follow the input tensors (float64 like MuJoCo, or float32).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from . import array_ops
from .array_ops import TorchOps

# Constants as in dm_control cartpole.xml (dm_control/suite/cartpole.xml):
#   <option timestep="0.01" integrator="RK4">, MuJoCo's default gravity 9.81;
#   cart: box geom mass 1 on a "slider" slide joint, damping 5e-4;
#   pole: capsule fromto 0 0 0 -> 0 0 1 (length 1, so centre of mass 0.5 above
#   the hinge), radius 0.045, mass 0.1, "hinge" joint damping 2e-6;
#   actuator: motor on the slider, gear 10, ctrlrange [-1, 1] (ctrllimited).
# The pole's inertia is MuJoCo's capsule inertia (mjCGeom::SetInertia): a
# cylinder plus two hemispherical caps sharing the mass by volume; it is ~13 %
# larger than the thin-rod m L^2 / 12.
# The slider's soft range limit (+-1.8 m, solreflimit .08 1) is modelled as a
# hard stop (slider_limit); contacts are disabled in the xml anyway.

def _capsule_inertia(mass: float, radius: float, half_length: float) -> float:
    height = 2.0 * half_length
    sphere_mass = mass * 4.0 * radius / (4.0 * radius + 3.0 * height)
    cylinder_mass = mass - sphere_mass
    inertia = cylinder_mass * (3.0 * radius ** 2 + height ** 2) / 12.0
    inertia += 2.0 * sphere_mass * radius ** 2 / 5.0 + sphere_mass * height * (3.0 * radius + 2.0 * height) / 8.0
    return inertia


CARTPOLE = dict(
    gravity=9.81,
    cart_mass=1.0,
    pole_mass=0.1,
    pole_com=0.5,                # hinge -> pole centre of mass (m)
    pole_inertia=_capsule_inertia(0.1, 0.045, 0.5),  # about the centre of mass
    slider_damping=5e-4,
    hinge_damping=2e-6,
    gear=10.0,
    timestep=0.01,
)
CARTPOLE_INTEGRATORS = ("semi_implicit_euler", "velocity_verlet", "rk4")


def cartpole_accel(theta, xdot, thetadot, force, slider_damping: float, hinge_damping: float, ops=TorchOps):
    """(x_ddot, theta_ddot) of the cart-pole; theta = 0 upright, > 0 tilts to +x.

    Lagrangian with q = (x, theta): mass matrix
    [[M + m, m l cos], [m l cos, I + m l^2]], gravity torque m g l sin(theta),
    centripetal term m l sin(theta) theta_dot^2 on the cart, viscous joint damping;
    l is pole_com (hinge to the pole's centre of mass, `com` below). Tensors, or the arrays
    of `ops` (envs/array_ops.py).
    """
    p = CARTPOLE
    M, m, com, g = p["cart_mass"], p["pole_mass"], p["pole_com"], p["gravity"]
    J = p["pole_inertia"] + m * com * com
    cos, sin = ops.cos(theta), ops.sin(theta)
    rhs_x = force - slider_damping * xdot + m * com * sin * thetadot * thetadot
    rhs_t = m * g * com * sin - hinge_damping * thetadot
    mlc = m * com * cos
    det = (M + m) * J - mlc * mlc  # > 0 always: (M + m) J > m^2 l^2
    xdd = (J * rhs_x - mlc * rhs_t) / det
    tdd = ((M + m) * rhs_t - mlc * rhs_x) / det
    return xdd, tdd


def check_step_arguments(dt, substeps: int, integrator: str) -> None:
    if not (isinstance(substeps, int) and not isinstance(substeps, bool) and substeps >= 1):
        raise ValueError(f"substeps must be an int >= 1, got {substeps!r}")
    if not (isinstance(dt, (int, float)) and not isinstance(dt, bool) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
    if integrator not in CARTPOLE_INTEGRATORS:
        raise ValueError(f"integrator must be one of {CARTPOLE_INTEGRATORS}, got {integrator!r}")


def cartpole_step(
    state: Tensor,
    action: Tensor,
    dt: float = CARTPOLE["timestep"],
    substeps: int = 1,
    integrator: str = "rk4",
    slider_damping: float = CARTPOLE["slider_damping"],
    hinge_damping: float = CARTPOLE["hinge_damping"],
) -> Tensor:
    """One control step of the cart-pole: state [W, 4] = (x, theta, x_dot, theta_dot).

    ``action`` [W] is clipped to [-1, 1] (ctrllimited) and drives the slider
    with gear 10 (N). The defaults (dt 0.01, one RK4 substep) are dm_control's
    settings. "velocity_verlet" treats the velocity-dependent terms
    explicitly (half-kick with the current velocity).
    """
    check_step_arguments(dt, substeps, integrator)
    force = CARTPOLE["gear"] * action.clamp(-1.0, 1.0).to(state.dtype)
    ops = array_ops.for_tensors(state, force)
    with ops.quiet():
        q = integrate(ops, array_ops.to_ops(ops, state), array_ops.to_ops(ops, force), dt, substeps, integrator,
                      slider_damping, hinge_damping)
    return array_ops.to_tensor(q)


def integrate(ops, state, force, dt: float, substeps: int, integrator: str, slider_damping: float,
              hinge_damping: float):
    """cartpole_step on the arrays of `ops` (arguments checked by the caller), `force` in N."""
    h = dt / substeps

    def accel(q, v):
        return ops.stack(cartpole_accel(q[..., 1], v[..., 0], v[..., 1], force, slider_damping, hinge_damping, ops),
                         -1)

    def derivative(y):  # dy/dt of y = (x, theta, x_dot, theta_dot): (x_dot, theta_dot, x_ddot, theta_ddot)
        xdd, tdd = cartpole_accel(y[..., 1], y[..., 2], y[..., 3], force, slider_damping, hinge_damping, ops)
        return ops.stack((y[..., 2], y[..., 3], xdd, tdd), -1)

    q, v = state[..., :2], state[..., 2:]
    for _ in range(substeps):
        if integrator == "semi_implicit_euler":
            v = v + h * accel(q, v)
            q = q + h * v
        elif integrator == "velocity_verlet":
            v_half = v + 0.5 * h * accel(q, v)
            q = q + h * v_half
            # The closing half-kick is implicit here, a(q1, v1): the centripetal
            # and damping terms depend on velocity. Using v_half for v1 would
            # drop the scheme to first order; one fixed-point pass keeps second.
            v = v_half + 0.5 * h * accel(q, v_half)
            v = v_half + 0.5 * h * accel(q, v)
        else:  # classic RK4 on y = (q, v), as MuJoCo's RK4 integrator
            y = ops.concatenate([q, v], -1)
            k1 = derivative(y)
            k2 = derivative(y + 0.5 * h * k1)
            k3 = derivative(y + 0.5 * h * k2)
            k4 = derivative(y + h * k3)
            y = y + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
            q, v = y[..., :2], y[..., 2:]
    return ops.concatenate([q, v], -1)


def cartpole_energy(state: Tensor) -> Tensor:
    """Total mechanical energy [W] (J), potential zero at hinge height.

    Conserved when both dampings are 0 and the action is 0.
    """
    p = CARTPOLE
    M, m, com, g = p["cart_mass"], p["pole_mass"], p["pole_com"], p["gravity"]
    J = p["pole_inertia"] + m * com * com
    theta, xdot, thetadot = state[..., 1], state[..., 2], state[..., 3]
    kinetic = 0.5 * (M + m) * xdot ** 2 + m * com * torch.cos(theta) * xdot * thetadot + 0.5 * J * thetadot ** 2
    return kinetic + m * g * com * torch.cos(theta)


SLIDER_LIMIT = 1.8  # m, dm_control cartpole.xml slider range


def slider_limit(q: Tensor, limit: float = SLIDER_LIMIT) -> Tensor:
    """Hard inelastic stop at |x| = limit: the cart's velocity into the stop is removed and the
    pole gets the impulse that keeps the hinge constraint (d theta_dot = m l cos / J * x_dot)."""
    ops = array_ops.for_tensors(q)
    with ops.quiet():
        return array_ops.to_tensor(stop_at_limit(ops, array_ops.to_ops(ops, q), limit))


def stop_at_limit(ops, q, limit: float = SLIDER_LIMIT):
    """slider_limit on the arrays of `ops`."""
    x, theta, xdot, thetadot = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    hit = ((x > limit) & (xdot > 0)) | ((x < -limit) & (xdot < 0))
    p = CARTPOLE
    m, com = p["pole_mass"], p["pole_com"]
    J = p["pole_inertia"] + m * com * com
    zero = ops.zeros_like(xdot)
    thetadot = ops.where(hit, thetadot + m * com * ops.cos(theta) / J * xdot, thetadot)
    xdot = ops.where(hit, zero, xdot)
    x = ops.clip(x, -limit, limit)
    return ops.stack((x, theta, xdot, thetadot), -1)
