"""A PSM-like surgical instrument built from pybullet primitives, and its Cartesian drive.

Design notes: docs/architecture-notes.md, services/tasks/surgical/instrument.py."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as pb

from services.tasks.surgical.settings import real

SHAFT_RADIUS = real(0.004)
SHAFT_LENGTH = real(0.03)
WRIST_HALF = (real(0.003), real(0.003), real(0.0025))
JAW_LENGTH = real(0.012)
JAW_HALF_THICKNESS = real(0.00075)  # along the closing axis (x)
JAW_HALF_WIDTH = real(0.00125)  # along y
HINGE_X = real(0.001)  # hinges either side of the axis
JAW_OPEN = math.radians(30.0)  # each jaw, from hanging straight down
JAW_CLOSED = math.radians(-12.0)  # well past touching: each jaw reaches across the axis, squeezing what
# it holds even when the object sits a discrete step off-centre
JAW_FORCE = 5.0
TOUCH = real(0.0002)
"""A jaw closer than this to the object touches it."""
WRIST, JAW_A, JAW_B = 0, 1, 2
JAWS = (JAW_A, JAW_B)
TIP_DROP = 2 * WRIST_HALF[2] + JAW_LENGTH
"""Closed jaw tips below the shaft's lower end (the base frame origin)."""
RGBA = (0.75, 0.75, 0.8, 1.0)
DRIVE_FORCE = 200.0
WRIST_FORCE = 50.0
MOTOR_GAIN = 0.6  # position gain of the wrist and jaw motors
MAX_JOINT_SPEED = 8.0  # rad/s: a jaw tip moves 0.4 mm real per physics step, far less than the thinnest
# part it can meet (the 1.5 mm jaw, a 1.5 mm wire), so it cannot tunnel through an object


def _box(client: int, half, offset=(0.0, 0.0, 0.0)) -> tuple[int, int]:
    col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, collisionFramePosition=offset,
                                  physicsClientId=client)  # fmt: skip
    vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=half, visualFramePosition=offset, rgbaColor=RGBA,
                               physicsClientId=client)  # fmt: skip
    return col, vis


@dataclass
class InstrumentState:
    """The commanded state: pivot position (world), yaw, and whether the jaw is commanded open."""

    pivot: np.ndarray
    yaw: float
    jaw_open: bool


class Instrument:
    """The tool in one pybullet client, its drive constraint and commanded state."""

    def __init__(self, client: int, pivot_height: float = 0.0) -> None:
        self.client = client
        self.pivot_height = pivot_height  # pivot above the closed tips, along the axis
        c = client
        shaft_col = pb.createCollisionShape(
            pb.GEOM_CYLINDER, radius=SHAFT_RADIUS, height=SHAFT_LENGTH,
            collisionFramePosition=(0, 0, SHAFT_LENGTH / 2), physicsClientId=c,
        )  # fmt: skip
        shaft_vis = pb.createVisualShape(
            pb.GEOM_CYLINDER, radius=SHAFT_RADIUS, length=SHAFT_LENGTH,
            visualFramePosition=(0, 0, SHAFT_LENGTH / 2), rgbaColor=RGBA, physicsClientId=c,
        )  # fmt: skip
        wrist_col, wrist_vis = _box(c, WRIST_HALF, (0, 0, -WRIST_HALF[2]))
        jaw_half = (JAW_HALF_THICKNESS, JAW_HALF_WIDTH, JAW_LENGTH / 2)
        jaw_col, jaw_vis = _box(c, jaw_half, (0, 0, -JAW_LENGTH / 2))
        hinge_z = -2 * WRIST_HALF[2]
        self.body = pb.createMultiBody(
            baseMass=0.05, baseCollisionShapeIndex=shaft_col, baseVisualShapeIndex=shaft_vis,
            basePosition=(0, 0, 1.0),
            linkMasses=[0.005, 0.002, 0.002],
            linkCollisionShapeIndices=[wrist_col, jaw_col, jaw_col],
            linkVisualShapeIndices=[wrist_vis, jaw_vis, jaw_vis],
            linkPositions=[(0, 0, 0), (HINGE_X, 0, hinge_z), (-HINGE_X, 0, hinge_z)],
            linkOrientations=[(0, 0, 0, 1)] * 3,
            linkInertialFramePositions=[(0, 0, 0)] * 3,
            linkInertialFrameOrientations=[(0, 0, 0, 1)] * 3,
            linkParentIndices=[0, 1, 1],
            linkJointTypes=[pb.JOINT_REVOLUTE] * 3,
            linkJointAxis=[(0, 0, 1), (0, -1, 0), (0, 1, 0)],
            physicsClientId=c,
        )  # fmt: skip
        for link in (-1, WRIST, JAW_A, JAW_B):
            pb.changeDynamics(self.body, link, lateralFriction=1.0, linearDamping=0.0, angularDamping=0.0,
                              physicsClientId=c)  # fmt: skip
        pb.setCollisionFilterPair(self.body, self.body, JAW_A, JAW_B, 0, physicsClientId=c)
        self.drive = pb.createConstraint(
            self.body, -1, -1, -1, pb.JOINT_FIXED, (0, 0, 0), (0, 0, 0), (0, 0, 1.0), physicsClientId=c
        )
        pb.changeConstraint(self.drive, maxForce=DRIVE_FORCE, physicsClientId=c)
        self.state = InstrumentState(np.zeros(3), 0.0, True)
        self._frame = np.array([0.0, 0.0, 1.0])  # where the drive constraint holds the shaft's base

    # --- geometry -----------------------------------------------------------------------------
    def base_from_pivot(self, pivot: np.ndarray) -> np.ndarray:
        return np.asarray(pivot, float) + np.array([0.0, 0.0, TIP_DROP - self.pivot_height])

    def tip_from_pivot(self, pivot: np.ndarray) -> np.ndarray:
        """Closed jaw tips (on the axis) for a pivot position."""
        return np.asarray(pivot, float) - np.array([0.0, 0.0, self.pivot_height])

    def pivot_from_tip(self, tip: np.ndarray) -> np.ndarray:
        return np.asarray(tip, float) + np.array([0.0, 0.0, self.pivot_height])

    def measured_pivot(self) -> tuple[np.ndarray, float]:
        """Pivot position and yaw from the simulated bodies."""
        pos, _ = pb.getBasePositionAndOrientation(self.body, physicsClientId=self.client)
        yaw = pb.getJointState(self.body, WRIST, physicsClientId=self.client)[0]
        return np.asarray(pos) - np.array([0.0, 0.0, TIP_DROP - self.pivot_height]), float(yaw)

    def jaw_angles(self) -> tuple[float, float]:
        states = pb.getJointStates(self.body, list(JAWS), physicsClientId=self.client)
        return float(states[0][0]), float(states[1][0])

    def jaw_opening(self) -> float:
        """Measured opening in [0, 1] (mean of the two jaws; 0 closed, 1 open)."""
        a = np.mean(self.jaw_angles())
        return float(np.clip((a - 0.0) / (JAW_OPEN - 0.0), 0.0, 1.0))

    def wrist_pose(self) -> tuple[tuple, tuple]:
        ls = pb.getLinkState(self.body, WRIST, computeForwardKinematics=True, physicsClientId=self.client)
        return ls[4], ls[5]

    def jaw_contacts(self, body: int) -> tuple[bool, bool]:
        """Whether each jaw touches ``body``: within ``TOUCH`` of it (0.2 mm real). pybullet's contact
        points alone flicker for a physics step now and then while a squeezed object settles."""
        c = self.client
        near = [pb.getClosestPoints(self.body, body, TOUCH, linkIndexA=j, physicsClientId=c) for j in JAWS]
        return bool(near[0]), bool(near[1])

    def touches(self, body: int) -> bool:
        return bool(pb.getContactPoints(bodyA=self.body, bodyB=body, physicsClientId=self.client))

    # --- set-up and motion ----------------------------------------------------------------------
    def _set_frame(self, base: np.ndarray) -> None:
        self._frame = np.asarray(base, float)
        pb.changeConstraint(self.drive, jointChildPivot=self._frame.tolist(), maxForce=DRIVE_FORCE,
                            physicsClientId=self.client)  # fmt: skip

    def _motors(self) -> None:
        c, s = self.client, self.state
        pb.setJointMotorControl2(self.body, WRIST, pb.POSITION_CONTROL, targetPosition=s.yaw, force=WRIST_FORCE,
                                 positionGain=MOTOR_GAIN, maxVelocity=MAX_JOINT_SPEED, physicsClientId=c)  # fmt: skip
        jaw = JAW_OPEN if s.jaw_open else JAW_CLOSED
        for j in JAWS:
            pb.setJointMotorControl2(self.body, j, pb.POSITION_CONTROL, targetPosition=jaw, force=JAW_FORCE,
                                     positionGain=MOTOR_GAIN, maxVelocity=MAX_JOINT_SPEED, physicsClientId=c)  # fmt: skip

    def reset(self, pivot: np.ndarray, yaw: float, jaw_open: bool = True) -> None:
        """Teleport to a pose at rest (episode start, free space)."""
        c = self.client
        self.state = InstrumentState(np.asarray(pivot, float).copy(), float(yaw), bool(jaw_open))
        base = self.base_from_pivot(pivot)
        pb.resetBasePositionAndOrientation(self.body, base.tolist(), (0, 0, 0, 1), physicsClientId=c)
        pb.resetBaseVelocity(self.body, (0, 0, 0), (0, 0, 0), physicsClientId=c)
        pb.resetJointState(self.body, WRIST, float(yaw), physicsClientId=c)
        jaw = JAW_OPEN if jaw_open else JAW_CLOSED
        for j in JAWS:
            pb.resetJointState(self.body, j, jaw, physicsClientId=c)
        self._set_frame(base)
        self._motors()

    def command(self, pivot: np.ndarray, yaw: float, jaw_open: bool) -> None:
        """Set the new commanded state (already clipped by the caller)."""
        self.state = InstrumentState(np.asarray(pivot, float).copy(), float(yaw), bool(jaw_open))
        self._motors()

    def settle(self, step_physics, ramp: int, min_steps: int, max_steps: int, tolerance: float) -> int:
        """Move the drive frame to the commanded pivot over ``ramp`` physics steps, then step until the
        shaft, the wrist and the jaws come to rest (or ``max_steps``). Returns the steps used."""
        start, goal = self._frame.copy(), self.base_from_pivot(self.state.pivot)
        used = 0
        while used < max_steps:
            if used < ramp:
                self._set_frame(start + (goal - start) * (used + 1) / ramp)
            step_physics()
            used += 1
            if used < max(min_steps, ramp) or used % 2:
                continue
            if self._at_rest(goal, tolerance):
                break
        return used

    def _at_rest(self, goal: np.ndarray, tolerance: float) -> bool:
        c = self.client
        pos, _ = pb.getBasePositionAndOrientation(self.body, physicsClientId=c)
        if np.linalg.norm(np.asarray(pos) - goal) > tolerance:
            return False
        states = pb.getJointStates(self.body, [WRIST, *JAWS], physicsClientId=c)
        if abs(states[0][0] - self.state.yaw) > 2e-3:
            return False
        return all(abs(v) < 0.05 for _, v, _, _ in states)
