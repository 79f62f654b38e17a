"""Scripted experts: privileged waypoint followers (BulletArm's close-loop planner idea).

Each step moves the commanded gripper toward the current goal, deltas clipped to one action's
reach, so expert actions are ordinary normalised actions. Goals are stated for the tool centre
point (between the finger tips), which is what grasping cares about.

Every expert opens with an approach like the public task suites' planners: rise above L_z if the
gripper starts below it, travel horizontally at a safe height (pivot at or above L_z + 1 cm, as
high as the start and the arm's reach allow) to a pre-contact pose directly above the target, turned
to the grasp/drag yaw on the way, and only then descend straight down. MEA augments only steps made
above L_z (its non-trivial phase), so this approach is what it has to work with.
"""

from __future__ import annotations

import math

import numpy as np

from proto.actions import DELTA_THETA, DELTA_XYZ
from services.tasks.robot import wrap

LZ = 0.27  # MEA's L_z (MeaSettings.lz): pivot height at or above which no object can be touched
SAFE_Z = LZ + 0.01  # lowest pivot height of the approach's travel (1 cm margin over L_z)
HEIGHT_STEP = 0.005  # m: the travel height is lowered in these steps until the arm reaches the goal


def nearest_symmetric_yaw(object_yaw: float, current: float, order: int) -> float:
    """The yaw among ``object_yaw + k*2pi/order`` closest to ``current`` (e.g. order 4 for a cube)."""
    step = 2 * math.pi / order
    k = round((current - object_yaw) / step)
    return object_yaw + k * step


class Follower:
    """Turns (tool-centre goal, yaw, jaw) into one normalised action for the env's robot."""

    def __init__(self, env) -> None:
        self.env = env

    def pivot_goal(self, tip_goal: np.ndarray, yaw_goal: float) -> np.ndarray:
        """Pivot position that puts the tool centre at ``tip_goal`` once turned to ``yaw_goal``."""
        r = self.env.robot
        pivot, _ = r.pivot()
        offset = pivot - r.tcp()  # pivot relative to the tool centre, at the current yaw
        turn = wrap(yaw_goal - r.target_yaw)
        c, s = math.cos(turn), math.sin(turn)
        offset = np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1], offset[2]])
        return np.asarray(tip_goal, dtype=float) + offset

    def action(
        self,
        tip_goal: np.ndarray,
        yaw_goal: float,
        jaw: float,
        tol: float = 1e-3,
        pivot_z: float | None = None,
    ) -> tuple[np.ndarray, bool]:
        """Action toward the goal, and whether the goal is reached after it. ``pivot_z``, when
        given, replaces the goal's height by a height of the pivot (the approach's travel)."""
        goal = self.pivot_goal(tip_goal, yaw_goal)
        if pivot_z is not None:
            goal[2] = pivot_z
        return self.pivot_action(goal, yaw_goal, jaw, tol)

    def pivot_action(
        self, pivot_goal: np.ndarray, yaw_goal: float, jaw: float, tol: float = 1e-3
    ) -> tuple[np.ndarray, bool]:
        """Action moving the commanded pivot toward ``pivot_goal``, and whether it is reached after it."""
        r = self.env.robot
        turn = wrap(yaw_goal - r.target_yaw)
        delta = np.asarray(pivot_goal, dtype=float) - r.target_pos
        a = np.zeros(5)
        a[0] = 2.0 * jaw - 1.0
        # (dx, dy) limited by its norm, not per axis: a step no longer than one action's reach in any
        # horizontal direction stays inside [-1, 1] under every rotation, so the isometric copies of
        # a demonstration may take any angle (a saturated diagonal step only admits multiples of 90)
        v = delta / DELTA_XYZ
        a[1:3] = v[:2] / max(1.0, float(np.hypot(v[0], v[1])))
        a[3] = np.clip(v[2], -1.0, 1.0)
        a[4] = np.clip(turn / DELTA_THETA, -1.0, 1.0)
        reached = bool(
            np.hypot(delta[0], delta[1]) <= DELTA_XYZ + tol
            and abs(delta[2]) <= DELTA_XYZ + tol
            and abs(turn) <= DELTA_THETA + 1e-6
        )
        return a, reached


