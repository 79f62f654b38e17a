"""Voxel-based orthogonal projection of gripper-centric point clouds (MEA paper, Sec. VI).

Design notes: docs/architecture-notes.md, services/observation/projection.py."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from services.observation.image_format import (
    DEPTH_CHANNEL,
    JAW_CHANNEL,
    N_CHANNELS,
    decode_jaw,
    encode,
    encode_jaw,
)

__all__ = [
    "ProjectionSpec",
    "dequantize",
    "dequantize_depth",
    "depth_indices",
    "finite_float",
    "observation_channels",
    "project",
    "project_batch",
    "quantize",
    "quantize_depth",
    "quantized_observations",
    "segment_policy_images",
    "segments_to_points",
]

_EMPTY = 255
"""Depth-index code of an empty column inside `project_batch` (real indices are < 254)."""
_CHUNK_POINTS = 16384
"""`project_batch` handles frames in groups of about this many points (at least one frame)."""
_AXIS_SIGN = np.array([[1.0], [1.0], [-1.0]])
"""Flips z so that the third voxel coordinate counts downward."""


def finite_float(name: str, value: object) -> float:
    """A settings field as a float: a finite real number (not a bool), else a ValueError naming it."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class ProjectionSpec:
    """Geometry of the voxel grid and of the projected image (all lengths in metres)."""

    size: int = 84
    """N: pixels per image side (= voxels per grid side in x and y)."""
    voxel: float = 0.4 / 84
    """v: voxel edge (m)."""
    z_top: float = 0.1
    """Height (m) of the grid's top plane above the gripper."""
    depth: float = 0.6
    """Grid depth (m) below z_top; deeper points are ignored."""

    def __post_init__(self) -> None:
        if isinstance(self.size, bool) or not isinstance(self.size, int | np.integer) or self.size < 2:
            raise ValueError(f"size must be an int >= 2, got {self.size!r}")
        object.__setattr__(self, "size", int(self.size))
        for name in ("voxel", "z_top", "depth"):
            object.__setattr__(self, name, finite_float(name, getattr(self, name)))
        if self.voxel <= 0:
            raise ValueError(f"voxel must be > 0, got {self.voxel}")
        if self.depth < self.voxel:
            raise ValueError(f"depth ({self.depth}) must be at least one voxel ({self.voxel})")
        if self.depth >= 254 * self.voxel:
            # Keeps the uint8 quantisation step s = (depth + v) / 255 strictly below one voxel, so
            # distinct depth levels get distinct nonzero codes (see `quantize_depth`), and keeps every
            # depth index k below the empty code 255 of `project_batch`.
            raise ValueError(f"depth ({self.depth}) must be less than 254 voxels ({254 * self.voxel})")
        # Lookup table depth index -> pixel value, (k + 0.5) v, with the empty code 255 -> 0.
        levels = ((np.arange(256) + 0.5) * self.voxel).astype(np.float32)
        levels[_EMPTY] = 0.0
        levels.flags.writeable = False
        object.__setattr__(self, "_depth_levels", levels)  # not a field: eq / hash / repr ignore it

    @property
    def depth_levels(self) -> np.ndarray:
        """Read-only float32 table (256,): entry k is the pixel value (k + 0.5) v; entry 255 is 0 (empty)."""
        return self._depth_levels

    @property
    def half_extent(self) -> float:
        """Half the side of the grid's xy square: N v / 2 (m)."""
        return 0.5 * self.size * self.voxel

    @property
    def max_value(self) -> float:
        """Upper end of the depth range used by `quantize`: depth + v (>= every projected value)."""
        return self.depth + self.voxel

    @property
    def quant_step(self) -> float:
        """Depth quantisation step of `quantize`: max_value / 255 (m); the error is at most half of it."""
        return self.max_value / 255.0


DEFAULT_SPEC = ProjectionSpec()
"""The paper's geometry: 84 x 84 px over 0.4 m."""


