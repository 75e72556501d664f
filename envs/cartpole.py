"""CartPole balance, as in the DeepMind Control Suite (``cartpole-balance``), from pixels.

One agent per world pushes a cart along a rail to keep a pole upright.

* Dynamics: ``physics.cartpole_step`` (dm_control's cartpole.xml constants, one RK4
  step of 0.01 s per env step, gear 10). The slider's range limit (+-1.8 m in the xml)
  is modelled as a hard, inelastic stop: a cart reaching the end loses its velocity
  and the pole receives the matching impulse (MuJoCo's limit is soft; it only differs
  there).
* Reward: ``physics.dmc_balance_reward`` (upright * centred * small control * small
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

import math

import torch

import marl_render as mr

from . import physics
from .core import BatchedEnv

FORCE_LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)
SLIDER_LIMIT = 1.8  # m, dm_control cartpole.xml slider range
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


class CartPoleBalance(BatchedEnv):
    """dm_control cartpole-balance, batched over worlds; see the module docstring."""

    name = "cartpole"
    default_num_agents = 1
    agent_range = (1, 1)
    default_max_steps = 1000
    default_resolution = 64
    dt = physics.CARTPOLE["timestep"]  # one RK4 step per env step
    physics_terms = frozenset()  # own dynamics (physics.cartpole_step); no planar terms
    background = SKY_COLOR
    fov_y = math.radians(45.0)
    near = 0.1
    far = 20.0
    overview_fov_y = math.radians(45.0)
    overview_resolution = (120, 160)

    def _setup(self):
        W = self.num_worlds
        self.agent_names = ["agent_0"]
        self.groups = {"agents": ["agent_0"]}
        if self.continuous:
            self.action_dim = 1
        else:
            self.num_actions = len(FORCE_LEVELS)
            self.action_meanings = tuple(f"force_{u:+g}" for u in FORCE_LEVELS)
        self.state_dim = 5
        self.force_levels = torch.tensor(FORCE_LEVELS, dtype=torch.float64, device=self.device)
        # (x, theta, x_dot, theta_dot), float64 like MuJoCo.
        self.qstate = torch.zeros(W, 4, dtype=torch.float64, device=self.device)
        self.last_control = torch.zeros(W, dtype=torch.float64, device=self.device)
        # Constant parts of the instance data: [cart, pole].
        self._scale = torch.tensor([CART_SIZE, (POLE_WIDTH, POLE_WIDTH, POLE_LENGTH)]).expand(W, 2, 3)
        self._color = torch.tensor([SELF_COLOR, POLE_COLOR]).expand(W, 2, 3)
        self._active = torch.ones(W, 2, dtype=torch.bool)
        # Pose buffers rewritten in place every step (no allocation on the hot path).
        self._position = torch.zeros(W, 2, 3)
        self._position[:, :, 2] = CART_HEIGHT
        self._rotation = torch.zeros(W, 2, 4)
        self._rotation[:, :, 0] = 1.0

    def _build_scene(self, scene: mr.Scene, overview: bool) -> None:
        # One static group (floor slab + two rails) and one instance group (cart + pole), all
        # boxes: the renderer culls and draws per group, so fewer groups is a faster frame.
        scene.add_static("scenery", "box",
                         position=[[0.0, 0.0, -0.1], [0.0, 0.07, CART_HEIGHT], [0.0, -0.07, CART_HEIGHT]],
                         scale=[[8.0, 8.0, 0.1], [4.0, 0.04, 0.04], [4.0, 0.04, 0.04]],
                         color=[FLOOR_COLOR, DECORATION_COLOR, DECORATION_COLOR])
        scene.add_group("cartpole", "box", capacity=2)

    def _init_cameras(self, renderer: mr.BatchRenderer, overview: bool) -> None:
        W = self.num_worlds
        renderer.set_cameras(position=torch.tensor(CAMERA_POSITION, dtype=torch.float64).expand(W, 1, 3),
                             rotation=torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(W, 1, 4))

    def _reset_state(self, mask):
        W, g = self.num_worlds, self.generator
        x = torch.rand(W, generator=g, dtype=torch.float64) * 0.2 - 0.1
        theta = torch.rand(W, generator=g, dtype=torch.float64) * 0.068 - 0.034
        qvel = 0.01 * torch.randn(W, 2, generator=g, dtype=torch.float64)
        fresh = torch.cat((x[:, None], theta[:, None], qvel), 1).to(self.device)
        self.qstate = torch.where(mask[:, None], fresh, self.qstate)
        self.last_control = torch.where(mask, torch.zeros_like(self.last_control), self.last_control)

    def control(self, actions: torch.Tensor) -> torch.Tensor:
        """Motor control [W] in [-1, 1] for validated actions."""
        return actions[:, 0, 0].to(torch.float64) if self.continuous else self.force_levels[actions[:, 0]]

    def _step_state(self, actions, alive):
        u = self.control(actions)
        q = physics.cartpole_step(self.qstate, u)
        q = slider_limit(q)
        reward = physics.dmc_balance_reward(q, u)
        self.qstate = q
        self.last_control = u
        terminated = torch.zeros(self.num_worlds, 1, dtype=torch.bool, device=self.device)
        return reward[:, None], terminated, {}

    def _instances(self, full: bool) -> dict:
        q = self.qstate.to("cpu", torch.float32)
        x, theta = q[:, 0], q[:, 1]
        half = 0.5 * theta
        position, rotation = self._position, self._rotation
        position[:, 0, 0] = x
        position[:, 1, 0] = x + 0.5 * POLE_LENGTH * torch.sin(theta)
        position[:, 1, 2] = CART_HEIGHT + 0.5 * POLE_LENGTH * torch.cos(theta)
        rotation[:, 1, 0] = torch.cos(half)  # about +Y: theta > 0 tilts the pole towards +x
        rotation[:, 1, 2] = torch.sin(half)
        update = {"position": position, "rotation": rotation}
        if full:
            update.update(scale=self._scale, color=self._color, active=self._active)
        return {"cartpole": update}

    def _state_obs(self):
        x, theta, xdot, thetadot = self.qstate.unbind(-1)
        state = torch.stack((x, torch.cos(theta), torch.sin(theta), xdot, thetadot), -1)
        return state[:, None].to(torch.float32)

    def _state_tensors(self):
        return {"qstate": self.qstate, "last_control": self.last_control}


def slider_limit(q: torch.Tensor, limit: float = SLIDER_LIMIT) -> torch.Tensor:
    """Hard inelastic stop at |x| = limit: the cart's velocity into the stop is removed and the
    pole gets the impulse that keeps the hinge constraint (d theta_dot = m l cos / J * x_dot)."""
    x, theta, xdot, thetadot = q.unbind(-1)
    hit = ((x > limit) & (xdot > 0)) | ((x < -limit) & (xdot < 0))
    p = physics.CARTPOLE
    m, l = p["pole_mass"], p["pole_com"]
    J = p["pole_inertia"] + m * l * l
    zero = torch.zeros_like(xdot)
    thetadot = torch.where(hit, thetadot + m * l * torch.cos(theta) / J * xdot, thetadot)
    xdot = torch.where(hit, zero, xdot)
    x = x.clamp(-limit, limit)
    return torch.stack((x, theta, xdot, thetadot), -1)
