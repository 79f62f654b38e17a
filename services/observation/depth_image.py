"""The `equirsac` variant's policy images: the rendered top-down depth image, quantised and rotated.

Design notes: docs/architecture-notes.md, services/observation/depth_image.py."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from services.observation.image_format import CODE_MAX, DEPTH_CHANNEL, N_CHANNELS, encode

__all__ = ["DepthImageSpec", "DEFAULT_DEPTH_SPEC", "depth_codes", "dequantize_depth", "policy_images",
           "rotate_images", "rotation_matrix"]  # fmt: skip

_CV_MAX_CHANNELS = 512
"""OpenCV's channel limit (CV_CN_MAX): frames are warped in groups of at most this many."""


@dataclass(frozen=True)
class DepthImageSpec:
    """Size and depth range of the rendered baseline image (all lengths in metres)."""

    size: int = 84
    """N: pixels per image side (the public Equi-RSAC image, 0.4 m wide)."""
    far: float = 0.5
    """Depth (m) of code 255: the renderer's clip depth (``render_gripper_depth(far=0.5)``), i.e.
    "nothing seen"; depths are clipped to [0, far]. Covers the whole workspace (docs/architecture-notes.md)."""

    def __post_init__(self) -> None:
        if isinstance(self.size, bool) or not isinstance(self.size, int | np.integer) or self.size < 2:
            raise ValueError(f"size must be an int >= 2, got {self.size!r}")
        object.__setattr__(self, "size", int(self.size))
        if not (isinstance(self.far, int | float | np.floating) and math.isfinite(self.far) and self.far > 0):
            raise ValueError(f"far must be a finite number > 0, got {self.far!r}")
        object.__setattr__(self, "far", float(self.far))

    @property
    def quant_step(self) -> float:
        """Depth of one code step: far / 255 (m); the quantisation error is at most half of it."""
        return self.far / 255.0

    @property
    def centre(self) -> float:
        """Pixel coordinate of the image centre, the rotation pivot: (N - 1) / 2."""
        return (self.size - 1) / 2.0


DEFAULT_DEPTH_SPEC = DepthImageSpec()
"""The public geometry: 84 x 84 px, depths 0 .. 0.5 m."""


def depth_codes(depth: np.ndarray, spec: DepthImageSpec = DEFAULT_DEPTH_SPEC) -> np.ndarray:
    """Depths (..., N, N) (m, any float dtype) -> uint8 codes ``round(clip(d, 0, far) / far * 255)``.

    Arithmetic in float64. For d in [0, far], ``|dequantize_depth(q) - d| <= far / 510`` (~0.98 mm).
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim < 2 or d.shape[-2:] != (spec.size, spec.size):
        raise ValueError(f"depth must have shape (..., {spec.size}, {spec.size}), got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError("depth images must be finite")
    return np.rint(np.clip(d, 0.0, spec.far) * (255.0 / spec.far)).astype(np.uint8)


def dequantize_depth(codes: np.ndarray, spec: DepthImageSpec = DEFAULT_DEPTH_SPEC) -> np.ndarray:
    """uint8 codes -> float32 depths ``q * far / 255`` (m)."""
    return (np.asarray(codes, dtype=np.float64) * spec.quant_step).astype(np.float32)


def policy_images(
    depth: np.ndarray, jaw: np.ndarray, spec: DepthImageSpec = DEFAULT_DEPTH_SPEC
) -> np.ndarray:
    """(T, N, N) depths and (T,) jaw openings -> (T, 2, N, N) uint8 policy stack.

    Channel 0: ``depth_codes``; channel 1: the jaw code ``round(clip(jaw, 0, 1) * 255)`` tiled, with
    the jaw first cast to float32 (``image_format.encode``, as for the voxel image: identical codes).
    """
    d = np.asarray(depth)
    if d.ndim != 3:
        raise ValueError(f"depth must have shape (T, {spec.size}, {spec.size}), got {d.shape}")
    jaw32 = np.asarray(jaw, dtype=np.float32)
    if jaw32.shape != d.shape[:1]:
        raise ValueError(f"jaw must have shape {d.shape[:1]}, got {jaw32.shape}")
    return encode(depth_codes(d, spec), jaw32)


def rotation_matrix(phi: float, size: int) -> np.ndarray:
    """The 2x3 inverse map (destination -> source pixel) in OpenCV's (x = column, y = row) order for a
    world rotation by ``phi`` about the image centre ``c = (size - 1) / 2``::

        src_col = cos(phi) col' - sin(phi) row' + c (1 - cos(phi) + sin(phi))
        src_row = sin(phi) col' + cos(phi) row' + c (1 - cos(phi) - sin(phi))

    (docs/architecture-notes.md's equations with rows = i, columns = j).
    """
    c, s = math.cos(phi), math.sin(phi)
    ctr = (size - 1) / 2.0
    return np.array([[c, -s, ctr * (1.0 - c + s)], [s, c, ctr * (1.0 - c - s)]], np.float64)


def rotate_images(images: np.ndarray, phi: float) -> np.ndarray:
    """Policy stacks (T, 2, N, N) uint8 seen in a world rotated by ``phi`` (rad) about the vertical.

    Channel 0 is warped about the exact centre (N - 1) / 2, bilinear, edges replicated, and rounded
    to the nearest code; channel 1 (jaw) is copied. ``phi = pi / 2`` gives ``np.rot90(k=1)`` over the
    image axes. Returns a new array.
    """
    x = np.asarray(images)
    if x.dtype != np.uint8 or x.ndim != 4 or x.shape[1] != N_CHANNELS or x.shape[2] != x.shape[3]:
        raise ValueError(f"images must be uint8 of shape (T, 2, N, N), got {x.dtype} {x.shape}")
    if not math.isfinite(phi):
        raise ValueError(f"phi must be finite, got {phi!r}")
    T, _, N, _ = x.shape
    out = x.copy()
    if T == 0:
        return out
    M = rotation_matrix(float(phi), N)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for t0 in range(0, T, _CV_MAX_CHANNELS):
        frames = np.ascontiguousarray(
            x[t0 : t0 + _CV_MAX_CHANNELS, DEPTH_CHANNEL].transpose(1, 2, 0), np.float32
        )
        warped = cv2.warpAffine(frames, M, (N, N), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        warped = warped.reshape(N, N, -1)  # a single frame comes back without its channel axis
        codes = np.clip(np.rint(warped), 0, CODE_MAX)
        out[t0 : t0 + _CV_MAX_CHANNELS, DEPTH_CHANNEL] = codes.transpose(2, 0, 1)
    return out
