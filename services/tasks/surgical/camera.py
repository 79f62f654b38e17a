"""The oblique camera of Surgical Grasp Any: depth + segmentation, back-projected to world points.

One fixed view (the reference's FOV 45 degrees, yaw 180, pitch -20, distance 0.2 x SCALING, looking
at the workspace centre: from the +y side, 20 degrees above the tray), rendered with pybullet's tiny
renderer. Each segment's masked depth pixels are back-projected with the *nominal* camera: when
domain randomisation moves the rendering camera, the points carry that calibration error, as
a real stereo camera's would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as pb

from services.tasks.surgical.settings import RandomisationSettings, SurgicalCameraSettings


@dataclass(frozen=True)
class CameraPose:
    """Offsets of the rendering camera from the nominal one (domain randomisation)."""

    distance: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    yaw_deg: float = 0.0

    @staticmethod
    def draw(r: RandomisationSettings, rng: np.random.Generator) -> CameraPose:
        u = rng.uniform(-1.0, 1.0, 4)
        return CameraPose(u[0] * r.camera_distance, u[1] * r.camera_pitch_deg, u[2] * r.camera_roll_deg,
                          u[3] * r.camera_yaw_deg)  # fmt: skip


def _view(s: SurgicalCameraSettings, pose: CameraPose) -> list[float]:
    return pb.computeViewMatrixFromYawPitchRoll(
        s.target, s.distance + pose.distance, s.yaw_deg + pose.yaw_deg, s.pitch_deg + pose.pitch_deg,
        s.roll_deg + pose.roll_deg, 2,
    )  # fmt: skip


class ObliqueCamera:
    """Renders the view and turns masks into world points (nominal back-projection)."""

    def __init__(self, settings: SurgicalCameraSettings) -> None:
        self.s = settings
        self.proj = pb.computeProjectionMatrixFOV(settings.fov_deg, 1.0, settings.near, settings.far)
        nominal = _view(settings, CameraPose())
        vp = np.array(self.proj).reshape(4, 4).T @ np.array(nominal).reshape(4, 4).T
        self.inv_vp = np.linalg.inv(vp)
        self.render_view = nominal
        n = settings.image_size
        xs = (np.arange(n) + 0.5) / n * 2 - 1  # pixel centres in normalised device coordinates
        self._ndc_x = np.tile(xs, n)
        self._ndc_y = np.repeat(-xs, n)  # row 0 = top of the image

    def set_pose(self, pose: CameraPose) -> None:
        """Move the rendering camera (the back-projection keeps the nominal one)."""
        self.render_view = _view(self.s, pose)

    def render(self, client: int) -> tuple[np.ndarray, np.ndarray]:
        """(linear depth along the view axis (N, N) float64, body ids (N, N) int; -1 = nothing)."""
        n, s = self.s.image_size, self.s
        _, _, _, depth, seg = pb.getCameraImage(
            n, n, self.render_view, self.proj, renderer=pb.ER_TINY_RENDERER, physicsClientId=client
        )
        d = np.asarray(depth, dtype=np.float64).reshape(n, n)
        z = s.far * s.near / (s.far - (s.far - s.near) * d)
        return z, np.asarray(seg, dtype=np.int64).reshape(n, n)

    def unproject(self, mask: np.ndarray, z_linear: np.ndarray) -> np.ndarray:
        """World points (K, 3) of the masked pixels at the given linear depths (nominal camera)."""
        s = self.s
        m = mask.reshape(-1)
        z = z_linear.reshape(-1)[m]
        d = (s.far - s.far * s.near / z) / (s.far - s.near)  # back to the depth buffer
        clip = np.stack([self._ndc_x[m], self._ndc_y[m], d * 2 - 1, np.ones_like(d)])
        world = self.inv_vp @ clip
        return (world[:3] / world[3]).T


def gaussian_blur3(image: np.ndarray, sigma: float) -> np.ndarray:
    """3 x 3 Gaussian blur with edge replication."""
    k = np.exp(-(np.arange(-1, 2) ** 2) / (2 * sigma**2))
    k /= k.sum()
    p = np.pad(image, 1, mode="edge")
    rows = k[0] * p[:-2] + k[1] * p[1:-1] + k[2] * p[2:]
    return k[0] * rows[:, :-2] + k[1] * rows[:, 1:-1] + k[2] * rows[:, 2:]


def cutout(mask: np.ndarray, keep: float, rng: np.random.Generator) -> np.ndarray:
    """``mask`` with a random rectangle inside its bounding box removed, of (1 - keep) of its area."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0 or keep >= 1.0:
        return mask
    h, w = rows.max() - rows.min() + 1, cols.max() - cols.min() + 1
    side = math.sqrt(max(0.0, 1.0 - keep))
    ch, cw = max(1, round(h * side)), max(1, round(w * side))
    r0 = rows.min() + int(rng.integers(0, h - ch + 1))
    c0 = cols.min() + int(rng.integers(0, w - cw + 1))
    out = mask.copy()
    out[r0 : r0 + ch, c0 : c0 + cw] = False
    return out


def image_noise(
    z: np.ndarray,
    masks: dict[str, np.ndarray],
    r: RandomisationSettings,
    distance: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Depth noise, blur and per-segment cutout (domain randomisation of the rendered images).

    TODO(h/sga-dsa): replace by ``services.observation.dsa.image_noise`` once it lands, so the env
    and MEA copies share one implementation."""
    noisy = z + rng.uniform(-1.0, 1.0, z.shape) * r.depth_noise * distance
    if r.blur_sigma > 0:
        noisy = gaussian_blur3(noisy, r.blur_sigma)
    cut = {name: cutout(m, float(rng.uniform(*r.cutout_keep)), rng) for name, m in masks.items()}
    return noisy, cut
