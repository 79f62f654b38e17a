"""Domain randomisation of the surgical observation: image noise and camera pose noise.

Design notes: docs/architecture-notes.md, services/observation/dsa_noise.py."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["camera_pose_noise", "image_noise"]

_CODE_MAX = 255
_MAX_CUTOUT_TRIES = 3
_N_DISCS = (2, 8)
_N_RECTANGLES = (3, 10)
_N_LINES = (3, 10)


def image_noise(
    image: np.ndarray,
    rng: np.random.Generator,
    *,
    cutout: tuple[float, float] = (0.8, 1.0),
    uniform: float = 0.005,
    blur_sigma: float = 0.3,
    blur_kernel: int = 3,
) -> np.ndarray:
    """Domain-randomisation noise on a (3, H, W) uint8 DSA image -> a new image (input untouched).

    Only channels 0 and 1 (depth codes) change; channel 2 (mask ids, state row) is copied bit for bit.
    ``blur_sigma <= 0`` or ``blur_kernel <= 1`` skips the blur, ``uniform <= 0`` the noise.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[0] != 3:
        raise ValueError(f"image must be uint8 of shape (3, H, W), got {img.dtype} {img.shape}")
    lo, hi = (float(v) for v in cutout)
    if not 0 <= lo <= hi:
        raise ValueError(f"cutout must be (lo, hi) with 0 <= lo <= hi, got {cutout!r}")
    if blur_kernel > 1 and blur_kernel % 2 == 0:
        raise ValueError(f"blur_kernel must be odd, got {blur_kernel}")
    out = img.copy()
    occ = img[:2] > 0
    depth = img[:2].astype(np.float64)
    if blur_sigma > 0 and blur_kernel > 1:
        depth = _masked_blur(depth, occ, blur_kernel, blur_sigma)
    if uniform > 0:
        depth += rng.uniform(-0.5 * uniform, 0.5 * uniform, depth.shape) * _CODE_MAX
    codes = np.where(occ, np.clip(np.floor(depth + 0.5), 1, _CODE_MAX), 0)
    if lo < 1:
        codes[:, _cutout_mask(occ, rng, lo, hi)] = 0
    out[:2] = codes.astype(np.uint8)
    return out


def _gaussian_kernel(size: int, sigma: float) -> np.ndarray:
    """1-D normalised Gaussian of odd ``size`` (``cv2.getGaussianKernel`` for sigma > 0)."""
    x = np.arange(size) - (size - 1) / 2
    k = np.exp(-(x**2) / (2 * sigma**2))
    return k / k.sum()


def _conv_same(a: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Separable 'same' correlation of (..., H, W) with the 1-D kernel on both axes, zero padding."""
    r = len(k) // 2
    p = np.pad(a, [(0, 0)] * (a.ndim - 2) + [(r, r), (r, r)])
    H, W = a.shape[-2:]
    rows = sum(k[t] * p[..., t : t + H, :] for t in range(len(k)))
    return sum(k[t] * rows[..., :, t : t + W] for t in range(len(k)))


def _masked_blur(values: np.ndarray, occ: np.ndarray, size: int, sigma: float) -> np.ndarray:
    """Gaussian average over occupied pixels only; empty pixels keep their value (they are masked out)."""
    k = _gaussian_kernel(size, sigma)
    num = _conv_same(values * occ, k)
    den = _conv_same(occ.astype(np.float64), k)
    return np.where(occ, num / np.where(occ, den, 1.0), values)


def _cutout_mask(occ: np.ndarray, rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    """(H, W) bool pixels to empty: the first shape draw that keeps each channel's occupied fraction
    in [lo, hi], or no pixel if none of ``_MAX_CUTOUT_TRIES`` draws does."""
    H, W = occ.shape[-2:]
    counts = occ.sum(axis=(-2, -1))
    for _ in range(_MAX_CUTOUT_TRIES):
        cut = _draw_shapes(rng, H, W)
        kept = (occ & ~cut).sum(axis=(-2, -1))
        frac = np.divide(kept, counts, out=np.ones(len(counts)), where=counts > 0)
        if np.all((frac >= lo) & (frac <= hi)):
            return cut
    return np.zeros((H, W), dtype=bool)


def _draw_shapes(rng: np.random.Generator, H: int, W: int) -> np.ndarray:
    """Union of random discs, rotated rectangles and lines on an H x W pixel grid (pixel centres)."""
    side = min(H, W)
    n_disc, n_rect, n_line = (int(rng.integers(a, b + 1)) for a, b in (_N_DISCS, _N_RECTANGLES, _N_LINES))
    r = np.arange(H)[:, None] + 0.5
    c = np.arange(W)[None, :] + 0.5
    cut = np.zeros((H, W), dtype=bool)
    for _ in range(n_disc):
        cr, cc = rng.uniform(0, H), rng.uniform(0, W)
        radius = rng.uniform(0.01, 0.2) * side / 2
        cut |= (r - cr) ** 2 + (c - cc) ** 2 <= radius**2
    boxes = [(rng.uniform(0.1, 0.2) * H, rng.uniform(0.1, 0.2) * W) for _ in range(n_rect)]
    boxes += [(max(rng.uniform(0.5, 1.0) * 0.01 * H, 1.0), rng.uniform(0.9, 1.0) * W) for _ in range(n_line)]
    for width, length in boxes:
        cr, cc, angle = rng.uniform(0, H), rng.uniform(0, W), rng.uniform(0, math.pi)
        u = (r - cr) * math.cos(angle) + (c - cc) * math.sin(angle)
        v = -(r - cr) * math.sin(angle) + (c - cc) * math.cos(angle)
        cut |= (np.abs(u) <= width / 2) & (np.abs(v) <= length / 2)
    return cut


def camera_pose_noise(
    rng: np.random.Generator, z: float = 0.01, angles_deg: tuple[float, float, float] = (3.0, 3.0, 1.0)
) -> np.ndarray:
    """A random 3x3 rotation ``Rz(c) Ry(b) Rx(a)``, ``a, b, c ~ U(-angles_deg, +angles_deg)`` drawn
    in that order: the reference's +-3 degree pitch / roll and +-1 degree about the up axis. Pass it
    as ``cam_rotation`` (applied about the cube centre) to ``dsa_image`` *and* ``voxel_centroid``.

    The z part (the reference's +-``z`` m jitter of the camera distance) is not in the result and is
    not drawn: it moves both clouds by the same vector, and the image is relative to the gripper
    (crop centred on its centroid, depth window on its median depth) and the P-controller's error is
    a difference of centroids, so it cancels except for the sub-voxel phase of the voxel boundaries.
    ``z`` is kept for the reference's parameter list and checked (finite, >= 0) only.
    """
    if not (math.isfinite(z) and z >= 0):
        raise ValueError(f"z must be finite and >= 0, got {z!r}")
    limits = np.radians(np.asarray(angles_deg, dtype=np.float64))
    if limits.shape != (3,) or not np.all(np.isfinite(limits)) or np.any(limits < 0):
        raise ValueError(f"angles_deg must be 3 finite numbers >= 0, got {angles_deg!r}")
    a, b, c = rng.uniform(-limits, limits)
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    ry = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    rz = np.array([[cc, -sc, 0.0], [sc, cc, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx
