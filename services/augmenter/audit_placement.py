"""Where the physics audit puts a copy's first state in the simulator, rotated copies included.

Design notes: docs/architecture-notes.md, services/augmenter/audit_placement.py."""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from proto.actions import DELTA_THETA
from proto.episode import Episode
from services.augmenter.core.isometric import WORKSPACE_CENTRE, cos_sin, rotate_points

if TYPE_CHECKING:  # pybullet is imported only where an env exists
    from services.tasks.env import ManipulationEnv, Observation

RESAMPLE_SALT = 0x5EED_A0D1  # offsets the replay's point-sampling stream from the recorded one
GRID = 9  # translations tried per axis of the feasible box
ROTATED_KINDS = ("isometric", "mea+isometric")


class NotSimulableError(Exception):
    """No placement of the copy exists in this simulator (the reason is the message)."""


def rotation_of(ep: Episode) -> float:
    """The copy's isometric angle (rad): ``params["rotation"]`` of a rotated copy, else 0."""
    aug = ep.augmentation
    if aug is None or aug.kind not in ROTATED_KINDS:
        return 0.0
    return float(aug.params["rotation"][0])


@dataclass(frozen=True)
class Placement:
    """The source scene moved rigidly, ``x -> R(phi) x + shift`` about the vertical, and the copy as
    the simulator will play it (privileged poses translated to match, yaws on the wrist's branch)."""

    phi: float
    shift: np.ndarray  # (2,) m
    episode: Episode

    @property
    def moves_scene(self) -> bool:
        return self.phi != 0.0 or bool(np.any(self.shift != 0.0))

    def move_scene(self, env: ManipulationEnv) -> None:
        """Turn and shift every body but the floor and the arm as they are now."""
        env.move_scene(self.phi, self.shift, cos_sin(self.phi))


def yaw_branch(ep: Episode, limit: float) -> float | None:
    """Multiple of 2 pi that puts the copy's commanded and recorded yaws inside [-limit, limit]."""
    yaw = np.asarray(ep.gripper_pose[:, 3], np.float64)
    commanded = yaw[0] + DELTA_THETA * np.r_[0.0, np.cumsum(np.asarray(ep.actions[:, 4], np.float64))]
    recorded = yaw[0] + np.unwrap(yaw - yaw[0])
    lo, hi = min(commanded.min(), recorded.min()), max(commanded.max(), recorded.max())
    k = math.ceil((-limit - lo) / (2 * math.pi))
    return 2 * math.pi * k if hi + 2 * math.pi * k <= limit else None


def anchor_shift(aug: Episode) -> np.ndarray:
    """The translation that puts the copy's contact steps back where the recording had them: the
    mean over those steps (the last step if none) of (un-turned pivot - turned pivot), where the
    copy's poses are the recording's turned by phi about ``WORKSPACE_CENTRE``."""
    centre = np.asarray(WORKSPACE_CENTRE, np.float64)
    xy = np.asarray(aug.gripper_pose[:, :2], np.float64)
    touching = np.asarray(aug.contacts, bool).any(axis=1)
    steps = xy[touching] if touching.any() else xy[-1:]
    unturned = rotate_points(steps - centre, -rotation_of(aug)) + centre
    return (unturned - steps).mean(axis=0)


def plan_placement(env: ManipulationEnv, aug: Episode) -> Placement:
    """Where ``aug`` goes in ``env`` (see the module docstring); NotSimulableError if nowhere."""
    phi = rotation_of(aug)
    if phi == 0.0:
        return Placement(0.0, np.zeros(2), aug)
    from services.tasks.robot import WORKSPACE, YAW_LIMIT  # deferred: pybullet, only for turned copies

    turn = yaw_branch(aug, YAW_LIMIT)
    if turn is None:
        raise NotSimulableError("wrist range: the turned yaws do not fit in the wrist's limits")
    pivots = np.asarray(aug.gripper_pose[:, :3], np.float64)
    objects = np.asarray(aug.object_poses[..., :2], np.float64).reshape(-1, 2)
    lo, hi = env.robot.pivot_bounds()
    low = np.maximum(lo[:2] - pivots[:, :2].min(0), WORKSPACE[:2, 0] - objects.min(0))
    high = np.minimum(hi[:2] - pivots[:, :2].max(0), WORKSPACE[:2, 1] - objects.max(0))
    if np.any(low > high + 1e-9):
        raise NotSimulableError("workspace: the turned scene does not fit in the workspace")
    high = np.maximum(high, low)
    anchor = np.clip(anchor_shift(aug), low, high)
    grid = np.stack(np.meshgrid(*[np.linspace(a, b, GRID) for a, b in zip(low, high, strict=True)]), -1)
    candidates = sorted(grid.reshape(-1, 2), key=lambda d: float(np.linalg.norm(d - anchor)))
    yaws = np.asarray(aug.gripper_pose[:, 3], np.float64) + turn
    for delta in [anchor, *candidates]:
        moved = pivots + np.r_[delta, 0.0]
        if all(
            np.linalg.norm(env.robot.reachable(p, float(y)) - p) <= 1e-9
            for p, y in zip(moved, yaws, strict=True)
        ):
            return _placement(aug, phi, np.asarray(delta, np.float64), turn)
    raise NotSimulableError("reach: the arm cannot reach the turned gripper path")


def _placement(aug: Episode, phi: float, delta: np.ndarray, turn: float) -> Placement:
    c, s = cos_sin(phi)
    centre = np.asarray(WORKSPACE_CENTRE, np.float64)
    stored_shift = centre - np.array([[c, -s], [s, c]]) @ centre  # the copy's poses: about the centre
    pose = np.array(aug.gripper_pose, np.float64, copy=True)
    pose[:, :2] += delta
    pose[:, 3] += turn
    objects = np.array(aug.object_poses, np.float64, copy=True)
    objects[..., :2] += delta
    placed = dataclasses.replace(
        aug, gripper_pose=pose.astype(np.float32), object_poses=objects.astype(np.float32)
    )
    return Placement(phi, stored_shift + delta, placed)


def place(
    env: ManipulationEnv,
    seed: int,
    pose: np.ndarray,
    jaw: float,
    resample: bool = True,
    placement: Placement | None = None,
) -> Observation:
    """Reset the task from ``seed``, move the scene as ``placement`` says (if given), and teleport
    the arm to ``pose`` (pivot x, y, z, yaw) with the jaw at ``jaw``; the world then rests as long
    as after an ordinary reset (``ManipulationEnv.place_state``).

    ``resample``: draw the observed points from a sampling stream independent of the recorded
    episode's (the env's sampling seed offset by ``RESAMPLE_SALT``; the objects are still placed
    from ``seed``). Without it a replay whose fused clouds are bit-identical to the recording draws
    the very same points and the Chamfer distance is 0, a floor no augmented copy could share."""
    sampling_seed = (int(seed) + RESAMPLE_SALT) % 2**63 if resample else None
    moved = placement is not None and placement.moves_scene
    arrange = functools.partial(placement.move_scene, env) if moved else None
    return env.place_state(seed, pose, jaw, sampling_seed=sampling_seed, arrange=arrange)
