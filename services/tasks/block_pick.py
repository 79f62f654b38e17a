"""Block Pick: two identical 5 cm cubes, one fixed; pick the movable one above 0.08 m."""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb

from services.tasks.env import ManipulationEnv, Task, workspace_xy_margin
from services.tasks.experts import (
    Approach,
    Follower,
    ObservableExpert,
    nearest_object,
    nearest_symmetric_yaw,
    object_positions,
    object_yaws,
)

HALF = 0.025  # cube half extent (m)
MOVABLE_MASS = 0.02  # kg
LIFT_HEIGHT = 0.08  # tool centre above this while holding = success
LEFT_FINGER = (8, 9, 10)
RIGHT_FINGER = (11, 12, 13)


class BlockPick(Task):
    name = "block_pick"

    def build(self, client: int) -> None:
        self.client = client
        col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[HALF] * 3, physicsClientId=client)
        vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[HALF] * 3, rgbaColor=(0.2, 0.3, 0.9, 1),
                                   physicsClientId=client)  # fmt: skip
        # body 0 static (mass 0), body 1 movable; which slot each takes is random per episode
        self.fixed = pb.createMultiBody(0.0, col, vis, basePosition=(0.4, 0.1, HALF), physicsClientId=client)
        self.movable = pb.createMultiBody(MOVABLE_MASS, col, vis, basePosition=(0.6, -0.1, HALF),
                                          physicsClientId=client)  # fmt: skip
        for b in (self.fixed, self.movable):
            pb.changeDynamics(b, -1, lateralFriction=1.0, spinningFriction=0.001, physicsClientId=client)
        self.order = [self.fixed, self.movable]

    def reset(self, rng: np.random.Generator) -> None:
        lo, hi = workspace_xy_margin(0.05)
        while True:
            a, b = rng.uniform(lo, hi), rng.uniform(lo, hi)
            if np.linalg.norm(a - b) >= 2.4 * 2 * HALF:
                break
        yaws = rng.uniform(-math.pi / 4, math.pi / 4, size=2)
        self.order = [self.fixed, self.movable] if rng.integers(2) == 0 else [self.movable, self.fixed]
        for body, xy, yaw in zip(self.order, (a, b), yaws, strict=True):
            pb.resetBasePositionAndOrientation(
                body,
                (xy[0], xy[1], HALF),
                pb.getQuaternionFromEuler((0, 0, yaw)),
                physicsClientId=self.client,
            )
            pb.resetBaseVelocity(body, (0, 0, 0), (0, 0, 0), physicsClientId=self.client)

    def holding(self, env: ManipulationEnv) -> bool:
        touching = env.gripper_touches(self.movable)
        return bool(touching & set(LEFT_FINGER)) and bool(touching & set(RIGHT_FINGER))

    def success(self, env: ManipulationEnv) -> bool:
        return self.holding(env) and env.robot.tcp()[2] > LIFT_HEIGHT

    def expert(self, env: ManipulationEnv, style: str, rng: np.random.Generator):
        return PickExpert(env, self, style)

    def observable_expert(self, env: ManipulationEnv) -> ObservablePickExpert:
        """The expert whose decisions follow from the observation (demonstrations' default)."""
        return ObservablePickExpert(env)


