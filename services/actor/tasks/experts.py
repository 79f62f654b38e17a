"""Scripted experts: privileged waypoint followers (BulletArm's close-loop planner idea).

Each step moves the commanded gripper toward the current goal, deltas clipped to one action's
reach, so expert actions are ordinary normalised actions. Goals are stated for the tool centre
point (between the finger tips), which is what grasping cares about.
"""

from __future__ import annotations

import math

import numpy as np

from services.actor.tasks.robot import DELTA_THETA, DELTA_XYZ, wrap


def nearest_symmetric_yaw(object_yaw: float, current: float, order: int) -> float:
    """The yaw among ``object_yaw + k*2pi/order`` closest to ``current`` (e.g. order 4 for a cube)."""
    step = 2 * math.pi / order
    k = round((current - object_yaw) / step)
    return object_yaw + k * step


class Follower:
    """Turns (tool-centre goal, yaw, jaw) into one normalised action for the env's robot."""

    def __init__(self, env) -> None:
        self.env = env

    def action(
        self, tip_goal: np.ndarray, yaw_goal: float, jaw: float, tol: float = 1e-3
    ) -> tuple[np.ndarray, bool]:
        """Action toward the goal, and whether the goal is reached after it."""
        r = self.env.robot
        pivot, yaw = r.pivot()
        offset = pivot - r.tcp()  # pivot relative to the tool centre, at the current yaw
        turn = wrap(yaw_goal - r.target_yaw)
        c, s = math.cos(turn), math.sin(turn)
        offset = np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1], offset[2]])
        delta = (np.asarray(tip_goal) + offset) - r.target_pos
        a = np.zeros(5)
        a[0] = 2.0 * jaw - 1.0
        a[1:4] = np.clip(delta / DELTA_XYZ, -1.0, 1.0)
        a[4] = np.clip(turn / DELTA_THETA, -1.0, 1.0)
        reached = bool(np.all(np.abs(delta) <= DELTA_XYZ + tol) and abs(turn) <= DELTA_THETA + 1e-6)
        return a, reached
