"""The manipulation POMDP shared by every task (paper Sec. IV-C).

Observation: point-cloud segments of the gripper and of each task object, in the gripper-centric
frame (origin at the centroid of the gripper's points, world orientation), plus the jaw opening.
The centroid is a fixed point of the gripper body: it is measured from the fused camera views once
(open jaw, free space) and then follows the gripper by forward kinematics.
Action: (jaw, dx, dy, dz, dtheta) in [-1, 1]^5, Delta_xyz = 0.05 m, Delta_theta = pi/8.
Reward: 1 on success (which terminates), else 0; the time limit truncates.
Privileged state (gripper pose, object poses, contacts) is recorded beside the observation for
MEA and the audit; a policy never sees it.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import pybullet as pb
import pybullet_data

from proto.actions import ACTION_DIM
from services.tasks.camera import (
    Cameras,
    CameraSettings,
    SceneView,
    paint_fingers,
    render_gripper_depth,
    render_rgb,
    sample_fixed,
)
from services.tasks.robot import GRIPPER_LINKS, WORKSPACE, WRIST_LINK, ControlSettings, Robot

SegmentParts = list[tuple[int, int | None]]  # (body id, link index or None for the whole body)

HIDDEN = (1.0, 1.0, 1.0, 0.0)
"""The floor's and the arm's colour: the observation's cameras skip them (alpha 0)."""
SHOWN = {"floor": (0.82, 0.82, 0.78, 1.0), "arm": (0.72, 0.74, 0.8, 1.0)}
"""Their colours in a third-person picture (``render_scene``)."""

DEPTH_IMAGE_REVISION = 2
"""The revision of ``_baseline_image``'s rendering, saved in a run's config.json by ``mea run``: 2
draws the floor, as the public environments do (2026-11-28); runs saved without it rendered none. A
depth-image run of another revision is not resumed (``read_resume``): its replay would mix two
observations. Change it with the rendering."""

SETTLE_STEPS = 10
"""Physics steps the world rests after the arm is placed (``reset``, ``place_state``): objects
settle on the floor before the first observation."""
GRIPPER_STARTS = ("random", "fixed")
"""Gripper poses at reset: ``random`` (each task's ``initial_gripper``: MEA's premise of a random
initial state) or ``fixed`` at ``FIXED_GRIPPER`` (the public Equi-RSAC environments' start)."""
FIXED_GRIPPER = ((0.5, 0.0), 0.0)
"""Pivot x, y (m) and yaw (rad) of the ``fixed`` start: the workspace centre, yaw 0."""


def check_action(action: np.ndarray) -> np.ndarray:
    """``action`` as ``ACTION_DIM`` floats, or a ValueError naming what is wrong with it."""
    a = np.asarray(action, dtype=float)
    if a.shape != (ACTION_DIM,):
        raise ValueError(f"action: expected shape ({ACTION_DIM},) (jaw, dx, dy, dz, dtheta), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"action: every component must be finite, got {a.tolist()}")
    return a


@dataclass(frozen=True)
class EnvSettings:
    """Simulation, control and observation settings shared by every task."""

    max_steps: int = 50
    """Time limit (steps); reaching it truncates the episode."""
    initial_tip_height: float = 0.2
    """Finger-tip height (m) at reset: fixed, so MEA knows the initial gripper height."""
    gripper_start: str = "random"
    """Gripper x, y and yaw at reset: random or fixed (GRIPPER_STARTS)."""
    depth_image: bool = False
    """Also render the baseline observation (public Equi-RSAC top-down depth image)."""
    depth_image_size: int = 84
    """Pixels per side of the baseline depth image."""
    camera: CameraSettings = field(default_factory=CameraSettings)
    """Camera rig and point sampling."""
    control: ControlSettings = field(default_factory=ControlSettings)
    """Arm control."""

    def __post_init__(self) -> None:
        if self.gripper_start not in GRIPPER_STARTS:
            raise ValueError(f"gripper_start must be one of {GRIPPER_STARTS}, not {self.gripper_start!r}")


@dataclass
class Observation:
    """One observation plus the privileged state recorded beside it."""

    points: np.ndarray  # (S, P, 3) float32, gripper-centric
    point_counts: np.ndarray  # (S,) int32
    jaw: float  # measured opening, 0 closed .. 1 open
    gripper_pose: np.ndarray  # (4,) float32 pivot x, y, z (world) and yaw: privileged
    object_poses: np.ndarray  # (M, 7) float32 world pose per object: privileged
    contacts: np.ndarray  # (M,) bool gripper touches object i: privileged
    depth_image: np.ndarray | None = None  # (N, N) float32 baseline image, when enabled
    image: np.ndarray | None = None  # (C, H, W) uint8 policy image the env renders itself (surgical DSA)
    controller_state: int = 0  # 1: a built-in controller takes the next action (surgical hybrid control)
    fsm_state: int | None = None  # index of the task's FSM state, where it has one (surgical)


class Task(ABC):
    """A task: its objects, how they are placed, when it succeeds, and its scripted experts."""

    name: str = ""
    object_names: tuple[str, ...] = ("object_0", "object_1")

    @abstractmethod
    def build(self, client: int) -> None:
        """Create the task's bodies once (they are re-posed, never re-created, at reset)."""

    @abstractmethod
    def reset(self, rng: np.random.Generator) -> None:
        """Place objects and choose which one is movable (hidden from the policy)."""

    def object_segments(self) -> dict[str, SegmentParts]:
        """Segment name -> bodies/links whose points form it (same order as object_names).

        Default: one whole body per slot of ``self.order`` (the bodies in their hidden order)."""
        return {name: [(body, None)] for name, body in zip(self.object_names, self.order, strict=True)}

    def object_poses(self) -> np.ndarray:
        """(M, 7) world poses (x, y, z, qx, qy, qz, qw) of the objects, in object_names order."""
        out = []
        for body in self.order:
            pos, quat = pb.getBasePositionAndOrientation(body, physicsClientId=self.client)
            out.append([*pos, *quat])
        return np.array(out)

    @abstractmethod
    def success(self, env: ManipulationEnv) -> bool:
        """Task goal reached in the current state."""

    @abstractmethod
    def expert(self, env: ManipulationEnv, style: str, rng: np.random.Generator):
        """A scripted (privileged) expert: an object with ``act() -> action`` for ``style`` in
        EXPERT_STYLES. The general tasks also have ``observable_expert(env)``, whose ``act(obs)``
        decides only from the observation; demonstrations use it by default (docs/tasks.md)."""

    def fixed_index(self) -> int:
        """Slot (index into object_names) of the immovable object: privileged, for checks only.

        Default: tasks keep ``self.order`` (bodies by slot) and ``self.fixed`` (the immovable body)."""
        return self.order.index(self.fixed)

    def initial_gripper(self, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        """Initial pivot x, y and yaw (the height is fixed by EnvSettings). x stops at 0.6: at the start
        height the arm reaches the pivot only to x ~ 0.65, and a first move must not stall."""
        xy = rng.uniform([0.35, -0.15], [0.6, 0.15])
        return xy, float(rng.uniform(-math.pi / 2, math.pi / 2))


EXPERT_STYLES = ("probe", "direct")  # probe: touch the fixed object first; direct: go to the movable one


class ManipulationEnv:
    """pybullet DIRECT simulation of one task; ``reset(seed)`` then ``step(action)``."""

    def __init__(self, task: Task, settings: EnvSettings = EnvSettings()) -> None:
        self.task = task
        self.settings = settings
        self.client = pb.connect(pb.DIRECT)
        c = self.client
        pb.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=c)
        pb.setGravity(0, 0, -9.8, physicsClientId=c)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=1.0 / settings.control.sim_hz, numSolverIterations=settings.control.solver_iterations,
            deterministicOverlappingPairs=1, physicsClientId=c,
        )  # fmt: skip
        self.floor = pb.loadURDF("plane.urdf", physicsClientId=c)
        pb.changeVisualShape(self.floor, -1, rgbaColor=HIDDEN, physicsClientId=c)  # not observed
        self.robot = Robot(c, settings.control)
        self.cameras = Cameras(c, settings.camera)
        self.segment_names = ("gripper", *task.object_names)
        self._calibrate()
        task.build(c)
        self._saved = pb.saveState(physicsClientId=c)
        self.seed = 0
        self.t = 0
        self.substeps = 0

    # --- geometry -----------------------------------------------------------------------------
    def gripper_parts(self) -> SegmentParts:
        """The bodies/links whose points form the gripper segment."""
        return [(self.robot.body, link) for link in GRIPPER_LINKS]

    def segment_clouds(self) -> dict[str, np.ndarray]:
        """Everything the cameras see of each segment now, world frame, before the draw of P points."""
        return self.cameras.render_segments({"gripper": self.gripper_parts(), **self.task.object_segments()})

    def _calibrate(self) -> None:
        """Find the gripper's point centroid in the flange frame (the controller's pivot)."""
        r = self.robot
        r.reset(np.array([0.5, 0.0, 0.3]), 0.0, jaw=1.0)
        pts = self.cameras.render_segments({"gripper": self.gripper_parts()})["gripper"]
        fpos, fquat = r.flange_pose()
        m = np.array(pb.getMatrixFromQuaternion(fquat)).reshape(3, 3)
        r.calibrate(m.T @ (pts.mean(axis=0) - fpos))

    def step_physics(self) -> None:
        pb.stepSimulation(physicsClientId=self.client)
        self.substeps += 1

    # --- POMDP --------------------------------------------------------------------------------
    def _forget_contacts(self) -> None:
        """Drop Bullet's cached contact pairs before restoring the saved state.

        restoreState keeps contact manifolds: objects pressed together (or against the gripper)
        at the end of one episode would carry stale penetration into the next and make it depend
        on the last. Moving every body but the arm far apart and running collision detection
        makes the broadphase free all their pairs; restoreState then puts everything back."""
        c = self.client
        for i in range(pb.getNumBodies(physicsClientId=c)):
            uid = pb.getBodyUniqueId(i, physicsClientId=c)
            if uid != self.robot.body:
                pb.resetBasePositionAndOrientation(
                    uid, (100.0 + 10.0 * i, 0.0, 100.0), (0, 0, 0, 1), physicsClientId=c
                )
        pb.performCollisionDetection(physicsClientId=c)

    def reset(self, seed: int) -> Observation:
        self._forget_contacts()
        pb.restoreState(self._saved, physicsClientId=self.client)
        self.seed, self.t = int(seed), 0
        rng = np.random.default_rng(self.seed)
        self.task.reset(rng)
        xy, yaw = self.task.initial_gripper(rng)  # drawn either way: the same rng stream per seed
        if self.settings.gripper_start == "fixed":
            xy, yaw = np.array(FIXED_GRIPPER[0]), FIXED_GRIPPER[1]
        z = self.settings.initial_tip_height + self.robot.tip_drop
        self.robot.reset(np.array([xy[0], xy[1], z]), yaw, jaw=1.0)
        self._rest()
        return self.observe()

    def place_state(
        self,
        seed: int,
        pivot_pose: np.ndarray,
        jaw: float,
        *,
        sampling_seed: int | None = None,
        arrange: Callable[[], None] | None = None,
    ) -> Observation:
        """Reset from ``seed``, call ``arrange()`` (e.g. ``move_scene``), and teleport the arm to
        ``pivot_pose`` (pivot x, y, z, yaw) with the jaw at ``jaw``; the world then rests as long as
        after ``reset``, and the observation of that state is returned.

        ``sampling_seed`` replaces the seed the observed points are drawn with: ``observe`` seeds
        its sampler with (seed, step), and the seed serves nothing else once the reset has placed
        the objects, so replacing it changes only which points are drawn."""
        self.reset(seed)
        if sampling_seed is not None:
            self.seed = int(sampling_seed)
        if arrange is not None:
            arrange()
        pose = np.asarray(pivot_pose, np.float64)
        self.robot.reset(pose[:3], float(pose[3]), jaw=float(jaw))
        self._rest()
        return self.observe()

    def move_scene(
        self, turn: float, shift: Sequence[float], cos_sin: tuple[float, float] | None = None
    ) -> None:
        """Move every body but the floor and the arm rigidly, as it is now: ``x -> R(turn) x + shift``
        about the world z axis (``shift``: x, y in m), orientations and velocities turned alike;
        joint states (a drawer's opening) are kept. ``cos_sin``: cos and sin of ``turn`` where the
        caller has them exact (quarter turns); default ``math.cos``/``math.sin``."""
        c, s = cos_sin if cos_sin is not None else (math.cos(turn), math.sin(turn))
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        qz = (0.0, 0.0, math.sin(turn / 2), math.cos(turn / 2))
        offset = np.r_[shift, 0.0]
        cid = self.client
        for i in range(pb.getNumBodies(physicsClientId=cid)):
            body = pb.getBodyUniqueId(i, physicsClientId=cid)
            if body in (self.floor, self.robot.body):
                continue
            pos, quat = pb.getBasePositionAndOrientation(body, physicsClientId=cid)
            lin, ang = pb.getBaseVelocity(body, physicsClientId=cid)
            new_pos = rot @ np.asarray(pos) + offset
            _, new_quat = pb.multiplyTransforms((0, 0, 0), qz, (0, 0, 0), quat)
            pb.resetBasePositionAndOrientation(body, new_pos.tolist(), new_quat, physicsClientId=cid)
            pb.resetBaseVelocity(body, (rot @ lin).tolist(), (rot @ ang).tolist(), physicsClientId=cid)

    def _rest(self) -> None:
        for _ in range(SETTLE_STEPS):  # let objects rest on the floor
            self.step_physics()

    def step(self, action: np.ndarray) -> tuple[Observation, float, bool, bool, dict]:
        """One env step. An action that is not ``ACTION_DIM`` finite numbers is refused with a
        ValueError naming what is wrong, before anything (robot, physics, time) changes."""
        a = check_action(action)
        _, _, clipped = self.robot.command(a)
        self.robot.settle(self.step_physics)
        self.t += 1
        obs = self.observe()
        success = bool(self.task.success(self))
        truncated = not success and self.t >= self.settings.max_steps
        return obs, float(success), success, truncated, {"success": success, "clipped": clipped}

    def observe(self) -> Observation:
        s = self.settings
        world = self.segment_clouds()
        # The frame origin is the centroid of the gripper's points, measured once in free space at
        # calibration and carried by forward kinematics: per-frame centroids jitter by millimetres
        # as the fixed cameras see different sides of the moving gripper.
        pivot, yaw = self.robot.pivot()
        origin = pivot
        rng = np.random.default_rng([self.seed, self.t, 1])  # sampling depends only on (seed, step)
        P = s.camera.points_per_segment
        points = np.zeros((len(self.segment_names), P, 3), np.float32)
        counts = np.zeros(len(self.segment_names), np.int32)
        for i, name in enumerate(self.segment_names):
            pts, n = sample_fixed(world[name] - origin if len(world[name]) else world[name], P, rng)
            points[i], counts[i] = pts, n
        image = self._baseline_image(pivot, yaw) if s.depth_image else None
        return Observation(
            points=points,
            point_counts=counts,
            jaw=self.robot.jaw_opening(),
            gripper_pose=np.array([*pivot, yaw], np.float32),
            object_poses=self.task.object_poses().astype(np.float32),
            contacts=self.contacts(),
            depth_image=image,
        )

    def _baseline_image(self, pivot: np.ndarray, yaw: float) -> np.ndarray:
        """The public Equi-RSAC observation: gripper-centred orthographic depth, fingers painted, the
        floor seen (as in the public environments: wherever no object is, the image reads the
        gripper's height above the floor; the point-cloud cameras never see it)."""
        body, c = self.robot.body, self.client
        for link in GRIPPER_LINKS:  # the camera sits inside the gripper: hide it, paint the fingers
            pb.changeVisualShape(body, link, rgbaColor=(1, 1, 1, 0), physicsClientId=c)
        pb.changeVisualShape(self.floor, -1, rgbaColor=SHOWN["floor"], physicsClientId=c)
        try:
            image = render_gripper_depth(c, pivot, size=self.settings.depth_image_size)
        finally:
            pb.changeVisualShape(self.floor, -1, rgbaColor=HIDDEN, physicsClientId=c)
            for link in GRIPPER_LINKS:
                pb.changeVisualShape(body, link, rgbaColor=(0.6, 0.6, 0.6, 1), physicsClientId=c)
        return paint_fingers(image, pivot, self.robot.tcp(), yaw, self.robot.pad_gap(), 0.4)

    def render_scene(self, size: int = 256) -> np.ndarray:
        """A third-person colour picture (size, size, 3) uint8 of the scene with the floor and the arm
        shown (``SceneView``): for videos, never observed. They are hidden again before it returns,
        so the observation and the physics are as without it."""
        c = self.client
        shown = [(self.floor, -1, SHOWN["floor"])]
        shown += [(self.robot.body, link, SHOWN["arm"]) for link in range(-1, WRIST_LINK)]
        for body, link, rgba in shown:
            pb.changeVisualShape(body, link, rgbaColor=rgba, physicsClientId=c)
        try:
            return render_rgb(c, SceneView(size=size))
        finally:
            for body, link, _ in shown:
                pb.changeVisualShape(body, link, rgbaColor=HIDDEN, physicsClientId=c)

    def contacts(self) -> np.ndarray:
        out = np.zeros(len(self.task.object_names), bool)
        for i, parts in enumerate(self.task.object_segments().values()):
            for body, _ in parts:
                pts = pb.getContactPoints(bodyA=self.robot.body, bodyB=body, physicsClientId=self.client)
                if any(p[3] in GRIPPER_LINKS for p in pts):
                    out[i] = True
        return out

    def gripper_touches(self, body: int, links: tuple[int, ...] = GRIPPER_LINKS) -> set[int]:
        """Gripper links touching ``body``."""
        pts = pb.getContactPoints(bodyA=self.robot.body, bodyB=body, physicsClientId=self.client)
        return {p[3] for p in pts if p[3] in links}

    def close(self) -> None:
        if self.client is not None and pb.isConnected(self.client):
            pb.disconnect(self.client)
        self.client = None


def workspace_xy_margin(margin: float) -> tuple[np.ndarray, np.ndarray]:
    """x, y bounds shrunk by ``margin`` (object placement)."""
    return WORKSPACE[:2, 0] + margin, WORKSPACE[:2, 1] - margin
