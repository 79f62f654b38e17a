"""Fixed depth cameras with segmentation masks, fused into per-segment point clouds.

Several views around the workspace are rendered (pybullet's tiny renderer, which skips the
invisible arm), each depth pixel of a segment is back-projected to the world, the views are fused,
voxel-downsampled (so denser views don't pull the centroid), and a fixed number of points is drawn
per segment. Several views mean the gripper never hides an object during the approach.

Also renders the baseline the paper compares against: the public Equi-RSAC observation, a
top-down orthographic depth image centred on the gripper; and a third-person colour picture of the
scene for videos (``SceneView``, ``scene_image``), which no policy observes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pybullet as pb

WORKSPACE_CENTRE = (0.5, 0.0, 0.08)


def _default_views() -> tuple[tuple[float, float, float], ...]:
    """(azimuth deg, elevation deg, distance m) of each camera around the workspace centre."""
    return (
        (45.0, 50.0, 0.95),
        (135.0, 50.0, 0.95),
        (225.0, 50.0, 0.95),
        (315.0, 50.0, 0.95),
        (0.0, 89.0, 1.0),
    )


@dataclass(frozen=True)
class CameraSettings:
    """Camera rig and point sampling."""

    image_size: int = 128
    """Pixels per side of each view (128 keeps the observed gripper yaw within ~1 degree)."""
    fov_deg: float = 42.0
    """Vertical field of view of each view."""
    views: tuple[tuple[float, float, float], ...] = field(default_factory=_default_views)
    """(azimuth deg, elevation deg, distance m) of each camera, looking at the workspace centre."""
    points_per_segment: int = 256
    """Fixed number of points drawn per segment (with replacement when fewer are seen)."""
    downsample_voxel: float = 0.004
    """Voxel edge (m) of the fusion downsampling: one point per occupied voxel."""
    near: float = 0.2
    """Near clipping plane (m)."""
    far: float = 2.5
    """Far clipping plane (m)."""


@dataclass(frozen=True)
class SceneView:
    """A third-person colour camera for videos (pybullet's yaw/pitch convention, degrees)."""

    size: int = 256
    """Pixels per side."""
    target: tuple[float, float, float] = WORKSPACE_CENTRE
    """Point looked at."""
    distance: float = 0.85
    yaw_deg: float = 90.0
    """90: from in front of the workspace, facing the arm's base (the arm comes in from the top)."""
    pitch_deg: float = -45.0
    fov_deg: float = 50.0


def render_rgb(client: int, view: SceneView = SceneView()) -> np.ndarray:
    """The scene as ``view`` sees it: (size, size, 3) uint8, pybullet's tiny renderer (no GPU, no
    window; shapes with alpha 0 are skipped, as for the observation's cameras)."""
    n = view.size
    matrix = pb.computeViewMatrixFromYawPitchRoll(
        view.target, view.distance, view.yaw_deg, view.pitch_deg, 0.0, 2
    )
    proj = pb.computeProjectionMatrixFOV(view.fov_deg, 1.0, 0.05, 10.0)
    _, _, rgba, _, _ = pb.getCameraImage(
        n, n, matrix, proj, renderer=pb.ER_TINY_RENDERER, flags=pb.ER_NO_SEGMENTATION_MASK,
        physicsClientId=client,
    )  # fmt: skip
    return np.asarray(rgba, np.uint8).reshape(n, n, 4)[..., :3].copy()


def scene_image(env, size: int = 256) -> np.ndarray:
    """A third-person picture of ``env``'s scene: its own ``render_scene`` where it has one (the
    general tasks show the arm and floor their cameras skip), else looking at its camera's target
    from 30 degrees aside and higher up (the surgical task's oblique camera)."""
    own = getattr(env, "render_scene", None)
    if own is not None:
        return own(size)
    cam = env.settings.camera
    view = SceneView(size=size, target=tuple(cam.target), distance=cam.distance, yaw_deg=cam.yaw_deg + 30.0,
                     pitch_deg=-35.0, fov_deg=cam.fov_deg)  # fmt: skip
    return render_rgb(env.client, view)


@dataclass
class _View:
    view: list[float]
    proj: list[float]
    inv_vp: np.ndarray  # 4x4 inverse of proj @ view (column-vector convention)


class Cameras:
    """Renders the rig and returns world-frame points per segment."""

    def __init__(self, client: int, settings: CameraSettings = CameraSettings()) -> None:
        self.client = client
        self.s = settings
        proj = pb.computeProjectionMatrixFOV(settings.fov_deg, 1.0, settings.near, settings.far)
        self.views: list[_View] = []
        cx, cy, cz = WORKSPACE_CENTRE
        for az, el, dist in settings.views:
            a, e = math.radians(az), math.radians(el)
            eye = (
                cx + dist * math.cos(e) * math.cos(a),
                cy + dist * math.cos(e) * math.sin(a),
                cz + dist * math.sin(e),
            )
            up = (0.0, 0.0, 1.0) if el < 80 else (-1.0, 0.0, 0.0)
            view = pb.computeViewMatrix(eye, WORKSPACE_CENTRE, up)
            vp = np.array(proj).reshape(4, 4).T @ np.array(view).reshape(4, 4).T
            self.views.append(_View(view, proj, np.linalg.inv(vp)))
        n = settings.image_size
        # pixel centres in normalised device coordinates (row 0 = top of the image)
        xs = (np.arange(n) + 0.5) / n * 2 - 1
        self._ndc_x = np.tile(xs, n)
        self._ndc_y = np.repeat(-xs, n)

    def render_segments(self, segments: dict[str, list[tuple[int, int | None]]]) -> dict[str, np.ndarray]:
        """World points seen of each segment, fused over views and voxel-downsampled.

        ``segments`` maps a name to (body id, link index or None for any link) pairs."""
        n = self.s.image_size
        code_to_name: dict[int, str] = {}
        body_to_name: dict[int, str] = {}
        for name, parts in segments.items():
            for body, link in parts:
                if link is None:
                    body_to_name[body] = name
                else:
                    code_to_name[body + ((link + 1) << 24)] = name
        found: dict[str, list[np.ndarray]] = {name: [] for name in segments}
        for v in self.views:
            _, _, _, depth, seg = pb.getCameraImage(
                n, n, v.view, v.proj, renderer=pb.ER_TINY_RENDERER,
                flags=pb.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX, physicsClientId=self.client,
            )  # fmt: skip
            seg = np.asarray(seg).reshape(-1)
            depth = np.asarray(depth, dtype=np.float64).reshape(-1)
            hit = seg >= 0
            bodies = np.where(hit, seg & ((1 << 24) - 1), -1)
            for name in segments:
                mask = np.zeros(seg.shape, bool)
                for code, nm in code_to_name.items():
                    if nm == name:
                        mask |= seg == code
                for body, nm in body_to_name.items():
                    if nm == name:
                        mask |= bodies == body
                if mask.any():
                    found[name].append(self._unproject(v, mask, depth))
        return {name: _downsample(np.concatenate(pts) if pts else np.zeros((0, 3)), self.s.downsample_voxel)
                for name, pts in found.items()}  # fmt: skip

    def _unproject(self, v: _View, mask: np.ndarray, depth: np.ndarray) -> np.ndarray:
        z_ndc = depth[mask] * 2 - 1
        clip = np.stack([self._ndc_x[mask], self._ndc_y[mask], z_ndc, np.ones_like(z_ndc)])
        world = v.inv_vp @ clip
        return (world[:3] / world[3]).T


def _downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point (the mean) per occupied voxel, in the voxels' (x, y, z) index order."""
    if len(points) == 0:
        return points.astype(np.float64)
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse, counts = np.unique(_voxel_ids(keys), return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.reshape(-1), points)
    return sums / counts[:, None]


def _voxel_ids(keys: np.ndarray) -> np.ndarray:
    """(n, 3) integer voxel indices -> one integer per voxel, ordered as the rows are in lexicographic
    order: np.unique on these gives the groups and order of np.unique(keys, axis=0) at a fraction of
    its cost (a row-wise unique sorts structured rows: a fifth of an env step went there)."""
    k = keys - keys.min(axis=0)
    span = k.max(axis=0) + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0**62:  # not in one int64: by rows
        return np.unique(keys, axis=0, return_inverse=True)[1].reshape(-1)
    return (k[:, 0] * span[1] + k[:, 1]) * span[2] + k[:, 2]


def sample_fixed(points: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Exactly ``count`` points: a random subset, or all of them plus repeats when fewer.

    Returns (points (count, 3), number of distinct points available). An unseen segment gives
    zeros and 0."""
    n = len(points)
    if n == 0:
        return np.zeros((count, 3)), 0
    if n >= count:
        idx = rng.choice(n, size=count, replace=False)
    else:
        idx = np.concatenate([np.arange(n), rng.integers(0, n, size=count - n)])
    return points[idx], n


FINGER_THICKNESS = 0.012  # m, painted finger size across the closing axis ...
FINGER_WIDTH = 0.025  # ... and along the other horizontal axis


def paint_fingers(
    image: np.ndarray, centre: np.ndarray, grip: np.ndarray, yaw: float, gap: float, span: float
) -> np.ndarray:
    """Paint the two fingers as 0-depth rectangles (the public tasks' convention): centred
    ``gap/2`` either side of the grip point along the closing axis (heading ``yaw``)."""
    n = image.shape[0]
    px = span / n
    coords = (np.arange(n) + 0.5 - n / 2) * px
    gx = centre[0] + coords[:, None]  # row -> +x
    gy = centre[1] + coords[None, :]  # column -> +y
    u = np.array([math.cos(yaw), math.sin(yaw)])
    out = image.copy()
    for sign in (1.0, -1.0):
        fc = grip[:2] + sign * (gap / 2 + FINGER_THICKNESS / 2) * u
        du = (gx - fc[0]) * u[0] + (gy - fc[1]) * u[1]
        dv = -(gx - fc[0]) * u[1] + (gy - fc[1]) * u[0]
        out[(np.abs(du) <= FINGER_THICKNESS / 2) & (np.abs(dv) <= FINGER_WIDTH / 2)] = 0.0
    return out


TELEPHOTO_DISTANCE = 5.0  # m: the baseline camera looks from far above through a narrow lens


def render_gripper_depth(
    client: int, centre: np.ndarray, size: int = 84, span: float = 0.4, height: float = 0.06, far: float = 0.5
) -> np.ndarray:
    """Baseline observation of the public Equi-RSAC tasks: top-down depth image centred on the
    gripper, ``span`` m wide at ``height`` above the gripper, values = depth below that plane (m),
    clipped to ``far``; up-vector -x, so rows follow +x and columns +y (the public pairing).

    pybullet's tiny renderer has no usable orthographic mode, so the camera sits
    TELEPHOTO_DISTANCE above that plane with a narrow field of view: nearly orthographic (scale
    changes by height/distance, under 9% over the 0.44 m between the gripper and the floor).
    The caller hides the gripper's own links (they would block the view) and paints its fingers."""
    plane = float(centre[2]) + height
    # the tiny renderer samples pixel corners; shifting half a pixel puts the gripper on the corner
    # between the four centre pixels, as the voxel projection does (rows +x, columns +y)
    half = span / size / 2
    eye = (float(centre[0]) - half, float(centre[1]) + half, plane + TELEPHOTO_DISTANCE)
    view = pb.computeViewMatrix(eye, (eye[0], eye[1], plane), (-1.0, 0.0, 0.0))
    fov = math.degrees(2 * math.atan(span / 2 / TELEPHOTO_DISTANCE))
    near, farp = TELEPHOTO_DISTANCE - 0.05, TELEPHOTO_DISTANCE + far
    proj = pb.computeProjectionMatrixFOV(fov, 1.0, near, farp)
    _, _, _, depth, _ = pb.getCameraImage(
        size, size, view, proj, renderer=pb.ER_TINY_RENDERER, flags=pb.ER_NO_SEGMENTATION_MASK,
        physicsClientId=client,
    )  # fmt: skip
    d = np.asarray(depth, dtype=np.float64).reshape(size, size)
    z = farp * near / (farp - (farp - near) * d)  # OpenGL depth buffer -> distance along the axis
    return np.clip(z - TELEPHOTO_DISTANCE, 0.0, far).astype(np.float32)
