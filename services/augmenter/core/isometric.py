"""Isometric SO(2) augmentation (Equi-RSAC style): one rotation about the vertical for a whole episode.

Rotating every point cloud about the gripper-centric z axis by phi, and the (dx, dy) part of every
action by the same phi, is the whole episode seen in a world rotated by phi (re-centring on the
gripper commutes with the rotation). dz, dtheta, the jaw, rewards and flags are unchanged. As in
the public code, rotated (dx, dy) is clipped to [-1, 1], which shortens large diagonal moves.
Privileged world poses are rotated about the vertical through ``centre`` (the workspace centre);
a rotated scene can leave the robot's box-shaped workspace, so these copies are for learning, not
for the physics audit.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from proto.episode import Augmentation, Episode

WORKSPACE_CENTRE = (0.5, 0.0)


def rotate_points(points: np.ndarray, phi: float) -> np.ndarray:
    c, s = math.cos(phi), math.sin(phi)
    out = np.array(points, dtype=np.float32, copy=True)
    out[..., 0] = c * points[..., 0] - s * points[..., 1]
    out[..., 1] = s * points[..., 0] + c * points[..., 1]
    return out


def rotate_actions(actions: np.ndarray, phi: float) -> np.ndarray:
    out = np.array(actions, dtype=np.float32, copy=True)
    out[:, 1:3] = rotate_points(actions[:, 1:3], phi)
    return np.clip(out, -1.0, 1.0)


def _rotate_quat_z(quats: np.ndarray, phi: float) -> np.ndarray:
    """Pre-multiply (x, y, z, w) quaternions by a rotation of phi about world z."""
    qz, qw = math.sin(phi / 2), math.cos(phi / 2)
    x, y, z, w = quats[..., 0], quats[..., 1], quats[..., 2], quats[..., 3]
    return np.stack([qw * x - qz * y, qw * y + qz * x, qw * z + qz * w, qw * w - qz * z], axis=-1)


def rotate_episode(ep: Episode, phi: float, *, centre: tuple[float, float] = WORKSPACE_CENTRE) -> dict:
    """The arrays of ``ep`` seen in a world rotated by ``phi`` about the vertical."""
    c = np.array([*centre, 0.0], np.float32)
    pose = np.array(ep.gripper_pose, np.float32, copy=True)
    pose[:, :3] = rotate_points(pose[:, :3] - c, phi) + c
    pose[:, 3] = pose[:, 3] + phi
    objects = np.array(ep.object_poses, np.float32, copy=True)
    objects[..., :3] = rotate_points(objects[..., :3] - c, phi) + c
    objects[..., 3:] = _rotate_quat_z(objects[..., 3:].astype(np.float64), phi)
    return {
        "points": rotate_points(ep.points, phi),
        "actions": rotate_actions(ep.actions, phi),
        "gripper_pose": pose,
        "object_poses": objects.astype(np.float32),
    }


def isometric_copy(ep: Episode, phi: float, *, seed: int, copy_index: int, episode_id: str) -> Episode:
    aug = Augmentation(source_episode_id=ep.episode_id, kind="isometric", seed=seed, copy_index=copy_index,
                       phase_split=0, params={"rotation": np.array([phi])})  # fmt: skip
    return dataclasses.replace(
        ep, episode_id=episode_id, images=None, augmentation=aug, **rotate_episode(ep, phi)
    )


def compose_with_mea(mea_ep: Episode, phi: float) -> Episode:
    """G_t x G: an MEA copy additionally rotated by the episode's shared isometric angle phi."""
    aug = mea_ep.augmentation
    params = dict(aug.params)
    params["rotation"] = np.array([phi])
    new_aug = dataclasses.replace(aug, kind="mea+isometric", params=params)
    return dataclasses.replace(mea_ep, augmentation=new_aug, **rotate_episode(mea_ep, phi))
