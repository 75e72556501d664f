"""Egocentric movement, shared by spread, tag, forage and push so that all feel the same.

An agent's camera looks along its body's heading (yaw 0 faces +Y). Actions:
discrete 5: 0 noop, 1 forward, 2 turn left, 3 turn right, 4 backward;
continuous 2: (thrust in [-1, 1] along the heading, turn rate in [-1, 1]).
Full thrust is THRUST newtons (an env may pass its own per agent), full turn TURN_RATE rad/s.
Bodies move with envs/physics.py at MPE-like settings: 0.1 s steps, a quarter of the
velocity lost per step to drag.
"""
from __future__ import annotations

import math

import torch

from . import physics, scenery
from .core import BatchedEnv

THRUST = 5.0  # N at full forward action
TURN_RATE = 3.0  # rad/s at full turn action
DT = 0.1  # s per env step
DRAG = -math.log(0.75) / DT  # 25% of the velocity lost per step, as in MPE
# discrete action -> (thrust, turn)
DISCRETE_ACTIONS = ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.0, -1.0), (-1.0, 0.0))
ACTION_MEANINGS = ("noop", "forward", "turn_left", "turn_right", "backward")


class EgocentricEnv(BatchedEnv):
    """Base of the arena envs: every agent sees through the same kind of body camera."""

    dt = DT
    fov_y = math.radians(90.0)
    near = 0.05
    far = 20.0

    @property
    def shadow_bounds(self):
        """shadows=True covers the arena and its walls, not the floor's far margin."""
        return scenery.arena_shadow_bounds(self.arena_half_extent)


def declare_actions(env) -> None:
    """Set the env's action_dim or num_actions / action_meanings, and its action table."""
    if env.continuous:
        env.action_dim = 2
    else:
        env.num_actions = len(DISCRETE_ACTIONS)
        env.action_meanings = ACTION_MEANINGS
    env.action_table = torch.tensor(DISCRETE_ACTIONS, device=env.device)


def arena_physics(terms, half_extent, *, max_speed: float, min_body_radius: float,
                  substeps: int = 2) -> physics.PhysicsConfig:
    return physics.PhysicsConfig(dt=DT, substeps=substeps, terms=terms, restitution=0.5, drag=DRAG,
                                 arena_half_extent=half_extent, max_speed=max_speed,
                                 min_body_radius=min_body_radius)


def drive(env, actions: torch.Tensor, alive: torch.Tensor, thrust=THRUST):
    """(yaw [W, N], force [W, N, 2]) for validated actions; departed agents neither turn nor push."""
    thrust_action, turn = (actions if env.continuous else env.action_table[actions]).unbind(-1)
    thrust_action = torch.where(alive, thrust_action, torch.zeros_like(thrust_action))
    turn = torch.where(alive, turn, torch.zeros_like(turn))
    yaw = scenery.wrap_angle(env.yaw + turn * (TURN_RATE * env.physics.dt))
    force = (thrust * thrust_action)[..., None] * scenery.heading(yaw)
    return yaw, force
