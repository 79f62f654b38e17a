"""Block Pull: two identical flat blocks, one fixed; drag the movable one until the two touch.

Both blocks share an x and lie apart along y; which one is fixed is drawn per episode and is
invisible (same shape, size and colour). The scripted expert closes the jaw into a paddle, travels
at a safe height (pivot at or above L_z + 1 cm) to straight above the far side of a block (the side
away from the other block) with the jaw's closing axis across the line between the blocks, lowers
it vertically and drags the block along that line. The ``probe`` style first tries this on the
fixed block (and so touches it), then lifts and does the same on the movable one. The observable
expert (the demonstrations' default) tries the nearest block and switches only if it did not move.
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb

from services.tasks.env import ManipulationEnv, Task
from services.tasks.experts import (
    Approach,
    Follower,
    ObservableExpert,
    moved,
    nearest_object,
    object_positions,
    object_yaws,
)
from services.tasks.robot import WORKSPACE

HALF = np.array([0.05, 0.05, 0.025])  # block half extents (m)
MOVABLE_MASS = 0.5  # kg
MIN_SEPARATION = 3.4 * HALF[0]  # centre distance at reset (m)
BLOCK_X = (0.4, 0.6)  # range of the blocks' shared x (m)
TOUCH_DISTANCE = 0.002  # blocks closer than this count as touching (m)

# Expert geometry (closed jaw, gripper yaw 0). The closed tips form a paddle 6.6 cm wide along x
# and 2.5 cm thick along y, centred on the tool centre; at yaw 0 the pivot sits 13.3 mm on the
# -y side of the tool centre, so the tool centre reaches y in [-0.187, 0.213] (placement below
# keeps every paddle goal inside that band).
PADDLE_HALF = 0.0125  # half thickness (y) of the closed-tip paddle (m)
CLEARANCE = 0.008  # gap between paddle and block when lowering behind it (m)
TCP_Y_RANGE = (WORKSPACE[1, 0] + 0.0133 + 0.002, WORKSPACE[1, 1] + 0.0133 - 0.002)
PUSH_YAW = 0.0  # jaw closing axis along x: across the pulling line (the y axis)
# Initial pivot x, y range. x stops at 0.6 (the default goes to 0.65): with the tips at 0.2 m the arm
# reaches the pivot only up to x = 0.65-0.67 (fully stretched elbow), so a first +x action from
# x > 0.62 would stall short of its command and break the transition prior.
INITIAL_XY = ((0.35, -0.15), (0.6, 0.15))


def footprint(yaw: float) -> float:
    """Half extent along y of a block turned by ``yaw`` (its x extent is the same)."""
    return float(HALF[0] * (abs(math.cos(yaw)) + abs(math.sin(yaw))))


def standoff(yaw: float) -> float:
    """Tool-centre distance (y) from a block's centre at which the paddle is lowered."""
    return footprint(yaw) + PADDLE_HALF + CLEARANCE


def block_yaw(quat) -> float:
    return float(pb.getEulerFromQuaternion(quat)[2])


