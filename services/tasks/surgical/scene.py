"""The world of Surgical Grasp Any: tray, instrument and one object, rebuilt from the seed at reset.

Every reset builds the world again in the same order, so an episode depends on its seed only.

Design notes: docs/architecture-notes.md, services/tasks/surgical/scene.py."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as pb

from services.tasks.surgical import objects
from services.tasks.surgical.instrument import WRIST, Instrument
from services.tasks.surgical.settings import SurgicalSettings, real

WORKSPACE = np.array([[-real(0.05), real(0.05)], [-real(0.05), real(0.05)], [0.0, real(0.07)]])
"""Bounds of the closed jaw tips (sim units): 10 x 10 x 7 cm real above the tray."""
TRAY_HALF = (real(0.07), real(0.07), real(0.002))
TRAY_RGBA = (0.35, 0.45, 0.35, 1.0)
OBJECT_RATIO = 0.8
GRIPPER_X_RATIO = -0.9
GRIPPER_Y_RATIO = 0.9
GRIPPER_Z_RATIO = (0.5, 0.9)
GRIPPER_YAW = 0.9 * math.pi


def from_ratio(ratio: float | np.ndarray, axis: int) -> float | np.ndarray:
    """Workspace ratio in [-1, 1] -> coordinate along ``axis``."""
    lo, hi = WORKSPACE[axis]
    return lo + (np.asarray(ratio) + 1.0) / 2.0 * (hi - lo)


@dataclass
class Placement:
    """What the seed drew for an episode."""

    spec: objects.ObjectSpec
    object_xy: np.ndarray
    object_yaw: float
    tip: np.ndarray
    yaw: float


def draw(settings: SurgicalSettings, rng: np.random.Generator) -> Placement:
    kind = objects.KINDS[int(rng.choice(len(objects.KINDS), p=settings.object_probabilities))]
    scale = float(rng.uniform(*settings.scale_range))
    xy = np.array([from_ratio(r, i) for i, r in enumerate(rng.uniform(-OBJECT_RATIO, OBJECT_RATIO, 2))])
    obj_yaw = float(rng.uniform(-math.pi, math.pi))
    tip = np.array([
        from_ratio(GRIPPER_X_RATIO, 0),
        from_ratio(rng.uniform(-GRIPPER_Y_RATIO, GRIPPER_Y_RATIO), 1),
        from_ratio(rng.uniform(*GRIPPER_Z_RATIO), 2),
    ], dtype=float)  # fmt: skip
    yaw = float(rng.uniform(-GRIPPER_YAW, GRIPPER_YAW))
    return Placement(objects.ObjectSpec(kind, scale), xy, obj_yaw, tip, yaw)


class Scene:
    """The bodies of one episode and the object's constraints."""

    def __init__(self, client: int, settings: SurgicalSettings, pivot_height: float) -> None:
        self.client = client
        self.settings = settings
        self.pivot_height = pivot_height
        self.build(None)

    def build(self, placement: Placement | None) -> None:
        """Reset the simulation and create tray, instrument and (with a placement) the object."""
        c, s = self.client, self.settings
        pb.resetSimulation(physicsClientId=c)
        pb.setGravity(0, 0, -9.8, physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=1.0 / s.sim_hz, numSolverIterations=50,
                                     deterministicOverlappingPairs=1, physicsClientId=c)  # fmt: skip
        col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=TRAY_HALF, physicsClientId=c)
        vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=TRAY_HALF, rgbaColor=TRAY_RGBA, physicsClientId=c)
        self.tray = pb.createMultiBody(0.0, col, vis, basePosition=(0, 0, -TRAY_HALF[2]), physicsClientId=c)
        self.instrument = Instrument(c, self.pivot_height)
        for link in range(-1, 3):
            pb.setCollisionFilterPair(self.instrument.body, self.tray, link, -1, 0, physicsClientId=c)
        self.object: int | None = None
        self.spec: objects.ObjectSpec | None = None
        self.tray_constraint: int | None = None
        self.grasp_constraint: int | None = None
        self.grasp_offset: tuple | None = None  # object pose in the wrist frame when grasped
        self.rest_z = 0.0
        if placement is None:
            return
        self.spec = placement.spec
        self.object = objects.build(c, placement.spec, placement.object_xy, placement.object_yaw)
        self.tray_constraint = self._fix(self.tray, -1, self.settings.tray_constraint_force)
        self.rest_z = float(self.object_pose()[2])
        pivot = self.instrument.pivot_from_tip(placement.tip)
        self.instrument.reset(pivot, placement.yaw, jaw_open=True)

    # --- object -------------------------------------------------------------------------------
    def object_pose(self) -> np.ndarray:
        pos, quat = pb.getBasePositionAndOrientation(self.object, physicsClientId=self.client)
        return np.array([*pos, *quat])

    def object_yaw(self) -> float:
        return float(pb.getEulerFromQuaternion(self.object_pose()[3:])[2])

    def _fix(self, parent: int, link: int, force: float) -> int:
        """A fixed constraint holding the object where it is now relative to (parent, link). Constraint
        frames are centre-of-mass frames; every body here has its centre of mass at its frame."""
        c = self.client
        if link < 0:
            ppos, pquat = pb.getBasePositionAndOrientation(parent, physicsClientId=c)
        else:
            ls = pb.getLinkState(parent, link, computeForwardKinematics=True, physicsClientId=c)
            ppos, pquat = ls[4], ls[5]
        opos, oquat = pb.getBasePositionAndOrientation(self.object, physicsClientId=c)
        inv_pos, inv_quat = pb.invertTransform(ppos, pquat)
        rel_pos, rel_quat = pb.multiplyTransforms(inv_pos, inv_quat, opos, oquat)
        cid = pb.createConstraint(
            parent, link, self.object, -1, pb.JOINT_FIXED, (0, 0, 0), rel_pos, (0, 0, 0),
            parentFrameOrientation=rel_quat, physicsClientId=c,
        )  # fmt: skip
        pb.changeConstraint(cid, maxForce=force, physicsClientId=c)
        return cid

    def attach(self) -> None:
        """The grasp: release the tray's hold and fix the object to the wrist."""
        c = self.client
        if self.tray_constraint is not None:
            pb.removeConstraint(self.tray_constraint, physicsClientId=c)
            self.tray_constraint = None
        self.grasp_constraint = self._fix(self.instrument.body, WRIST, self.settings.tray_constraint_force)
        self.grasp_offset = self.object_in_wrist()

    def release(self) -> None:
        if self.grasp_constraint is not None:
            pb.removeConstraint(self.grasp_constraint, physicsClientId=self.client)
            self.grasp_constraint = None

    def object_in_wrist(self) -> tuple:
        wpos, wquat = self.instrument.wrist_pose()
        inv_pos, inv_quat = pb.invertTransform(wpos, wquat)
        opos, oquat = pb.getBasePositionAndOrientation(self.object, physicsClientId=self.client)
        return pb.multiplyTransforms(inv_pos, inv_quat, opos, oquat)

    def held(self) -> bool:
        """The grasp holds: the object is still where the grasp put it relative to the wrist."""
        if self.grasp_constraint is None or self.grasp_offset is None:
            return False
        pos, _ = self.object_in_wrist()
        return float(np.linalg.norm(np.subtract(pos, self.grasp_offset[0]))) <= self.settings.hold_tolerance

    def lifted(self) -> float:
        """Height the object has risen above where it lay."""
        return float(self.object_pose()[2]) - self.rest_z
