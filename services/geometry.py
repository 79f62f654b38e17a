"""Rotations about the vertical (z) axis in plain numpy: points, quaternions and yaw angles.

Angles are in radians, counter-clockwise seen from above: a quarter turn takes (x, y) to (-y, x).
Nothing here changes the callers' precision: x and y are computed in whatever dtype numpy promotes
the points and the cosines to (float32 points and a Python float stay float32) and written into a
copy of the points or a given array, so every caller gets the bits its own formula gave before.
"""

from __future__ import annotations

import math

import numpy as np


def turn_xy(
    points: np.ndarray, cos: float | np.ndarray, sin: float | np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """x, y of ``points`` (..., >= 2) turned by the angle whose cosine and sine are given (scalars, or
    arrays broadcasting against ``points[..., 0]``); the other components unchanged.

    The arithmetic is in the dtype numpy promotes ``points`` and the cosines to; the result goes into
    ``out`` (default: a copy of ``points``, which must not share memory with it), so passing one
    chooses the stored dtype."""
    if out is None:
        out = points.copy()
    out[..., 0] = cos * points[..., 0] - sin * points[..., 1]
    out[..., 1] = sin * points[..., 0] + cos * points[..., 1]
    return out


def rotate_z(points: np.ndarray, angle: float) -> np.ndarray:
    """``points`` (..., >= 2) turned by ``angle`` about z (``math.cos``/``math.sin``), same dtype."""
    return turn_xy(points, math.cos(angle), math.sin(angle))


def rotate_z_per_step(points: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """``points`` (T, ..., >= 2) with row ``t`` turned by ``angles[t]`` about z (angles of shape (T,) or
    any leading shape of ``points``; ``np.cos``/``np.sin``), same dtype as the points."""
    angles = np.asarray(angles)
    shape = angles.shape + (1,) * (points.ndim - 1 - angles.ndim)
    return turn_xy(points, np.cos(angles).reshape(shape), np.sin(angles).reshape(shape))


def rotate_quat_z(quats: np.ndarray, angle: float) -> np.ndarray:
    """(x, y, z, w) quaternions (..., 4) pre-multiplied by a rotation of ``angle`` about world z: the
    orientations of bodies turned by ``angle`` about the vertical."""
    qz, qw = math.sin(angle / 2), math.cos(angle / 2)
    x, y, z, w = quats[..., 0], quats[..., 1], quats[..., 2], quats[..., 3]
    return np.stack([qw * x - qz * y, qw * y + qz * x, qw * z + qz * w, qw * w - qz * z], axis=-1)


def wrap_angle(angle: float | np.ndarray) -> float | np.ndarray:
    """``angle`` (a float or an array) wrapped into [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi
