"""Kuka iiwa with its parallel gripper (pybullet_data `kuka_iiwa/kuka_with_gripper2.sdf`).

The policy commands deltas of a pivot (the gripper points' centroid) and a yaw about it, tracked in
real physics, so that a rotation leaves every object point put in the gripper-centric frame (the
transition prior MEA relies on) and contacts are simulated.

Design notes: docs/architecture-notes.md, services/tasks/robot.py."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as pb
import pybullet_data

from proto.actions import DELTA_THETA, DELTA_XYZ

# x, y bounds of the pivot and z bounds of the fingers' lowest point (m), as in the Equi-RSAC tasks
WORKSPACE = np.array([[0.3, 0.7], [-0.2, 0.2], [0.01, 0.25]])
REACH = 0.78  # m: the flange stays within this of the shoulder (link 1); measured, IK fails past ~0.8
YAW_LIMIT = 2.9  # commanded yaw is kept in [-2.9, 2.9] rad: the wrist joint stops at +-3.05
YAW_OFFSET = math.pi  # gripper yaw 0 = flange yaw pi = wrist joint 6 at 0, mid-range

BASE_POSITION = (-0.2, 0.0, 0.0)  # far enough back that the elbow (joint 3) stays inside its limits
ARM_JOINTS = tuple(range(7))
FLANGE_LINK = 6  # last arm link: IK target (joint 7 cannot move it)
WRIST_LINK = 7  # gripper base ("base_link"); its joint 7 is held at 0
FINGER_JOINTS = (8, 11)
TIP_JOINTS = (10, 13)
GRIPPER_LINKS = tuple(range(7, 14))
REST_POSE = (0.0, 0.4, 0.0, -1.6, 0.0, 1.2, 0.0)
JAW_OPEN_ANGLE = 0.3  # finger angle (rad) at jaw = 1: about 10 cm between the pads
JAW_CLOSED_ANGLE = -0.05  # pads 3 mm apart: past touching anything worth grasping, so grasps squeeze
TIP_PARALLEL = -0.2  # tip-joint offset that keeps the pads parallel (the model tilts them 0.2 rad)
DOWN = pb.getQuaternionFromEuler((math.pi, 0.0, 0.0))


@dataclass(frozen=True)
class ControlSettings:
    """How precisely and how long the controller tracks each commanded pose."""

    sim_hz: float = 240.0
    """Physics rate."""
    max_substeps: int = 120
    """Most physics steps per action."""
    min_substeps: int = 8
    """Fewest physics steps per action (lets contacts and the jaw settle)."""
    tolerance_m: float = 2e-4
    """Pivot position error at which an action counts as reached."""
    tolerance_rad: float = 2e-3
    """Yaw error at which an action counts as reached."""
    arm_force: float = 300.0
    """Joint motor force limit (N m), the model's maximum."""
    position_gain: float = 0.3
    """Position gain of the joint motors (pybullet's default 0.1 lags by centimetres)."""
    finger_force: float = 100.0
    """Finger motor force (N m)."""
    finger_friction: float = 1.5
    """Lateral friction of the gripper links (the model's 0.5-0.8 lets grasped cubes slip)."""
    solver_iterations: int = 50
    """Constraint solver iterations (BulletArm's 'fast' physics mode)."""


def _yaw_of(quat) -> float:
    """Yaw of a gripper pointing down: heading of its local x axis in the world xy plane."""
    m = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
    return math.atan2(m[1, 0], m[0, 0])


def wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


class Robot:
    """The arm, its gripper, and the pivot/yaw/jaw controller. One instance per pybullet client."""

    def __init__(self, client: int, settings: ControlSettings = ControlSettings()) -> None:
        self.client = client
        self.settings = settings
        pb.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=client)
        self.body = pb.loadSDF("kuka_iiwa/kuka_with_gripper2.sdf", physicsClientId=client)[0]
        pb.resetBasePositionAndOrientation(self.body, BASE_POSITION, (0, 0, 0, 1), physicsClientId=client)
        # The arm is not part of the observation: make it invisible to the cameras (the tiny
        # renderer skips alpha-0 shapes, which also makes each view ~10x cheaper).
        for link in range(-1, WRIST_LINK):
            pb.changeVisualShape(self.body, link, rgbaColor=(1, 1, 1, 0), physicsClientId=client)
        for link in GRIPPER_LINKS:
            pb.changeDynamics(
                self.body, link, lateralFriction=settings.finger_friction, physicsClientId=client
            )
        n = pb.getNumJoints(self.body, physicsClientId=client)
        info = [pb.getJointInfo(self.body, j, physicsClientId=client) for j in range(n)]
        self._movable = [j for j in range(n) if info[j][2] != pb.JOINT_FIXED]
        self.shoulder = np.array(pb.getLinkState(self.body, 1, physicsClientId=client)[4])
        self.pivot_offset = np.zeros(3)  # pivot in the flange frame; set by calibrate()
        self.tip_drop = 0.0  # pivot height above the fingers' lowest point, open jaw; set by calibrate()
        self.grip_offset = np.zeros(3)  # where the closed tips meet, flange frame; set by calibrate()
        self.target_pos = np.zeros(3)
        self.target_yaw = 0.0
        self.jaw = 1.0

    # --- state --------------------------------------------------------------------------------
    def flange_pose(self) -> tuple[np.ndarray, tuple]:
        ls = pb.getLinkState(
            self.body, FLANGE_LINK, computeForwardKinematics=True, physicsClientId=self.client
        )
        return np.array(ls[4]), ls[5]

    def pivot(self) -> tuple[np.ndarray, float]:
        """Measured pivot position (world) and yaw."""
        pos, quat = self.flange_pose()
        m = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
        return pos + m @ self.pivot_offset, wrap(_yaw_of(quat) - YAW_OFFSET)

    def tcp(self) -> np.ndarray:
        """Tool centre point (for scripted experts): where the finger tips meet when the jaw
        closes, a fixed point of the flange frame found by calibrate()."""
        pos, quat = self.flange_pose()
        m = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
        return pos + m @ self.grip_offset

    def pad_gap(self) -> float:
        """Distance between the finger-tip pads (m)."""
        near = pb.getClosestPoints(self.body, self.body, 0.3, linkIndexA=TIP_JOINTS[0], linkIndexB=TIP_JOINTS[1],
                                   physicsClientId=self.client)  # fmt: skip
        return max(0.0, min(p[8] for p in near)) if near else 0.0

    def finger_angle(self) -> float:
        return pb.getJointState(self.body, FINGER_JOINTS[1], physicsClientId=self.client)[0]

    def jaw_opening(self) -> float:
        """Measured jaw opening in [0, 1] (0 closed, 1 open)."""
        a = (self.finger_angle() - JAW_CLOSED_ANGLE) / (JAW_OPEN_ANGLE - JAW_CLOSED_ANGLE)
        return float(np.clip(a, 0.0, 1.0))

    def reachable(self, pos: np.ndarray, yaw: float) -> np.ndarray:
        """``pos`` pulled toward the shoulder until the arm can reach it (the workspace's far, high
        corners are beyond this arm: x = 0.7 at finger height 0.25 m needs a 0.9 m reach)."""
        flange, _ = self._flange_target(pos, yaw)
        d = flange - self.shoulder
        n = float(np.linalg.norm(d))
        return pos if n <= REACH else pos - d * (1.0 - REACH / n)

    def pivot_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Box the commanded pivot stays in: the workspace, with z shifted so that it bounds the tips."""
        shift = np.array([0.0, 0.0, self.tip_drop])
        return WORKSPACE[:, 0] + shift, WORKSPACE[:, 1] + shift

    def calibrate(self, pivot_in_flange: np.ndarray) -> None:
        """Set the pivot (gripper point centroid, in the flange frame), measure how far it sits
        above the open fingers' lowest point, and find where the closed tips meet."""
        self.pivot_offset = np.asarray(pivot_in_flange, dtype=float)
        pivot, _ = self.pivot()
        self.tip_drop = float(pivot[2] - self.lowest_point())
        self._set_fingers(0.0, reset=True)
        near = pb.getClosestPoints(self.body, self.body, 0.05, linkIndexA=TIP_JOINTS[0], linkIndexB=TIP_JOINTS[1],
                                   physicsClientId=self.client)  # fmt: skip
        meet = np.mean([(np.array(p[5]) + np.array(p[6])) / 2 for p in near], axis=0)
        pos, quat = self.flange_pose()
        m = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
        self.grip_offset = m.T @ (meet - pos)
        self._set_fingers(self.jaw, reset=True)

    def lowest_point(self) -> float:
        """Height of the lowest point of the fingers (what must clear the floor)."""
        return min(pb.getAABB(self.body, j, physicsClientId=self.client)[0][2] for j in TIP_JOINTS)

    # --- set-up -------------------------------------------------------------------------------
    def _flange_target(self, pos: np.ndarray, yaw: float) -> tuple[np.ndarray, tuple]:
        quat = pb.getQuaternionFromEuler((math.pi, 0.0, yaw + YAW_OFFSET))
        m = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
        return pos - m @ self.pivot_offset, quat

    def _ik(self, pos: np.ndarray, yaw: float) -> list[float]:
        fpos, fquat = self._flange_target(pos, yaw)
        sol = pb.calculateInverseKinematics(
            self.body, FLANGE_LINK, fpos.tolist(), fquat, maxNumIterations=200, residualThreshold=1e-7,
            physicsClientId=self.client,
        )  # fmt: skip
        return [sol[self._movable.index(j)] for j in ARM_JOINTS]

    def reset(self, pos: np.ndarray, yaw: float, jaw: float = 1.0) -> None:
        """Teleport to a pose (no physics): used only at episode start, in free space."""
        for j, q in enumerate(REST_POSE):
            pb.resetJointState(self.body, j, q, physicsClientId=self.client)
        pb.resetJointState(self.body, WRIST_LINK, 0.0, physicsClientId=self.client)
        self._set_fingers(jaw, reset=True)
        for _ in range(8):  # IK from the current configuration converges in a few rounds
            q = self._ik(pos, yaw)
            for j, qj in zip(ARM_JOINTS, q, strict=True):
                pb.resetJointState(self.body, j, qj, physicsClientId=self.client)
        self.target_pos = np.array(pos, dtype=float)
        self.target_yaw = float(yaw)
        self.jaw = float(jaw)
        self._drive(q)

    def _set_fingers(self, jaw: float, reset: bool = False) -> None:
        angle = JAW_CLOSED_ANGLE + float(np.clip(jaw, 0, 1)) * (JAW_OPEN_ANGLE - JAW_CLOSED_ANGLE)
        targets = {
            FINGER_JOINTS[0]: -angle,
            FINGER_JOINTS[1]: angle,
            TIP_JOINTS[0]: angle + TIP_PARALLEL,
            TIP_JOINTS[1]: -angle - TIP_PARALLEL,
        }
        for j, t in targets.items():
            if reset:
                pb.resetJointState(self.body, j, t, physicsClientId=self.client)
            pb.setJointMotorControl2(
                self.body, j, pb.POSITION_CONTROL, targetPosition=t, force=self.settings.finger_force,
                physicsClientId=self.client,
            )  # fmt: skip

    def _drive(self, q: list[float]) -> None:
        n = len(ARM_JOINTS)
        pb.setJointMotorControlArray(
            self.body, list(ARM_JOINTS), pb.POSITION_CONTROL, targetPositions=q,
            forces=[self.settings.arm_force] * n, positionGains=[self.settings.position_gain] * n,
            velocityGains=[1.0] * n, physicsClientId=self.client,
        )  # fmt: skip
        pb.setJointMotorControl2(
            self.body, WRIST_LINK, pb.POSITION_CONTROL, targetPosition=0.0, force=self.settings.arm_force,
            physicsClientId=self.client,
        )  # fmt: skip

    # --- acting -------------------------------------------------------------------------------
    def command(self, action: np.ndarray) -> tuple[np.ndarray, float, bool]:
        """Turn a normalised action (jaw, dx, dy, dz, dtheta) into a new commanded pose.

        Returns the commanded pivot, yaw and whether the workspace/yaw limits clipped it."""
        a = np.clip(np.asarray(action, dtype=float), -1.0, 1.0)
        want = self.target_pos + a[1:4] * DELTA_XYZ
        want_yaw = self.target_yaw + a[4] * DELTA_THETA
        yaw = float(np.clip(want_yaw, -YAW_LIMIT, YAW_LIMIT))
        pos = self.reachable(np.clip(want, *self.pivot_bounds()), yaw)
        clipped = bool(np.any(np.abs(pos - want) > 1e-12) or abs(yaw - want_yaw) > 1e-12)
        self.target_pos, self.target_yaw = pos, yaw
        self.jaw = float((a[0] + 1.0) / 2.0)  # the jaw action maps directly to an opening
        return pos, yaw, clipped

    def settle(self, step_physics) -> int:
        """Track the commanded pose with IK + motors until reached (or the step budget runs out).

        ``step_physics()`` advances the world one physics step. Returns the substeps used."""
        s = self.settings
        self._set_fingers(self.jaw)
        used = 0
        while used < s.max_substeps:
            self._drive(self._ik(self.target_pos, self.target_yaw))
            for _ in range(4):
                step_physics()
            used += 4
            if used < s.min_substeps:
                continue
            pos, yaw = self.pivot()
            if (
                np.linalg.norm(pos - self.target_pos) < s.tolerance_m
                and abs(wrap(yaw - self.target_yaw)) < s.tolerance_rad
                and self._fingers_still()
            ):
                break
        return used

    def _fingers_still(self) -> bool:
        """Fingers at their target, or blocked by something they hold."""
        states = pb.getJointStates(self.body, list(FINGER_JOINTS), physicsClientId=self.client)
        return all(abs(v) < 0.05 for _, v, _, _ in states)
