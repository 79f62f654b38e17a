"""What the state critic reads: the simulator's privileged state of each step, in a canonical frame.

Design notes: docs/architecture-notes.md, services/algorithms/privileged.py."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from proto.episode import OBJECT_SYMMETRY

if TYPE_CHECKING:
    from proto.episode import Episode

STATE_DIM = 18
"""Floats per observation row (docs/architecture-notes.md)."""
CANONICAL_ANGLE = 0
"""Column of the frame angle."""
SCALE = 1.0 / 0.2
"""Lengths are given per 0.2 m (the tasks' workspace is about 0.4 m across)."""


def yaw_of(quaternions: np.ndarray) -> np.ndarray:
    """Yaw (rad) of (..., 4) quaternions (x, y, z, w) of bodies that stay upright."""
    x, y, z, w = (quaternions[..., i] for i in range(4))
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def critic_state(
    gripper_pose: np.ndarray,
    object_poses: np.ndarray,
    contacts: np.ndarray,
    jaw: np.ndarray,
    fixed_object: int,
    object_symmetry: int,
) -> np.ndarray:
    """(T+1, STATE_DIM) float32 rows from an episode's privileged arrays: ``gripper_pose``
    (T+1, 4) world (x, y, z, yaw), ``object_poses`` (T+1, 2, 7) world (x, y, z, quaternion),
    ``contacts`` (T+1, 2), ``jaw`` (T+1,), the immovable object's index and the objects' rotational
    symmetry order. ValueError when the task does not have exactly two objects, one immovable."""
    g = np.asarray(gripper_pose, np.float64)
    o = np.asarray(object_poses, np.float64)
    if o.ndim != 3 or o.shape[1:] != (2, 7) or g.shape != (o.shape[0], 4):
        raise ValueError(
            f"object_poses: the state critic needs two objects, (T+1, 2, 7), beside gripper_pose (T+1, 4); "
            f"got {o.shape} and {g.shape}"
        )
    if fixed_object not in (0, 1):
        raise ValueError(
            f"fixed_object: the state critic needs to know the immovable object (0 or 1), got {fixed_object}"
        )
    if object_symmetry < 1:
        raise ValueError(f"object_symmetry must be >= 1, got {object_symmetry}")
    mov, fix = o[:, 1 - fixed_object], o[:, fixed_object]
    axis = fix[:, :2] - mov[:, :2]
    phi = np.arctan2(axis[:, 1], axis[:, 0])
    c, s = np.cos(phi), np.sin(phi)

    def in_frame(v: np.ndarray) -> np.ndarray:  # (T+1, 2) world -> frame (turned by -phi)
        return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]], axis=1)

    n = float(object_symmetry)
    yaw_m, yaw_f = yaw_of(mov[:, 3:]) - phi, yaw_of(fix[:, 3:]) - phi
    grip = g[:, 3] - phi
    touch = np.asarray(contacts, bool)
    out = np.concatenate(
        [
            phi[:, None],
            in_frame(mov[:, :2] - g[:, :2]) * SCALE,
            in_frame(fix[:, :2] - g[:, :2]) * SCALE,
            (mov[:, 2:3] - g[:, 2:3]) * SCALE,
            (fix[:, 2:3] - g[:, 2:3]) * SCALE,
            g[:, 2:3] * SCALE,
            np.stack([np.cos(n * yaw_m), np.sin(n * yaw_m), np.cos(n * yaw_f), np.sin(n * yaw_f)], axis=1),
            np.stack([np.cos(2.0 * grip), np.sin(2.0 * grip)], axis=1),
            np.asarray(jaw, np.float64)[:, None],
            np.stack([touch[:, 1 - fixed_object], touch[:, fixed_object]], axis=1).astype(np.float64),
            np.linalg.norm(axis, axis=1, keepdims=True) * SCALE,
        ],
        axis=1,
    )
    if not np.isfinite(out).all():
        raise ValueError("gripper_pose/object_poses: non-finite privileged state")
    return out.astype(np.float32)


def episode_critic_state(ep: Episode) -> np.ndarray:
    """``critic_state`` of an ``Episode`` (raw or augmented: copies carry their transformed poses)."""
    return critic_state(ep.gripper_pose, ep.object_poses, ep.contacts, ep.jaw, int(ep.fixed_object),
                        OBJECT_SYMMETRY[ep.task])  # fmt: skip