class PickExpert:
    """Go above a cube, align, descend, close, lift. ``probe`` first tries the fixed cube.

    The first cube is approached at a safe height (``Approach``: pivot at or above L_z + 1 cm) up to
    the pre-contact pose straight above it, already at the grasp yaw, and the gripper then descends
    vertically. After a probe the open gripper rises to TRAVEL + 0.05 (pivot above L_z) and moves on
    to the movable cube at TRAVEL (no need to climb higher: nothing stands in between)."""

    TRAVEL = 0.12  # tool-centre height while moving between cubes (after the first grasp attempt)
    GRASP = (
        0.05  # tool-centre height when closing: closing swings the tips 1.3 cm down, still clear of the floor
    )

    def __init__(self, env: ManipulationEnv, task: BlockPick, style: str) -> None:
        self.env, self.task = env, task
        self.follow = Follower(env)
        targets = [task.fixed, task.movable] if style == "probe" else [task.movable]
        self.plan: list[tuple[int, str]] = []
        for body in targets:
            self.plan += [(body, "above"), (body, "down"), (body, "close"), (body, "lift")]
        self.approach = Approach(self.follow)
        self.i = 0
        self.wait = 0
        self.grasp_yaw: float | None = None  # frozen at the grasp: never turn a held cube

    def _cube(self, body: int) -> tuple[np.ndarray, float]:
        pos, quat = pb.getBasePositionAndOrientation(body, physicsClientId=self.env.client)
        return np.array(pos), pb.getEulerFromQuaternion(quat)[2]

    def act(self) -> np.ndarray:
        body, phase = self.plan[min(self.i, len(self.plan) - 1)]
        pos, cube_yaw = self._cube(body)
        if phase in ("close", "lift") and self.grasp_yaw is not None:
            yaw = self.grasp_yaw
        else:
            yaw = nearest_symmetric_yaw(cube_yaw, self.env.robot.target_yaw, 4)
            self.grasp_yaw = yaw if phase == "down" else None
        if phase == "above" and self.i == 0:  # first cube: safe-height approach
            a, done = self.approach.act(pos[:2], yaw, jaw=1.0)
        elif phase == "above":
            a, done = self.follow.action(np.array([pos[0], pos[1], self.TRAVEL]), yaw, jaw=1.0)
        elif phase == "down":
            a, done = self.follow.action(np.array([pos[0], pos[1], PickExpert.GRASP]), yaw, jaw=1.0)
        elif phase == "close":  # hold still while the fingers close
            a, _ = self.follow.action(self.env.robot.tcp(), yaw, jaw=0.0)
            self.wait += 1
            done = self.wait >= 2
        else:  # lift; after a probe, release and rise before the next cube
            last = self.i >= len(self.plan) - 1
            tip = self.env.robot.tcp()
            a, done = self.follow.action(
                np.array([tip[0], tip[1], self.TRAVEL + 0.05]), yaw, jaw=0.0 if last else 1.0
            )
            done = done and not last
        if done:
            self.i += 1
            self.wait = 0
        return a


class ObservablePickExpert(ObservableExpert):
    """The pick expert deciding from what it observes: ``act(obs)``.

    It grasps the cube nearest the gripper (``nearest_object``) as PickExpert grasps, then lifts
    with the jaw closed. A cube seen to rise with the gripper (RISE) is the movable one: the lift
    goes on (success ends the episode). A cube that has not risen after LIFT_TRIES lifting steps
    is released; the open gripper rises to TRAVEL + 0.05 and picks the other cube, which it then
    lifts without letting go (one of the two moves). Geometry and motion come from the observed
    cube poses, never from which cube is fixed or from contacts."""

    RISE = 0.01  # m: a cube this much higher than at the grasp rose with the gripper
    LIFT_TRIES = 2  # lifting steps before a cube that has not risen is let go

    def __init__(self, env: ManipulationEnv) -> None:
        super().__init__(env, "above")
        self.wait = 0
        self.tries = 0
        self.grasp_yaw: float | None = None  # frozen at the descent: never turn a held cube
        self.start_z = 0.0  # the target's observed height at the grasp

    def act(self, obs) -> np.ndarray:
        if self.target is None:
            self.target = nearest_object(obs)
        pos = object_positions(obs)[self.target]
        stays = pos[2] - self.start_z < self.RISE
        if self.phase == "lift" and self.first and self.tries >= self.LIFT_TRIES and stays:
            self.phase, self.wait = "release", 0  # bounded lift: this cube stays down
        robot = self.env.robot
        if self.phase in ("above", "down"):
            yaw = nearest_symmetric_yaw(float(object_yaws(obs)[self.target]), robot.target_yaw, 4)
            self.grasp_yaw = yaw
            if self.phase == "above" and self.first:
                a, done = self.approach.act(pos[:2], yaw, jaw=1.0)
            else:
                height = PickExpert.TRAVEL if self.phase == "above" else PickExpert.GRASP
                a, done = self.follow.action(np.array([pos[0], pos[1], height]), yaw, jaw=1.0)
            if done:
                self.phase = "down" if self.phase == "above" else "close"
        elif self.phase == "close":  # hold still while the fingers close
            a, _ = self.follow.action(robot.tcp(), self.grasp_yaw, jaw=0.0)
            self.wait += 1
            if self.wait >= 2:
                self.phase, self.tries, self.start_z = "lift", 0, float(pos[2])
        elif self.phase == "lift":
            tip = robot.tcp()
            a, _ = self.follow.action(
                np.array([tip[0], tip[1], PickExpert.TRAVEL + 0.05]), self.grasp_yaw, jaw=0.0
            )
            self.tries += 1
        elif self.phase == "release":  # open in place before rising
            a, _ = self.follow.action(robot.tcp(), self.grasp_yaw, jaw=1.0)
            self.wait += 1
            if self.wait >= 1:
                self.phase = "rise"
        else:  # rise with the jaw open, then the other cube
            tip = robot.tcp()
            a, done = self.follow.action(
                np.array([tip[0], tip[1], PickExpert.TRAVEL + 0.05]), self.grasp_yaw, jaw=1.0
            )
            if done:
                self.phase, self.target, self.first = "above", 1 - self.target, False
        return a
