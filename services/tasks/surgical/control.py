"""The hybrid controller of Surgical Grasp Any (reference ``wrapper/pid.py``) and the FSM rewards.

The P-controller measures the error between the gripper's and the object's voxel centroids in the
occupancy grid (``services.observation.dsa.voxel_centroid`` with the task's ``DsaSpec``, the one
voxelisation the policy image uses too; occupancy units: the grid's unit cube, 1 unit = 1 sim unit
= 20 cm real here), plus an offset that keeps the gripper above the object:

    err = centroid(gripper) - centroid(object) + error_offset

While any axis has |err| > phase_threshold it drives (action = clip(-Kp * err, -1, 1) on the axes
outside the threshold, 0 on the others, no rotation, jaw open). Once every axis is inside, it hands
over to the policy and is *latched* off for the rest of the episode (the reference re-enters it when
the error grows again; here the policy keeps control, so an episode has one approach phase and one
policy phase). ``active`` is what the observation reports as ``controller_state``: 1 when the next
action will be the controller's.
"""

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
