"""The hybrid controller of Surgical Grasp Any (reference ``wrapper/pid.py``) and the FSM rewards.

A P-controller on voxel centroids drives the approach, then hands over to the policy for the rest of
the episode; ``active`` is what the observation reports as ``controller_state``.

Design notes: docs/architecture-notes.md, services/tasks/surgical/control.py."""

from __future__ import annotations

import numpy as np

from services.tasks.surgical.settings import FSM_STATES, ControllerSettings, RewardSettings


def centroid_error(
    gripper: np.ndarray | None, obj: np.ndarray | None, settings: ControllerSettings
) -> np.ndarray | None:
    """Gripper centroid - object centroid + offset (occupancy units); None if either is unseen."""
    if gripper is None or obj is None:
        return None
    return gripper - obj + np.asarray(settings.error_offset)


class HybridController:
    """The latched P-controller of the approach."""

    def __init__(self, settings: ControllerSettings) -> None:
        self.s = settings
        self.active = settings.enabled

    def outside(self, err: np.ndarray | None) -> np.ndarray:
        """Axes whose error is beyond the phase threshold (all of them when the error is unknown)."""
        if err is None:
            return np.ones(3, bool)
        return np.abs(err) > np.asarray(self.s.phase_threshold)

    def reset(self, err: np.ndarray | None) -> None:
        self.active = bool(self.s.enabled and self.outside(err).any())

    def update(self, err: np.ndarray | None) -> None:
        """After a step: hand over (for good) once every axis is inside the threshold."""
        if self.active and not self.outside(err).any():
            self.active = False

    def action(self, err: np.ndarray | None) -> np.ndarray:
        """The controller's action (jaw, dx, dy, dz, dtheta): P on the axes outside the threshold, jaw
        open; no motion when the error is unknown (a segment unseen)."""
        a = np.zeros(5)
        a[0] = 1.0
        if err is not None:
            move = -np.asarray(self.s.gain) * err * self.outside(err)
            a[1:4] = np.clip(move, -1.0, 1.0)
        return a


def fsm_reward(state: str, rewards: RewardSettings) -> float:
    if state == "done_success":
        return rewards.success
    if state == "done_fail":
        return rewards.fail
    if state == "prog_norm":
        return rewards.normal_step
    return rewards.abnormal_step


def fsm_index(state: str) -> int:
    return FSM_STATES.index(state)
