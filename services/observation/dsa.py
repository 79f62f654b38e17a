"""Surgical Grasp Any observation: occupancy voxels -> per-object orthographic image (``dsa_occup2``).

Design notes: docs/architecture-notes.md, services/observation/dsa.py."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from proto.episode import DSA_TASKS
from services.observation.dsa_noise import camera_pose_noise, image_noise
from services.observation.image_format import CODE_MAX, DTYPE
from services.observation.projection import finite_float

__all__ = [
    "CONTROLLER_STATES",
    "DSA_TASKS",
    "FSM_STATES",
    "GRIPPER_STATES",
    "STATE_ROW",
    "SURGICAL_GRASP_ANY",
    "DsaSpec",
    "camera_pose_noise",
    "decode_state_rows",
    "dsa_image",
    "dsa_image_from_voxels",
    "image_noise",
    "in_cube",
    "state_blocks",
    "to_occupancy",
    "voxel_centroid",
    "voxelize",
    "world_clouds",
]

GRIPPER_STATES = ("open", "closed")
"""gripper_state values 0, 1."""
FSM_STATES = ("prog_norm", "prog_abnorm_1", "prog_abnorm_2", "prog_abnorm_3", "done_fail", "done_success")
"""fsm_state values 0 .. 5, the reference FSM's states in its order: in progress, normal; abnormal
(1 workspace / z limit, 2 object sliding, 3 gripper toggle); done with failure; done with success."""
CONTROLLER_STATES = ("policy", "p_controller")
"""controller_state values 0, 1: who acts this step."""
STATE_ROW = -1
"""Row of channel 2 that carries the state codes."""
_STATE_SIZES = (len(GRIPPER_STATES), len(FSM_STATES), len(CONTROLLER_STATES))
_STATE_NAMES = ("gripper_state", "fsm_state", "controller_state")
_EMPTY = -1
"""Top-voxel index of an empty column."""


@dataclass(frozen=True)
class DsaSpec:
    """Occupancy grid, crop and codes of the surgical observation (docs/architecture-notes.md)."""

    grid: int = 200
    """Occupancy voxels per side over the cube [-0.5, 0.5]^3 (occupancy units)."""
    scale: float = 1.0
    """Occupancy units per simulator metre (sim is 5x real: the default cube is 1 m sim = 20 cm real)."""
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Simulator point (m) mapped to the cube centre."""
    image: int = 64
    """Output pixels per side."""
    zoom: float = 0.3
    """Crop side as a fraction of the cube, centred on the gripper's (x, y); rounded to whole voxels."""
    window: float = 0.3
    """Depth window width (occupancy units) mapped onto codes 1 .. 255."""
    depth_offset: float = 0.1
    """Window centre = gripper median depth + this (occupancy units; positive = below the gripper)."""
    object_code: int = 70
    """Mask id of the object in channel 2."""
    gripper_code: int = 140
    """Mask id of the gripper in channel 2."""

    def __post_init__(self) -> None:
        for name in ("grid", "image", "object_code", "gripper_code"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f"{name} must be an int, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("scale", "zoom", "window", "depth_offset"):
            object.__setattr__(self, name, finite_float(name, getattr(self, name)))
        origin = tuple(float(v) for v in self.origin)
        if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
            raise ValueError(f"origin must be 3 finite numbers, got {self.origin!r}")
        object.__setattr__(self, "origin", origin)
        if self.grid < 2:
            raise ValueError(f"grid must be >= 2, got {self.grid}")
        if self.image < 3:
            raise ValueError(f"image must be >= 3 (the state row has three blocks), got {self.image}")
        if self.scale <= 0 or self.window <= 0:
            raise ValueError(f"scale and window must be > 0, got {self.scale}, {self.window}")
        if not 0 < self.zoom <= 1 or self.crop_voxels < 1:
            raise ValueError(f"zoom must be in (0, 1] and cover >= 1 voxel, got {self.zoom}")
        codes = (self.object_code, self.gripper_code)
        if not all(1 <= c <= CODE_MAX for c in codes) or codes[0] == codes[1]:
            raise ValueError(f"object_code and gripper_code must be distinct in 1 .. {CODE_MAX}, got {codes}")

    @property
    def crop_voxels(self) -> int:
        """S: crop side in voxels, ``round(zoom * grid)`` (half up)."""
        return math.floor(self.zoom * self.grid + 0.5)


SURGICAL_GRASP_ANY = DsaSpec(origin=(0.0, 0.0, 0.035 * 5.0))
"""The DSA spec of Surgical Grasp Any, the one place it is defined: the env's P-controller and policy
image (``services.tasks.surgical``) and the augmenter's re-projection of MEA copies
(``services.augmenter.core.pipeline.discrete_reprojector``) all use it. Its cube is 1 sim unit
(20 cm real; the simulator is 5x real) on a side, world-aligned, centred on the workspace centre
(0, 0, 0.035 x 5) = (0, 0, 0.175): the reference's 200^3 ``Occup`` grid. Its low corner
(-0.5, -0.5, -0.325) lies on the 0.005 lattice the env downsamples clouds on, so a downsampled
point is one occupied voxel."""


# ------------------------------------------------------------------------------------------------
# Occupancy
# ------------------------------------------------------------------------------------------------


def to_occupancy(
    points_world: np.ndarray, spec: DsaSpec, cam_rotation: np.ndarray | None = None
) -> np.ndarray:
    """(N, 3) sim-world points -> (N, 3) float64 occupancy coordinates ``R ((p - origin) * scale)``.

    ``cam_rotation`` (3x3, optional) is camera pose noise, applied about the cube centre: the part of
    a camera rotation that changes the relative geometry (a rotation about the far camera is this
    plus a common translation, which the gripper-centred crop and depth window cancel).
    """
    pts = np.asarray(points_world, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    q = (pts - np.asarray(spec.origin)) * spec.scale
    if cam_rotation is not None:
        rot = np.asarray(cam_rotation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise ValueError(f"cam_rotation must be a finite 3x3 matrix, got shape {rot.shape}")
        q = q @ rot.T
    return q


def in_cube(points_world: np.ndarray, spec: DsaSpec, cam_rotation: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: which sim-world points ``voxelize`` keeps (inside the cube, finite), by the same
    arithmetic, so a cloud cropped with it voxelises to the same set."""
    c = (to_occupancy(points_world, spec, cam_rotation) + 0.5) * spec.grid
    return np.logical_and(c >= 0, c < spec.grid).all(axis=1)


def voxelize(points_occ: np.ndarray, spec: DsaSpec) -> np.ndarray:
    """(N, 3) occupancy points -> (K, 3) int64 unique voxel indices ``floor((q + 0.5) G)``, sorted
    lexicographically; points outside the cube and non-finite points are dropped."""
    q = np.asarray(points_occ, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {q.shape}")
    G = spec.grid
    c = (q + 0.5) * G
    ok = np.logical_and(c >= 0, c < G).all(axis=1)  # NaN compares False; +-inf fails the range
    idx = c[ok].astype(np.int64)  # truncation == floor since c >= 0
    flat = np.unique((idx[:, 0] * G + idx[:, 1]) * G + idx[:, 2])
    return np.stack([flat // (G * G), flat // G % G, flat % G], axis=1)


def voxel_centroid(
    points_world: np.ndarray, spec: DsaSpec, *, cam_rotation: np.ndarray | None = None
) -> np.ndarray | None:
    """Centroid (occupancy units, (3,) float64) of the occupied voxels' centres, None if none.

    The hybrid P-controller's error is gripper centroid - object centroid (reference ``pid.py``); pass
    the same ``cam_rotation`` as to ``dsa_image`` so controller and image see the same scene.
    """
    vox = voxelize(to_occupancy(points_world, spec, cam_rotation), spec)
    if len(vox) == 0:
        return None
    return (vox.sum(axis=0) / len(vox) + 0.5) / spec.grid - 0.5


# ------------------------------------------------------------------------------------------------
# Image
# ------------------------------------------------------------------------------------------------


def dsa_image(
    gripper_world: np.ndarray,
    object_world: np.ndarray,
    spec: DsaSpec,
    *,
    gripper_state: int,
    fsm_state: int,
    controller_state: int,
    cam_rotation: np.ndarray | None = None,
) -> np.ndarray:
    """Gripper and object clouds (N, 3) in sim-world metres -> (3, image, image) uint8 observation.

    Channels: 0 gripper depth, 1 object depth (top-most voxel per column, window codes 1 .. 255,
    0 empty), 2 mask ids with the state row; cropped around the gripper (docs/architecture-notes.md).
    """
    g = voxelize(to_occupancy(gripper_world, spec, cam_rotation), spec)
    o = voxelize(to_occupancy(object_world, spec, cam_rotation), spec)
    return dsa_image_from_voxels(
        g, o, spec, gripper_state=gripper_state, fsm_state=fsm_state, controller_state=controller_state
    )


def world_clouds(points: np.ndarray, point_counts: np.ndarray, pivot: np.ndarray) -> list[np.ndarray]:
    """The observed points of each segment of one episode row, back in the sim world (float64).

    ``points`` (S, P, 3) are gripper-centric, ``point_counts`` (S,) the distinct points each segment
    had and ``pivot`` the row's ``gripper_pose[:3]``: rows ``[:min(count, P)]`` are distinct observed
    points (the rest repeat them, ``services.tasks.camera.sample_fixed``), returned as
    ``float64(points) + float64(pivot)``. The surgical env renders its policy image from exactly these
    (the float32 values it stores), so re-rendering a stored row reproduces its image bit for bit.
    """
    pts = np.asarray(points)
    counts = np.asarray(point_counts)
    if pts.ndim != 3 or pts.shape[2] != 3 or counts.shape != pts.shape[:1]:
        raise ValueError(
            f"points (S, P, 3) and point_counts (S,) expected, got {pts.shape} and {counts.shape}"
        )
    origin = np.asarray(pivot, dtype=np.float64).reshape(3)
    P = pts.shape[1]
    return [pts[i, : min(int(c), P)].astype(np.float64) + origin for i, c in enumerate(counts)]


def dsa_image_from_voxels(
    gripper_voxels: np.ndarray,
    object_voxels: np.ndarray,
    spec: DsaSpec,
    *,
    gripper_state: int,
    fsm_state: int,
    controller_state: int,
) -> np.ndarray:
    """``dsa_image`` from voxel sets (unique (K, 3) int rows, as ``voxelize`` returns).

    For MEA copies that move the gripper by whole voxels (an action moves 0.05 occupancy units = 10
    voxels at G = 200): shift the indices and re-render without re-voxelising. Rows outside the
    cube are dropped, so shifted sets need no clipping.
    """
    states = _check_states(gripper_state, fsm_state, controller_state)
    G, S, N = spec.grid, spec.crop_voxels, spec.image
    g, o = _in_cube(gripper_voxels, G), _in_cube(object_voxels, G)
    out = np.zeros((3, N, N), DTYPE)
    if len(g):
        g_top, o_top = _top_map(g, G), _top_map(o, G)
        # Crop start x0 = floor(cx + 1/2 - S/2), cx = sum(i)/K + 1/2: integer floor division.
        K = len(g)
        x0, y0 = ((2 * g[:, :2].sum(axis=0) + K * (2 - S)) // (2 * K)).tolist()
        g_crop, o_crop = _crop(g_top, x0, y0, S), _crop(o_top, x0, y0, S)
        d_med = np.median(G - g_top[g_top != _EMPTY] - 0.5)  # voxel units, exact half-integers
        mask = np.zeros((S, S), DTYPE)
        mask[o_crop != _EMPTY] = spec.object_code
        mask[g_crop != _EMPTY] = spec.gripper_code
        src = ((2 * np.arange(N) + 1) * S) // (2 * N)  # centre-aligned nearest neighbour
        rows = np.ix_(src, src)
        out[0] = _depth_codes(g_crop, d_med, spec)[rows]
        out[1] = _depth_codes(o_crop, d_med, spec)[rows]
        out[2] = mask[rows]
    for (start, stop), value, size in zip(state_blocks(N), states, _STATE_SIZES, strict=True):
        out[2, STATE_ROW, start:stop] = _state_code(value, size)
    return out


def _in_cube(voxels: np.ndarray, G: int) -> np.ndarray:
    """(K, 3) int64 rows with every index in [0, G)."""
    v = np.asarray(voxels)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"voxels must have shape (K, 3), got {v.shape}")
    if len(v) and not np.issubdtype(v.dtype, np.integer):
        raise ValueError(f"voxels must be integer indices, got {v.dtype}")
    v = v.astype(np.int64, copy=False)
    return v[((v >= 0) & (v < G)).all(axis=1)]


def _top_map(voxels: np.ndarray, G: int) -> np.ndarray:
    """(G, G) int64 map: the largest k per column (i, j), ``_EMPTY`` for empty columns."""
    top = np.full(G * G, _EMPTY, np.int64)
    np.maximum.at(top, voxels[:, 0] * G + voxels[:, 1], voxels[:, 2])
    return top.reshape(G, G)


def _crop(top: np.ndarray, x0: int, y0: int, S: int) -> np.ndarray:
    """The S x S window of ``top`` starting at (x0, y0), ``_EMPTY`` where it leaves the grid."""
    G = top.shape[0]
    out = np.full((S, S), _EMPTY, top.dtype)
    xa, xb, ya, yb = max(x0, 0), min(x0 + S, G), max(y0, 0), min(y0 + S, G)
    if xa < xb and ya < yb:
        out[xa - x0 : xb - x0, ya - y0 : yb - y0] = top[xa:xb, ya:yb]
    return out


def _depth_codes(top: np.ndarray, d_med: float, spec: DsaSpec) -> np.ndarray:
    """Top-voxel indices -> uint8 window codes ``1 + round(254 t)``, 0 where empty.

    ``t = (c + w/2 - d) / w`` with ``d = (G - k - 0.5) / G``; computed from the exact voxel-unit
    difference ``d_med - D`` so a common z shift of both clouds leaves the codes unchanged.
    """
    G = spec.grid
    rel = d_med - (G - top - 0.5)  # exact: half-integers well inside float64's integer range
    t = (rel / G + spec.depth_offset + 0.5 * spec.window) / spec.window
    codes = np.clip(np.floor((CODE_MAX - 1) * t + 0.5) + 1, 1, CODE_MAX)
    return np.where(top != _EMPTY, codes, 0).astype(DTYPE)


# ------------------------------------------------------------------------------------------------
# State row
# ------------------------------------------------------------------------------------------------


def state_blocks(width: int) -> tuple[tuple[int, int], ...]:
    """Column ranges [start, stop) of gripper_state, fsm_state, controller_state in the state row."""
    a, b = width // 3, 2 * width // 3
    return ((0, a), (a, b), (b, width))


def _state_code(value: int, size: int) -> int:
    """State value 0 .. size - 1 -> code ``value * 255 / (size - 1)`` (an integer for 2 and 6 states)."""
    return value * CODE_MAX // (size - 1)


def _check_states(*values: int) -> tuple[int, ...]:
    """Validate (gripper_state, fsm_state, controller_state) as ints in their ranges."""
    out = []
    for name, value, size in zip(_STATE_NAMES, values, _STATE_SIZES, strict=True):
        if not isinstance(value, int | np.integer) or not 0 <= int(value) < size:
            raise ValueError(f"{name} must be an int in 0 .. {size - 1}, got {value!r}")
        out.append(int(value))
    return tuple(out)


def decode_state_rows(image: np.ndarray) -> tuple[int, int, int]:
    """(gripper_state, fsm_state, controller_state) from a (3, H, W) image's state row.

    Raises ``ValueError`` if a block is not constant or holds no valid code (a corrupted image).
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[0] != 3 or img.shape[2] < 3:
        raise ValueError(f"image must have shape (3, H, W >= 3), got {img.shape}")
    row = img[2, STATE_ROW]
    out = []
    for name, (start, stop), size in zip(_STATE_NAMES, state_blocks(img.shape[2]), _STATE_SIZES, strict=True):
        block = row[start:stop]
        code = int(block[0])
        value = next((v for v in range(size) if _state_code(v, size) == code), None)
        if value is None or np.any(block != code):
            raise ValueError(
                f"state row block {name} holds codes {np.unique(block).tolist()}, not one valid code"
            )
        out.append(value)
    return out[0], out[1], out[2]