# ------------------------------------------------------------------------------------------------
# Projection
# ------------------------------------------------------------------------------------------------


def project_batch(
    points: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC, valid: np.ndarray | None = None
) -> np.ndarray:
    """Project T clouds at once: (T, M, 3) -> (T, N, N) float32.

    ``I[t, i, j] = (min k + 0.5) v`` over the valid points of frame t in column (i, j), 0 when the
    column is empty (see docs/architecture-notes.md for i, j, k). ``valid`` (T, M) bool, optional, drops
    points (e.g. filler points of unseen segments); NaN / inf and out-of-grid points are always
    dropped.

    Vectorised across frames: frames are processed in groups of about ``_CHUNK_POINTS`` points, each
    group with one ``np.minimum.at`` over its flat (frames * N * N) image. Grouping keeps the
    temporaries small and cache-resident; a single pass over, say, 50 x 3072 points would spend most
    of its time in page faults of ~10 MB of fresh temporaries.
    """
    kmin = depth_indices(points, spec, valid)
    return spec.depth_levels.take(kmin)  # (k + 0.5) v; 0 if empty (code 255)


def depth_indices(
    points: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC, valid: np.ndarray | None = None
) -> np.ndarray:
    """The integer core of `project_batch`: (T, M, 3) -> (T, N, N) uint8 topmost depth index.

    Entry ``[t, i, j]`` is ``min k`` over the valid points of frame t in column (i, j), or 255 when
    the column is empty; ``project_batch`` is ``spec.depth_levels[depth_indices(...)]``.
    """
    pts = np.asarray(points)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points must have shape (T, M, 3), got {pts.shape}")
    T, M, _ = pts.shape
    N = spec.size
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (T, M):
            raise ValueError(f"valid must have shape {(T, M)}, got {valid.shape}")
    kmin = np.full((T, N, N), _EMPTY, np.uint8)
    if M == 0:
        return kmin
    kmin_flat = kmin.reshape(T * N * N)  # a view: `kmin` is contiguous
    step = max(1, _CHUNK_POINTS // M)
    for t0 in range(0, T, step):
        frames = slice(t0, t0 + step)
        pixels = slice(t0 * N * N, (t0 + step) * N * N)
        _project_frames(pts[frames], spec, None if valid is None else valid[frames], kmin_flat[pixels])
    return kmin


def _project_frames(
    pts: np.ndarray, spec: ProjectionSpec, valid: np.ndarray | None, kmin: np.ndarray
) -> None:
    """Core of `depth_indices` for F frames: (F, M, 3) points -> flat ``kmin`` (F * N * N,) uint8,
    filled with 255 (empty) on entry; each occupied column gets its smallest depth index."""
    F, M, _ = pts.shape
    N = spec.size
    # Continuous voxel coordinates, one row per axis (so every step is a long 1-D loop):
    #   c = ((x + h) / v, (y + h) / v, (z_top - z) / v),   h = N v / 2,
    # in float64 whatever the input dtype; the voxel indices (i, j, k) are floor(c).
    v, h = spec.voxel, spec.half_extent
    c = np.empty((3, F * M), np.float64)
    np.multiply(pts.reshape(F * M, 3).T, _AXIS_SIGN, out=c)  # (x, y, -z): the sign flip is exact
    c += np.array([[h], [h], [spec.z_top]])
    c /= v
    # Keep 0 <= c < (N, N, depth / v). Comparisons with NaN are False and +-inf fails the range
    # check, so non-finite points drop out here too.
    ok = c >= 0
    ok &= c < np.array([[N], [N], [spec.depth / v]])
    ok = np.logical_and.reduce(ok, axis=0)
    if valid is not None:
        ok &= valid.reshape(F * M)
    idx = np.flatnonzero(ok)

    ijk = c.take(idx, axis=1).astype(np.intp)  # floor == truncation, since c >= 0
    flat = ijk[0] * N + ijk[1]  # pixel (i, j) of frame t sits at flat index (t N + i) N + j
    if F > 1:
        flat += (idx // M) * (N * N)
    k = ijk[2].astype(np.uint8)  # k < depth / v < 254 (see ProjectionSpec)
    np.minimum.at(kmin, flat, k)


def project(points: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC) -> np.ndarray:
    """Project one cloud: (M, 3) gripper-centric points -> (N, N) float32 depth-from-top image.

    ``I[i, j] = (min k + 0.5) v`` over the points in column (i, j), 0 for an empty column, with
    ``i = floor((x + h)/v)`` (row, +x), ``j = floor((y + h)/v)`` (column, +y), ``h = N v / 2``, and
    ``k = floor((z_top - z)/v)``. NaN / inf points and points outside the grid are ignored.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (M, 3), got {pts.shape}")
    return project_batch(pts[None], spec)[0]


def segments_to_points(points: np.ndarray, counts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Flatten wire-format segmented clouds: (T, S, P, 3) -> points (T, S*P, 3), valid (T, S*P) bool.

    ``counts`` (T, S) are the points observed per segment before resampling; a segment with count 0
    was not seen and its P points are filler, so they are marked invalid. ``counts=None``: all valid.
    The result plugs straight into ``project_batch(points, spec, valid)``.
    """
    pts = np.asarray(points)
    if pts.ndim != 4 or pts.shape[3] != 3:
        raise ValueError(f"points must have shape (T, S, P, 3), got {pts.shape}")
    T, S, P, _ = pts.shape
    flat = pts.reshape(T, S * P, 3)
    if counts is None:
        return flat, np.ones((T, S * P), dtype=bool)
    counts = np.asarray(counts)
    if counts.shape != (T, S):
        raise ValueError(f"counts must have shape {(T, S)}, got {counts.shape}")
    valid = np.repeat(counts > 0, P, axis=1)  # (T, S) -> (T, S*P), segment-major like `flat`
    return flat, valid


# ------------------------------------------------------------------------------------------------
# Policy input and compact storage
# ------------------------------------------------------------------------------------------------


def observation_channels(
    depth_images: np.ndarray, jaw: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC
) -> np.ndarray:
    """Stack the policy input: (T, N, N) depth images and (T,) jaw openings -> (T, 2, N, N) float32.

    Channel 0 is the depth image, channel 1 the jaw opening (0 closed .. 1 open) tiled over the image.
    """
    depth = np.asarray(depth_images, dtype=np.float32)
    jaw = np.asarray(jaw, dtype=np.float32)
    N = spec.size
    if depth.ndim != 3 or depth.shape[1:] != (N, N):
        raise ValueError(f"depth_images must have shape (T, {N}, {N}), got {depth.shape}")
    if jaw.shape != depth.shape[:1]:
        raise ValueError(f"jaw must have shape {depth.shape[:1]}, got {jaw.shape}")
    out = np.empty((depth.shape[0], N_CHANNELS, N, N), np.float32)
    out[:, DEPTH_CHANNEL] = depth
    out[:, JAW_CHANNEL] = jaw[:, None, None]
    return out


def quantize_depth(depth: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC) -> np.ndarray:
    """Depth values -> uint8 codes: 0 (empty, value <= 0) stays 0; d > 0 -> clip(round(d / s), 1, 255).

    ``s = spec.quant_step = (depth + v) / 255``. For every d in ``[s/2, depth + v]`` (which holds all
    projected values, since they are >= v/2 > s/2) ``|dequantize_depth(q) - d| <= s / 2`` (~0.8 mm
    with the default spec), plus float32 rounding of the values (< 1e-7 m). With the default spec
    every level (k + 0.5) v = (3 k + 1.5) s is a rounding tie, so the bound is attained. Since ``s < v`` (``depth < 254 v``, checked by ProjectionSpec), the depth
    levels ``(k + 0.5) v``, one voxel apart, get distinct codes >= 1.
    """
    d = np.asarray(depth, dtype=np.float64)
    q = np.clip(np.rint(d / spec.quant_step), 1, 255)
    return np.where(d > 0, q, 0).astype(np.uint8)


def dequantize_depth(codes: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC) -> np.ndarray:
    """uint8 codes -> float32 depth: ``q * s`` (code 0 -> exactly 0, i.e. empty)."""
    return (np.asarray(codes, dtype=np.float32) * np.float32(spec.quant_step)).astype(np.float32)


def quantize(images: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC) -> np.ndarray:
    """Observation stacks (..., 2, N, N) float -> uint8, for a compact replay buffer.

    * depth channel: ``quantize_depth`` (0 reserved for empty; error <= ``spec.quant_step / 2``,
      about 0.8 mm with the default spec);
    * jaw channel: ``round(clip(jaw, 0, 1) * 255)`` (error <= 1 / 510).
    """
    x = np.asarray(images)
    if x.ndim < 3 or x.shape[-3] != N_CHANNELS:
        raise ValueError(f"images must have shape (..., {N_CHANNELS}, N, N), got {x.shape}")
    out = np.empty(x.shape, np.uint8)
    out[..., DEPTH_CHANNEL, :, :] = quantize_depth(x[..., DEPTH_CHANNEL, :, :], spec)
    out[..., JAW_CHANNEL, :, :] = encode_jaw(x[..., JAW_CHANNEL, :, :])
    return out


def dequantize(codes: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC) -> np.ndarray:
    """Inverse of `quantize`: uint8 (..., 2, N, N) -> float32 (..., 2, N, N)."""
    q = np.asarray(codes)
    if q.dtype != np.uint8 or q.ndim < 3 or q.shape[-3] != N_CHANNELS:
        raise ValueError(f"codes must be uint8 of shape (..., {N_CHANNELS}, N, N), got {q.dtype} {q.shape}")
    out = np.empty(q.shape, np.float32)
    out[..., DEPTH_CHANNEL, :, :] = dequantize_depth(q[..., DEPTH_CHANNEL, :, :], spec)
    out[..., JAW_CHANNEL, :, :] = decode_jaw(q[..., JAW_CHANNEL, :, :])
    return out


@functools.lru_cache(maxsize=16)
def _depth_codes(spec: ProjectionSpec) -> np.ndarray:
    """Read-only uint8 table (256,): ``quantize_depth`` of each entry of ``spec.depth_levels``."""
    codes = quantize_depth(spec.depth_levels, spec)
    codes.flags.writeable = False
    return codes


def quantized_observations(
    points: np.ndarray, jaw: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC, valid: np.ndarray | None = None
) -> np.ndarray:
    """``quantize(observation_channels(project_batch(points, spec, valid), jaw, spec), spec)``, bit for
    bit, without the float intermediates: (T, M, 3) points and (T,) jaw -> (T, 2, N, N) uint8.

    Every projected pixel is one of 256 values ``depth_levels[k]``, so its code is a table lookup
    ``quantize_depth(depth_levels)[k]``; the jaw code is computed once per frame and tiled.
    """
    kmin = depth_indices(points, spec, valid)
    jaw32 = np.asarray(jaw, dtype=np.float32)
    if jaw32.shape != kmin.shape[:1]:
        raise ValueError(f"jaw must have shape {kmin.shape[:1]}, got {jaw32.shape}")
    return encode(_depth_codes(spec).take(kmin), jaw32)


def segment_policy_images(
    points: np.ndarray, point_counts: np.ndarray, jaw: np.ndarray, spec: ProjectionSpec = DEFAULT_SPEC
) -> np.ndarray:
    """Policy images of segmented observations: (T, S, P, 3) points with (T, S) counts and (T,) jaw
    -> (T, 2, N, N) uint8. The one path from observations to images, for stored episodes (augmenter)
    and live observations (actors, evaluator) alike, so both are bit-identical."""
    flat, valid = segments_to_points(points, point_counts)
    return quantized_observations(flat, jaw, spec, valid)