class Approach:
    """The opening of every expert: rise straight up if the pivot is below SAFE_Z, then travel at a
    constant height to the pre-contact pose above the target (tool centre above ``tip_xy``, gripper
    at ``yaw``). The travel height is chosen once: the commanded height, at least SAFE_Z, lowered
    (not below SAFE_Z) until the arm reaches the pre-contact pose without clipping."""

    def __init__(self, follower: Follower) -> None:
        self.follow = follower
        self.height: float | None = None

    def travel_height(self, tip_xy: np.ndarray, yaw: float) -> float:
        r = self.follow.env.robot
        low, high = r.pivot_bounds()
        h = min(max(float(r.target_pos[2]), SAFE_Z), float(high[2]))
        while h - HEIGHT_STEP >= SAFE_Z:
            goal = self.follow.pivot_goal(np.array([tip_xy[0], tip_xy[1], 0.0]), yaw)
            goal[2] = h
            inside = np.all(goal >= low) and np.all(goal <= high)
            if inside and np.allclose(r.reachable(goal, yaw), goal, atol=1e-9, rtol=0.0):
                break
            h -= HEIGHT_STEP
        return h

    def act(self, tip_xy: np.ndarray, yaw: float, jaw: float) -> tuple[np.ndarray, bool]:
        """Action toward the pre-contact pose, and whether it is reached after it."""
        r = self.follow.env.robot
        if self.height is None:
            self.height = self.travel_height(tip_xy, yaw)
        if r.target_pos[2] < SAFE_Z - 1e-9:  # below L_z: rise in place before moving sideways
            goal = np.array([r.target_pos[0], r.target_pos[1], self.height])
            a, _ = self.follow.pivot_action(goal, r.target_yaw, jaw)
            return a, False
        return self.follow.action(np.array([tip_xy[0], tip_xy[1], 0.0]), yaw, jaw, pivot_z=self.height)


# --- observable experts ---------------------------------------------------------------------------
# The experts above follow privileged plans (which object is fixed decides where they go first).
# The observable experts below decide only from what an observation carries: which object is
# nearest the gripper, and whether the object they act on moved. A policy cloning them is taught
# choices it can see (docs/tasks.md, "How the experts decide").

MOVED = 0.005  # m: an object whose observed position changed this much since its probe began moved
TIE = 0.001  # m: objects this close to equally far from the gripper count as tied


def object_positions(obs) -> np.ndarray:
    """(M, 3) observed object positions (the centres the objects' points show), world frame."""
    return np.asarray(obs.object_poses, dtype=float)[:, :3]


def object_yaws(obs) -> np.ndarray:
    """(M,) observed object yaws (about world z), from the poses' quaternions (x, y, z, w)."""
    q = np.asarray(obs.object_poses, dtype=float)[:, 3:]
    x, y, z, w = q.T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def nearest_object(obs) -> int:
    """Slot of the object nearest the gripper in (x, y): nearest the origin of the observation's
    gripper-centric frame, as the policy sees it. A tie (within TIE) goes to the smaller world y,
    then the smaller world x, a rule the policy can see too (the frame keeps world orientation)."""
    pos = object_positions(obs)
    gripper = np.asarray(obs.gripper_pose, dtype=float)[:2]
    dist = np.hypot(*(pos[:, :2] - gripper).T)
    tied = [i for i in range(len(pos)) if dist[i] <= dist.min() + TIE]
    return min(tied, key=lambda i: (pos[i, 1], pos[i, 0]))


def moved(obs, slot: int, start: np.ndarray) -> bool:
    """Whether object ``slot`` is observed at least MOVED away from ``start``."""
    return bool(np.linalg.norm(object_positions(obs)[slot] - start) >= MOVED)


class ObservableExpert:
    """What every observable expert (``act(obs)``) keeps: its follower and approach, the slot of the
    object it acts on (None until chosen, ``nearest_object`` first) and its phase."""

    def __init__(self, env, phase: str) -> None:
        self.env = env
        self.follow = Follower(env)
        self.approach = Approach(self.follow)
        self.target: int | None = None  # slot of the object acted on
        self.phase = phase
        self.first = True  # still on the first object (approached at a safe height)


def layout_style(env, obs) -> str:
    """The demonstration style a layout gives the observable expert: ``probe`` where the object
    nearest the gripper at reset is the immovable one (the expert probes it, sees no motion and
    switches), ``direct`` where it is the movable one. Reads the hidden fixedness: for choosing
    seeds of each style (the recorder's choice), never for the expert's decisions."""
    return "probe" if nearest_object(obs) == env.task.fixed_index() else "direct"


def seed_for_style(env, style: str, seeds, limit: int = 1000) -> int:
    """The first seed from the iterator ``seeds`` whose layout gives ``style`` (``layout_style``
    after ``env.reset(seed)``); the seeds before it are skipped. Deterministic: the seeds and the
    layouts they give are. RuntimeError after ``limit`` seeds (about half the layouts give each)."""
    for _ in range(limit):
        seed = next(seeds)
        if layout_style(env, env.reset(seed)) == style:
            return seed
    raise RuntimeError(f"no layout of style {style!r} among {limit} seeds")
