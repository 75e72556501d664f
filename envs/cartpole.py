"""CartPole balance, as in the DeepMind Control Suite (``cartpole-balance``), from pixels.

One agent per world pushes a cart along a rail to keep a pole upright.

* Dynamics: ``cartpole_dynamics.cartpole_step`` (dm_control's cartpole.xml constants, one
  RK4 step of 0.01 s per env step, gear 10). The slider's range limit (+-1.8 m in the
  xml) is modelled as a hard, inelastic stop (``cartpole_dynamics.slider_limit``): a cart
  reaching the end loses its velocity and the pole receives the matching impulse
  (MuJoCo's limit is soft; it only differs there).
* Reward: ``dmc_rewards.dmc_balance_reward`` (upright * centred * small control * small
  velocity), in [0, 1] per step.
* Episode: never terminates early; truncated after ``max_steps`` = 1000 (10 s).
* Reset: cart x ~ U(-0.1, 0.1), pole angle ~ U(-0.034, 0.034), velocities 0.01 N(0, 1).
* Actions: continuous ``[W, 1, 1]`` in [-1, 1] (motor control); discrete: 5 force
  levels ``FORCE_LEVELS`` = (-1, -0.5, 0, 0.5, 1).
* Pixels: dm_control's "fixed" camera: at (0, -4, 1) looking along +Y, 45 degree field
  of view. The floor, two rails, the cart and the pole, all boxes.
* State obs (5): cart x, cos(angle), sin(angle), cart velocity, angular velocity
  (dm_control's position + velocity observation).
"""
from __future__ import annotations

import dataclasses
import functools
import math

import torch

import marl_render as mr

from . import array_ops
from .cartpole_dynamics import CARTPOLE, SLIDER_LIMIT, integrate, stop_at_limit
from .compiled import compile_kernel
from .dmc_rewards import balance_reward
from .roster import Card
from .scenario import STATE_LIMIT, Scenario, Step

FORCE_LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)
CART_HEIGHT = 1.0  # the cart body's z (hinge height)
CART_SIZE = (0.4, 0.3, 0.2)  # full sizes of the cart box (geom size .2 .15 .1)
POLE_LENGTH = 1.0
POLE_WIDTH = 0.09  # capsule radius 0.045
CAMERA_POSITION = (0.0, -4.0, 1.0)

SELF_COLOR = (0.7, 0.5, 0.3)  # dm_control material "self"
POLE_COLOR = (0.6, 0.42, 0.25)
DECORATION_COLOR = (0.3, 0.5, 0.7)
FLOOR_COLOR = (0.15, 0.25, 0.35)
SKY_COLOR = (0.4, 0.6, 0.8)
# The heuristic's feedback gains on (x, theta, x_dot, theta_dot): push the cart under the pole.
HEURISTIC_GAINS = (0.5, 8.0, 1.0, 1.5)


def advance(ops, qstate, control, dt: float):
    """One env step of every world on the arrays of `ops`: the new (x, theta, x_dot, theta_dot)
    after one RK4 step and the slider stop, and the balance reward [W]."""
    force = CARTPOLE["gear"] * ops.clip(control, -1.0, 1.0)
    q = stop_at_limit(ops, integrate(ops, qstate, force, dt, 1, "rk4", CARTPOLE["slider_damping"],
                                     CARTPOLE["hinge_damping"]))
    return q, balance_reward(ops, q, control)


@dataclasses.dataclass(frozen=True)
class CartPoleState:
    qstate: torch.Tensor  # [W, 4] float64 (x, theta, x_dot, theta_dot), like MuJoCo's qpos + qvel
    last_control: torch.Tensor  # [W] float64: the motor control of the last step


