"""Isometric SO(2) augmentation (Equi-RSAC style): one rotation about the vertical for a whole episode.

Point clouds and the (dx, dy) of actions turn by one angle phi, drawn so that no rotated action needs
clipping: every copy is exact (its stored actions produce its stored next observations).

Design notes: docs/architecture-notes.md, services/augmenter/core/isometric.py."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from proto.episode import Augmentation, Episode
from services.geometry import rotate_quat_z, turn_xy

WORKSPACE_CENTRE = (0.5, 0.0)
ROTATION_DRAWS = 32
"""Uniform angles tried by ``draw_rotation`` before it falls back to a multiple of 90 degrees."""
QUARTER = math.pi / 2
ROTATION_PARAM = "rotation"
"""``Augmentation.params`` key of a rotated copy: (1,) float64, its angle (rad) about the vertical."""


def cos_sin(phi: float) -> tuple[float, float]:
    """cos and sin of ``phi``, exact (0, +-1) at multiples of 90 degrees, so that those rotations
    only permute and negate coordinates (``math.cos(pi / 2)`` is 6e-17, not 0)."""
    k = round(phi / QUARTER)
    if abs(phi - k * QUARTER) <= 1e-12:
        return ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))[k % 4]
    return math.cos(phi), math.sin(phi)


def rotate_points(points: np.ndarray, phi: float) -> np.ndarray:
    """x, y of ``points`` (..., >= 2) turned by ``phi`` about the vertical (float64 math, one
    rounding to float32)."""
    c, s = cos_sin(phi)
    return turn_xy(np.asarray(points, np.float64), c, s, out=np.array(points, dtype=np.float32, copy=True))


def rotation_fits(actions: np.ndarray, phi: float) -> bool:
    """Every (dx, dy) of ``actions`` (T, 5) turned by ``phi`` stays inside [-1, 1] as stored."""
    a = np.asarray(actions)
    return len(a) == 0 or float(np.abs(rotate_points(a[:, 1:3], phi)).max()) <= 1.0


def rotate_actions(actions: np.ndarray, phi: float) -> np.ndarray:
    """(jaw, dx, dy, dz, dtheta) with (dx, dy) turned by ``phi``; ValueError if any rotated (dx, dy)
    would leave [-1, 1] (draw the angle with ``draw_rotation``: a copy is never clipped)."""
    out = np.array(actions, dtype=np.float32, copy=True)
    out[:, 1:3] = rotate_points(actions[:, 1:3], phi)
    if len(out) and float(np.abs(out[:, 1:3]).max()) > 1.0:
        raise ValueError(
            f"rotating these actions by {phi!r} rad takes (dx, dy) outside [-1, 1] "
            f"(max {float(np.abs(out[:, 1:3]).max()):.4f}); a rotated copy must not be clipped"
        )
    return out


def draw_rotation(
    rng: np.random.Generator, actions: Sequence[np.ndarray], draws: int = ROTATION_DRAWS
) -> float:
    """An angle (rad) under which every (dx, dy) of every array in ``actions`` stays inside [-1, 1]:
    the first of up to ``draws`` uniform draws in [0, 2 pi) that fits, else a uniformly drawn
    multiple of 90 degrees (exact for any action in [-1, 1]). Deterministic given ``rng``."""
    for _ in range(draws):
        phi = float(rng.uniform(0.0, 2.0 * math.pi))
        if all(rotation_fits(a, phi) for a in actions):
            return phi
    return float(int(rng.integers(4)) * QUARTER)


def rotate_episode(ep: Episode, phi: float, *, centre: tuple[float, float] = WORKSPACE_CENTRE) -> dict:
    """The arrays of ``ep`` seen in a world rotated by ``phi`` about the vertical."""
    c = np.array([*centre, 0.0], np.float32)
    actions = rotate_actions(ep.actions, phi)
    pose = np.array(ep.gripper_pose, np.float32, copy=True)
    pose[:, :3] = rotate_points(pose[:, :3] - c, phi) + c
    pose[:, 3] = pose[:, 3] + phi
    objects = np.array(ep.object_poses, np.float32, copy=True)
    objects[..., :3] = rotate_points(objects[..., :3] - c, phi) + c
    objects[..., 3:] = rotate_quat_z(objects[..., 3:].astype(np.float64), phi)
    return {
        "points": rotate_points(ep.points, phi),
        "actions": actions,
        "gripper_pose": pose,
        "object_poses": objects.astype(np.float32),
    }


def isometric_copy(ep: Episode, phi: float, *, seed: int, copy_index: int, episode_id: str) -> Episode:
    aug = Augmentation(source_episode_id=ep.episode_id, kind="isometric", seed=seed, copy_index=copy_index,
                       phase_split=0, params={ROTATION_PARAM: np.array([phi])})  # fmt: skip
    return dataclasses.replace(
        ep, episode_id=episode_id, images=None, augmentation=aug, **rotate_episode(ep, phi)
    )


def compose_with_mea(mea_ep: Episode, phi: float) -> Episode:
    """G_t x G: an MEA copy additionally rotated by the episode's shared isometric angle phi."""
    aug = mea_ep.augmentation
    params = dict(aug.params)
    params[ROTATION_PARAM] = np.array([phi])
    new_aug = dataclasses.replace(aug, kind="mea+isometric", params=params)
    return dataclasses.replace(mea_ep, augmentation=new_aug, **rotate_episode(mea_ep, phi))