class BlockPull(Task):
    name = "block_pull"

    def build(self, client: int) -> None:
        self.client = client
        col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=HALF.tolist(), physicsClientId=client)
        vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=HALF.tolist(), rgbaColor=(0.9, 0.5, 0.2, 1),
                                   physicsClientId=client)  # fmt: skip
        # one static (mass 0) and one movable body; which slot each takes is random per episode
        self.fixed = pb.createMultiBody(
            0.0, col, vis, basePosition=(0.5, 0.1, HALF[2]), physicsClientId=client
        )
        self.movable = pb.createMultiBody(MOVABLE_MASS, col, vis, basePosition=(0.5, -0.1, HALF[2]),
                                          physicsClientId=client)  # fmt: skip
        for b in (self.fixed, self.movable):
            pb.changeDynamics(b, -1, lateralFriction=0.5, spinningFriction=0.001, physicsClientId=client)
        self.order = [self.fixed, self.movable]

    @staticmethod
    def sample_layout(rng: np.random.Generator) -> tuple[float, np.ndarray, np.ndarray]:
        """Shared x, the two y's and yaws: centres more than MIN_SEPARATION apart, each block
        inside the workspace, and the paddle goal beyond each block (away from the other)
        reachable, so the probe can visit either."""
        x = float(rng.uniform(*BLOCK_X))
        while True:
            yaws = rng.uniform(-math.pi / 4, math.pi / 4, size=2)
            ys = rng.uniform(TCP_Y_RANGE[0], TCP_Y_RANGE[1], size=2)
            if abs(ys[0] - ys[1]) <= MIN_SEPARATION:
                continue
            hi, lo = (0, 1) if ys[0] > ys[1] else (1, 0)
            if ys[hi] + standoff(yaws[hi]) > TCP_Y_RANGE[1] or ys[lo] - standoff(yaws[lo]) < TCP_Y_RANGE[0]:
                continue
            inside = [abs(y) + footprint(w) <= WORKSPACE[1, 1] - 0.005 for y, w in zip(ys, yaws, strict=True)]
            if all(inside):
                return x, ys, yaws

    def reset(self, rng: np.random.Generator) -> None:
        x, ys, yaws = self.sample_layout(rng)
        self.order = [self.fixed, self.movable] if rng.integers(2) == 0 else [self.movable, self.fixed]
        for body, y, yaw in zip(self.order, ys, yaws, strict=True):
            pb.resetBasePositionAndOrientation(
                body, (x, float(y), HALF[2]), pb.getQuaternionFromEuler((0, 0, float(yaw))),
                physicsClientId=self.client,
            )  # fmt: skip
            pb.resetBaseVelocity(body, (0, 0, 0), (0, 0, 0), physicsClientId=self.client)

    def initial_gripper(self, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        xy = rng.uniform(*INITIAL_XY)
        return xy, float(rng.uniform(-math.pi / 2, math.pi / 2))

    def touching(self) -> bool:
        c = self.client
        if pb.getContactPoints(self.fixed, self.movable, physicsClientId=c):
            return True
        return bool(pb.getClosestPoints(self.fixed, self.movable, TOUCH_DISTANCE, physicsClientId=c))

    def success(self, env: ManipulationEnv) -> bool:
        return self.touching()

    def expert(self, env: ManipulationEnv, style: str, rng: np.random.Generator):
        if style == "probe":
            return PullExpert(env, self, [self.fixed, self.movable])
        if style == "direct":
            return PullExpert(env, self, [self.movable])
        raise ValueError(f"unknown expert style {style!r}")

    def observable_expert(self, env: ManipulationEnv) -> ObservablePullExpert:
        """The expert whose decisions follow from the observation (demonstrations' default)."""
        return ObservablePullExpert(env)


class PullExpert:
    """Close the jaw, travel above the far side of a block, lower the paddle behind it, drag the
    block toward the other one. Every block but the last is dragged at only until the gripper
    touches it (or a few tries), then the paddle lifts and moves on; the last is dragged until
    the episode ends. ``probe`` = [fixed, movable], ``direct`` = [movable].

    The first block is approached at a safe height (``Approach``: pivot at or above L_z + 1 cm) up
    to the pre-contact pose straight above its far side, already at the drag yaw; the paddle then
    descends vertically. Between blocks it lifts to TRAVEL only (the blocks are 5 cm tall)."""

    TRAVEL = 0.12  # tool-centre height between blocks (closed tips 7.5 cm up, blocks 5 cm tall)
    PUSH_Z = 0.056  # tool-centre height while dragging: closed tips about 1 cm above the floor
    PUSH_STEP = 0.04  # drag per step (m)
    PROBE_STEP = CLEARANCE + 0.004  # a probe's push: 4 mm past touching (pressing a static block
    # harder only forces the paddle open by an amount that depends on the arm's configuration)
    PROBE_PUSHES = 3  # most drag attempts at a probed block before moving on

    def __init__(self, env: ManipulationEnv, task: BlockPull, targets: list[int]) -> None:
        self.env, self.task = env, task
        self.follow = Follower(env)
        self.plan: list[tuple[int, str]] = []
        for k, body in enumerate(targets):
            self.plan += [(body, "travel"), (body, "lower"), (body, "drag")]
            if k < len(targets) - 1:
                self.plan.append((body, "lift"))
        self.approach = Approach(self.follow)
        self.i = 0
        self.pushes = 0

    def _pose(self, body: int) -> tuple[np.ndarray, float]:
        pos, quat = pb.getBasePositionAndOrientation(body, physicsClientId=self.env.client)
        return np.array(pos), block_yaw(quat)

    def _far_side(self, body: int) -> tuple[np.ndarray, float]:
        """Paddle goal beyond ``body`` (away from the other block) and the outward direction (+-1)."""
        pos, yaw = self._pose(body)
        other = self.task.movable if body == self.task.fixed else self.task.fixed
        out = 1.0 if pos[1] >= self._pose(other)[0][1] else -1.0
        return np.array([pos[0], pos[1] + out * standoff(yaw)]), out

    def act(self) -> np.ndarray:
        body, phase = self.plan[min(self.i, len(self.plan) - 1)]
        probing = phase == "drag" and self.i < len(self.plan) - 1
        # a probed block is dragged at until touched (or a few tries), then the paddle lifts
        if probing and (self.env.gripper_touches(body) or self.pushes >= self.PROBE_PUSHES):
            self.i += 1
            self.pushes = 0
            body, phase = self.plan[self.i]
        goal_xy, out = self._far_side(body)
        tip = self.env.robot.tcp()
        done = False
        if phase == "travel" and self.i == 0:  # first block: safe-height approach
            a, done = self.approach.act(goal_xy, PUSH_YAW, jaw=0.0)
        elif phase == "travel":
            a, done = self.follow.action(np.array([*goal_xy, self.TRAVEL]), PUSH_YAW, jaw=0.0)
        elif phase == "lower":
            a, done = self.follow.action(np.array([*goal_xy, self.PUSH_Z]), PUSH_YAW, jaw=0.0)
        elif phase == "drag":
            x = self._pose(body)[0][0]  # stay centred on the block as it slides
            step = self.PROBE_STEP if probing else self.PUSH_STEP
            goal = np.array([x, tip[1] - out * step, self.PUSH_Z])
            a, _ = self.follow.action(goal, PUSH_YAW, jaw=0.0)
            self.pushes += 1
        else:  # lift straight up before travelling to the next block
            a, done = self.follow.action(np.array([tip[0], tip[1], self.TRAVEL]), PUSH_YAW, jaw=0.0)
        if done:
            self.i += 1
        return a


class ObservablePullExpert(ObservableExpert):
    """The pull expert deciding from what it observes: ``act(obs)``.

    It goes to the block nearest the gripper (``nearest_object``), lowers the paddle behind its far
    side and probes it with short pushes (PullExpert.PROBE_STEP). If the block is seen to move
    (``moved``) it drags it into the other one; if it has not moved after PROBE_PUSHES pushes, the
    paddle lifts and drags the other block, without probing it (one of the two moves). Geometry
    and motion come from the observed block poses, never from which block is fixed or from
    contacts; motion is measured against the block's position when the probe began."""

    def __init__(self, env: ManipulationEnv) -> None:
        super().__init__(env, "travel")
        self.known = False  # the target is known to be the movable block
        self.pushes = 0
        self.start: np.ndarray | None = None  # the target's observed position when its probe began

    def _far_side(self, obs) -> tuple[np.ndarray, float]:
        """Paddle goal beyond the target (away from the other block) and the outward direction."""
        pos, yaw = object_positions(obs), object_yaws(obs)
        t = self.target
        out = 1.0 if pos[t, 1] >= pos[1 - t, 1] else -1.0
        return np.array([pos[t, 0], pos[t, 1] + out * standoff(float(yaw[t]))]), out

    def act(self, obs) -> np.ndarray:
        if self.target is None:
            self.target = nearest_object(obs)
        if self.phase == "probe":
            if moved(obs, self.target, self.start):
                self.phase, self.known = "drag", True
            elif self.pushes >= PullExpert.PROBE_PUSHES:  # bounded probe: it does not move
                self.phase, self.target, self.known, self.first = "lift", 1 - self.target, True, False
        goal_xy, out = self._far_side(obs)
        tip = self.env.robot.tcp()
        if self.phase == "travel":
            if self.first:
                a, done = self.approach.act(goal_xy, PUSH_YAW, jaw=0.0)
            else:
                a, done = self.follow.action(np.array([*goal_xy, PullExpert.TRAVEL]), PUSH_YAW, jaw=0.0)
            if done:
                self.phase = "lower"
        elif self.phase == "lower":
            a, done = self.follow.action(np.array([*goal_xy, PullExpert.PUSH_Z]), PUSH_YAW, jaw=0.0)
            if done:
                self.phase = "drag" if self.known else "probe"
                self.start = object_positions(obs)[self.target]
        elif self.phase in ("probe", "drag"):
            x = object_positions(obs)[self.target, 0]  # stay centred on the block as it slides
            step = PullExpert.PUSH_STEP if self.phase == "drag" else PullExpert.PROBE_STEP
            goal = np.array([x, tip[1] - out * step, PullExpert.PUSH_Z])
            a, _ = self.follow.action(goal, PUSH_YAW, jaw=0.0)
            self.pushes += self.phase == "probe"
        else:  # lift straight up before travelling to the other block
            a, done = self.follow.action(np.array([tip[0], tip[1], PullExpert.TRAVEL]), PUSH_YAW, jaw=0.0)
            if done:
                self.phase = "travel"
        return a