class CartPoleBalance(Scenario):
    """dm_control cartpole-balance, batched over worlds; see the module docstring."""

    name = "cartpole"
    default_num_agents = 1
    agent_range = (1, 1)
    default_max_steps = 1000
    default_max_steps = 1000
    # How long the pole must stay up.
    difficulties = {"easy": {"max_steps": 200}, "medium": {}, "hard": {"max_steps": 2000}}
    default_resolution = 64
    dt = CARTPOLE["timestep"]  # one RK4 step per env step
    physics_terms = frozenset()  # own dynamics (cartpole_dynamics.cartpole_step); no planar terms
    background = SKY_COLOR
    fov_y = math.radians(45.0)
    near = 0.1
    far = 20.0
    overview_fov_y = math.radians(45.0)
    overview_resolution = (120, 160)
    card = Card(reward="dm_control's balance reward in [0, 1] per step: upright x centred x small control x small "
                       "velocity",
                episode_end="never terminates; truncated at max_steps",
                continuous=("motor control: force on the cart, x 10 N (gear 10)",))
    # The trainer's defaults. 48 pixels: at 32 the 9 cm pole is thinner than a pixel and is not drawn at all.
    # Action repeat 8: the state-feedback heuristic still scores 982 holding each action 8 steps, and a
    # decision then costs half the CNN work per env step. 10 x 8 passes: 4 x 4 left the same learner on the
    # state at ~650 (it learns to drift and let the pole fall); 10 x 8 reaches 994 from the state.
    training = {"worlds": 64, "resolution": 48, "frames": 2, "action_repeat": 8, "rollout": 32, "epochs": 10,
                "minibatches": 8, "entropy": 0.003, "budget": {"pixels": 5_226_496, "state": 2_490_368}}

    def setup(self):
        W = self.num_worlds
        self.discrete_actions(tuple(f"force_{u:+g}" for u in FORCE_LEVELS))
        self.continuous_actions(1)
        self.state_dim = 5
        self.force_levels = torch.tensor(FORCE_LEVELS, dtype=torch.float64, device=self.device)
        # Constant parts of the instance data: [cart, pole].
        self._scale = torch.tensor([CART_SIZE, (POLE_WIDTH, POLE_WIDTH, POLE_LENGTH)]).expand(W, 2, 3)
        self._color = torch.tensor([SELF_COLOR, POLE_COLOR]).expand(W, 2, 3)
        self._active = torch.ones(W, 2, dtype=torch.bool)
        self._never_terminated = torch.zeros(W, 1, dtype=torch.bool, device=self.device)  # read, never written
        # Pose buffers rewritten in place every step (no allocation on the hot path).
        self._position = torch.zeros(W, 2, 3)
        self._position[:, :, 2] = CART_HEIGHT
        self._rotation = torch.zeros(W, 2, 4)
        self._rotation[:, :, 0] = 1.0
        self._kernel = None  # the compiled advance() (compile_physics), else the default path

    def initial_state(self):
        W = self.num_worlds
        return CartPoleState(qstate=torch.zeros(W, 4, dtype=torch.float64, device=self.device),
                             last_control=torch.zeros(W, dtype=torch.float64, device=self.device))

    def state_bounds(self):
        """The cart on its rail (|x| <= the slider stop), the control in [-1, 1]; angles and rates
        within the default +-STATE_LIMIT."""
        free = STATE_LIMIT
        return {"qstate": ((-SLIDER_LIMIT, -free, -free, -free), (SLIDER_LIMIT, free, free, free)),
                "last_control": (-1.0, 1.0)}

    def spawn_level(self, draws):
        W = self.num_worlds
        x = draws.rand("x", (W,), dtype=torch.float64) * 0.2 - 0.1
        theta = draws.rand("theta", (W,), dtype=torch.float64) * 0.068 - 0.034
        qvel = 0.01 * draws.randn("qvel", (W, 2), dtype=torch.float64)
        fresh = torch.cat((x[:, None], theta[:, None], qvel), 1).to(self.device)
        return CartPoleState(qstate=fresh, last_control=torch.zeros(W, dtype=torch.float64, device=self.device))

    def control(self, actions: torch.Tensor) -> torch.Tensor:
        """Motor control [W] in [-1, 1] for validated actions."""
        return actions[:, 0, 0].to(torch.float64) if self.continuous else self.force_levels[actions[:, 0]]

    def step(self, state, actions, alive, generator):
        u = self.control(actions)
        compiled = None if self._kernel is None else self._kernel(state.qstate, u)  # None: it failed
        if compiled is not None:
            q, reward = compiled
        else:
            # One pass over the arrays of the cheapest namespace (envs/array_ops.py): at small
            # batches the cost of this step is the number of calls, not the arithmetic.
            ops = array_ops.for_tensors(state.qstate, u)
            with ops.quiet():
                q, reward = advance(ops, array_ops.to_ops(ops, state.qstate), array_ops.to_ops(ops, u), self.dt)
            q, reward = array_ops.to_tensor(q), array_ops.to_tensor(reward)
        return Step(CartPoleState(qstate=q, last_control=u), reward[:, None], self._never_terminated, {})

    def compile_physics(self) -> bool:
        W = self.num_worlds
        example = (torch.zeros(W, 4, dtype=torch.float64, device=self.device),
                   torch.zeros(W, dtype=torch.float64, device=self.device))
        self._kernel = compile_kernel(functools.partial(advance, array_ops.TorchOps, dt=self.dt), example,
                                      f"cartpole physics for {W} worlds", key=("cartpole", W, str(self.device)))
        return self.physics_compiled

    @property
    def physics_compiled(self) -> bool:
        return self._kernel is not None and self._kernel.active

    def observation(self, state, alive):
        x, theta, xdot, thetadot = state.qstate.unbind(-1)
        return torch.stack((x, torch.cos(theta), torch.sin(theta), xdot, thetadot), -1)[:, None].to(torch.float32)

    def heuristic(self, state, alive):
        """A linear balance controller on the state (pole angle and rate, cart position and speed)."""
        x, theta, xdot, thetadot = state.qstate.unbind(-1)
        u = (HEURISTIC_GAINS[0] * x + HEURISTIC_GAINS[1] * theta + HEURISTIC_GAINS[2] * xdot
             + HEURISTIC_GAINS[3] * thetadot).clamp(-1, 1)
        if self.continuous:
            return u[:, None, None].to(torch.float32)
        return (u[:, None, None] - self.force_levels.to(u.dtype)).abs().argmin(-1)  # nearest force level

    # ------------------------------------------------------------------ scene binding
    def build_scene(self, scene: mr.Scene, overview: bool) -> None:
        # One static group (floor slab + two rails) and one instance group (cart + pole), all
        # boxes: the renderer culls and draws per group, so fewer groups is a faster frame.
        scene.add_static("scenery", "box",
                         position=[[0.0, 0.0, -0.1], [0.0, 0.07, CART_HEIGHT], [0.0, -0.07, CART_HEIGHT]],
                         scale=[[8.0, 8.0, 0.1], [4.0, 0.04, 0.04], [4.0, 0.04, 0.04]],
                         color=[FLOOR_COLOR, DECORATION_COLOR, DECORATION_COLOR], role=["floor", None, None])
        scene.add_group("cartpole", "box", capacity=2)

    def place_cameras(self, renderer: mr.BatchRenderer, overview: bool) -> None:
        W = self.num_worlds
        renderer.set_cameras(position=torch.tensor(CAMERA_POSITION, dtype=torch.float64).expand(W, 1, 3),
                             rotation=torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(W, 1, 4))

    def instances(self, state, full: bool) -> dict:
        # numpy views of the pose buffers: a handful of small writes, each far cheaper than torch's
        ops = array_ops.NumpyOps
        q = state.qstate.to("cpu", torch.float32).numpy()
        x, theta = q[:, 0], q[:, 1]
        half = 0.5 * theta
        position, rotation = self._position.numpy(), self._rotation.numpy()
        position[:, 0, 0] = x
        position[:, 1, 0] = x + 0.5 * POLE_LENGTH * ops.sin(theta)
        position[:, 1, 2] = CART_HEIGHT + 0.5 * POLE_LENGTH * ops.cos(theta)
        rotation[:, 1, 0] = ops.cos(half)  # about +Y: theta > 0 tilts the pole towards +x
        rotation[:, 1, 2] = ops.sin(half)
        update = {"position": self._position, "rotation": self._rotation}
        if full:
            update.update(scale=self._scale, color=self._color, active=self._active)
        return {"cartpole": update}
