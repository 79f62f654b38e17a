"""The scripted oracle of Surgical Grasp Any, acting in the nine discrete actions.

The task's expert: privileged, like the reference's discrete oracle, it aligns the jaws with the
object's grasp point, descends, closes the jaw and lifts.

Design notes: docs/architecture-notes.md, services/tasks/surgical/oracle.py."""

from __future__ import annotations

import math

import numpy as np

from proto.discrete_actions import NAMES, TOGGLE
from services.tasks.surgical.objects import grasp_yaw
from services.tasks.surgical.settings import real

ABOVE = real(0.003)
MARGIN = real(0.0005)
YAW_WEIGHT = 0.4
_AXIS_ACTIONS = (("+x", "-x"), ("+y", "-y"), ("+z", "-z"), ("+yaw", "-yaw"))


def nearest_grasp_yaw(object_yaw: float, yaw: float, limit: float) -> float:
    """The grasp yaw (modulo pi) closest to ``yaw`` within [-limit, limit]."""
    base = grasp_yaw(object_yaw)
    k = round((yaw - base) / math.pi)
    options = [base + (k + d) * math.pi for d in (-1, 0, 1)]
    inside = [o for o in options if abs(o) <= limit] or options
    return min(inside, key=lambda o: abs(o - yaw))


class Oracle:
    """``act() -> action`` (a 5-vector of one of the nine discrete actions)."""

    def __init__(self, env) -> None:
        self.env = env

    def act(self) -> np.ndarray:
        return self.env.discrete_action(self.choose())

    def choose(self) -> int:
        env = self.env
        if env.grasped:
            return NAMES.index("+z")
        acts = env.settings.actions
        step_t, step_r = acts.step_translation, acts.step_rotation
        tip, yaw = env.tip(), env.instrument.state.yaw
        goal = env.scene.object_pose()[:2]
        goal_yaw = nearest_grasp_yaw(env.scene.object_yaw(), yaw, acts.yaw_limit)
        top = env.scene.spec.height
        err = np.array(
            [(goal[0] - tip[0]) / step_t, (goal[1] - tip[1]) / step_t, 0.0, (goal_yaw - yaw) / step_r]
        )
        outside = np.abs(err) > 0.5  # within half a step an axis is as close as the steps allow
        if outside[[0, 1, 3]].any():  # align above the object
            err[2] = max(0.0, (top + ABOVE - tip[2]) / step_t)
            outside[2] = err[2] > 0.0
            err[3] *= YAW_WEIGHT
            axis = int(np.argmax(np.abs(err) * outside))
            return NAMES.index(_AXIS_ACTIONS[axis][0 if err[axis] > 0 else 1])
        if not env.jaw_open:  # a failed closing (when trials remain): open again first
            return TOGGLE
        if tip[2] > top - MARGIN:
            return NAMES.index("-z")
        return TOGGLE
