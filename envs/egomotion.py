"""Egocentric movement, shared by the arena envs so that all of them feel the same.

An agent's camera looks along its body's heading (yaw 0 faces +Y). Actions:
discrete 5: 0 noop, 1 forward, 2 turn left, 3 turn right, 4 backward;
continuous 2: (thrust in [-1, 1] along the heading, turn rate in [-1, 1]).
Full thrust is THRUST newtons (an env may give its own per agent), full turn TURN_RATE rad/s.
Bodies move with envs/planar.py at MPE-like settings: 0.1 s steps, a quarter of the
velocity lost per step to drag.
"""
from __future__ import annotations

import math

import torch

from . import scenery

THRUST = 5.0  # N at full forward action
TURN_RATE = 3.0  # rad/s at full turn action
DT = 0.1  # s per env step
DRAG = -math.log(0.75) / DT  # 25% of the velocity lost per step, as in MPE
# discrete action -> (thrust, turn)
DISCRETE_ACTIONS = ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.0, -1.0), (-1.0, 0.0))
ACTION_MEANINGS = ("noop", "forward", "turn_left", "turn_right", "backward")
CONTINUOUS_MEANINGS = ("thrust along the body's heading (+ forward)", "turn rate (+ left)")  # continuous=True's dims


def drive(yaw: torch.Tensor, command: torch.Tensor, alive: torch.Tensor, thrust, dt: float):
    """(new yaw [W, N], force [W, N, 2]) of agents with headings `yaw` [W, N] given commands
    [W, N, 2] (thrust, turn) in [-1, 1]; `thrust` is the full thrust (N, a float or [N]).
    Departed agents (alive False) neither turn nor push."""
    thrust_action, turn = command.unbind(-1)
    thrust_action = torch.where(alive, thrust_action, torch.zeros_like(thrust_action))
    turn = torch.where(alive, turn, torch.zeros_like(turn))
    yaw = scenery.wrap_angle(yaw + turn * (TURN_RATE * dt))
    force = (thrust * thrust_action)[..., None] * scenery.heading(yaw)
    return yaw, force
