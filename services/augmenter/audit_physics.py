"""The physics audit: replay an augmented episode through the simulator and measure, step by step,
how far the simulation is from what the copy claims.

Design notes: docs/architecture-notes.md, services/augmenter/audit_physics.py."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import TYPE_CHECKING

import numpy as np

from proto.episode import Episode
from services.augmenter.audit_placement import NotSimulableError, place, plan_placement, rotation_of
from services.augmenter.core.audit_metrics import (
    AuditResult,
    AuditTolerance,
    FloorSample,
    compare_observation,
    moved_observation,
    observation_checks,
    phases,
    valid_transitions,
    yaw_diff,
)
from services.augmenter.core.isometric import isometric_copy
from services.augmenter.core.mea import MeaSettings

if TYPE_CHECKING:  # the env (pybullet) is imported only where a caller builds one
    from services.tasks.env import ManipulationEnv, Observation


def fused_clouds(env: ManipulationEnv) -> list[np.ndarray]:
    """Everything the cameras see of each segment now (before the random draw of P points), in the
    gripper-centric frame, in segment order."""
    world = env.segment_clouds()
    origin = env.robot.pivot()[0]
    return [world[name] - origin if len(world[name]) else world[name] for name in env.segment_names]


def compare_with_simulation(
    env: ManipulationEnv, obs: Observation, points: np.ndarray, counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(chamfer (S,), surface (S,)) mm of claimed ``points``/``counts`` against ``obs``, the env's
    observation of its current state, and what the cameras see of it now."""
    return compare_observation(obs.points, obs.point_counts, fused_clouds(env), points, counts)


def audit_episode(
    env: ManipulationEnv,
    aug: Episode,
    source: Episode,
    tol: AuditTolerance | None = None,
    resample: bool = True,
) -> AuditResult:
    """Replay ``aug`` through ``env``'s physics from its first state and compare, step by step.

    ``source`` is the raw episode ``aug`` was made from (its seed places the objects); ``tol``
    defaults to the task's ``TASK_TOLERANCES``. An episode without ``augmentation`` (e.g. ``source``
    itself) is audited as the identity transform: all transitions trivial but the last. A rotated
    copy is played in the source scene turned about a vertical axis that keeps it in the workspace
    (``audit_placement.plan_placement``; its privileged poses are compared translated to match);
    ``audit_placement.NotSimulableError`` if there is none."""
    t0 = time.perf_counter()
    if aug.task != env.task.name or source.task != env.task.name:
        raise ValueError(f"episode of task {aug.task!r} audited in a {env.task.name!r} env")
    tol = tol or AuditTolerance.for_task(aug.task, rotated=rotation_of(aug) != 0.0)
    placement = plan_placement(env, aug)
    aug = placement.episode
    T, S = aug.num_steps, len(aug.segments)
    split = aug.augmentation.phase_split if aug.augmentation is not None else 0
    chamfer, surface = np.zeros((T + 1, S)), np.zeros((T + 1, S))
    jaw_err, pivot_err, yaw_err = np.zeros(T + 1), np.zeros(T + 1), np.zeros(T + 1)
    reward_ok, term_ok = np.zeros(T, bool), np.zeros(T, bool)

    def compare(i: int, obs: Observation) -> None:
        chamfer[i], surface[i] = compare_with_simulation(env, obs, aug.points[i], aug.point_counts[i])
        jaw_err[i] = abs(float(obs.jaw) - float(aug.jaw[i]))
        pivot_err[i] = 1000.0 * float(np.linalg.norm(obs.gripper_pose[:3] - aug.gripper_pose[i, :3]))
        yaw_err[i] = math.degrees(yaw_diff(float(obs.gripper_pose[3]), float(aug.gripper_pose[i, 3])))

    compare(0, place(env, source.seed, aug.gripper_pose[0], float(aug.jaw[0]), resample, placement))
    for t in range(T):
        obs, reward, terminated, _, _ = env.step(np.asarray(aug.actions[t], np.float64))
        compare(t + 1, obs)
        reward_ok[t] = float(reward) == float(aug.rewards[t])
        term_ok[t] = bool(terminated) == bool(aug.terminated[t])
    checks = observation_checks(chamfer, surface, jaw_err, aug.segments, tol)
    obs_ok, valid = valid_transitions(checks, reward_ok, term_ok)
    return AuditResult(
        episode_id=aug.episode_id, source_id=source.episode_id, segments=list(aug.segments),
        phase=phases(T, split), chamfer=chamfer, surface=surface, jaw_error=jaw_err, obs_ok=obs_ok,
        reward_ok=reward_ok, terminated_ok=term_ok, valid=valid, pivot_error_mm=pivot_err,
        yaw_error_deg=yaw_err, touched=np.logical_or.accumulate(aug.contacts.any(axis=1)),
        seconds=time.perf_counter() - t0, checks=checks,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# the noise floor
# --------------------------------------------------------------------------------------------


def identity_replay(
    env: ManipulationEnv, source: Episode, tol: AuditTolerance | None = None, resample: bool = True
) -> AuditResult:
    """Audit ``source`` against itself (no transform at all): resampling and replay noise."""
    return audit_episode(env, source, source, tol, resample)


def view_floor(
    env: ManipulationEnv,
    source: Episode,
    rng: np.random.Generator,
    samples: int = 6,
    lz: float = MeaSettings.lz,
    max_xy: float = 0.15,
    max_z: float = 0.05,
    max_yaw: float = 0.5,
) -> list[FloorSample]:
    """How equivariant the camera pipeline is: ``samples`` rigid offsets of the recorded first
    state (|dx|, |dy| <= max_xy, |dz| <= max_z m, |dtheta| <= max_yaw rad, the pivot kept inside
    the live robot's bounds and reach and at or above ``lz``, so nothing is touched)."""
    pose0 = source.gripper_pose[0].astype(np.float64)
    lo, hi = env.robot.pivot_bounds()
    out: list[FloorSample] = []
    for _ in range(samples * 20):
        if len(out) >= samples:
            break
        offset = rng.uniform([-max_xy, -max_xy, -max_z, -max_yaw], [max_xy, max_xy, max_z, max_yaw])
        pos, yaw = pose0[:3] + offset[:3], float(pose0[3] + offset[3])
        if np.any(pos < lo) or np.any(pos > hi) or pos[2] < lz or abs(yaw) > MeaSettings.yaw_limit:
            continue
        if np.linalg.norm(env.robot.reachable(pos, yaw) - pos) > 1e-9:
            continue
        obs = place(env, source.seed, np.r_[pos, yaw], float(source.jaw[0]))
        claimed = moved_observation(source.points[0], offset)
        chamfer, surface = compare_with_simulation(env, obs, claimed, source.point_counts[0])
        out.append(FloorSample(chamfer, surface, abs(float(obs.jaw) - float(source.jaw[0])), offset))
    return out


def rotated_views(
    env: ManipulationEnv, source: Episode, rng: np.random.Generator, samples: int = 6
) -> list[FloorSample]:
    """How equivariant the camera pipeline is under turning the scene: the recorded first
    observation turned by ``samples`` random angles (those a copy could be placed with), against
    the simulator with the scene turned so, placed as a rotated copy is. ``offset`` holds the
    world shift and the angle: (shift x, shift y, 0, phi)."""
    still = dataclasses.replace(source, actions=np.zeros_like(source.actions))  # only state 0 is compared
    out: list[FloorSample] = []
    for _ in range(samples * 10):
        if len(out) >= samples:
            break
        phi = float(rng.uniform(0.0, 2 * math.pi))
        turned = isometric_copy(still, phi, seed=0, copy_index=0, episode_id=f"{source.episode_id}.view")
        try:
            placement = plan_placement(env, turned)
        except NotSimulableError:
            continue
        pose = placement.episode.gripper_pose[0]
        obs = place(env, source.seed, pose, float(source.jaw[0]), placement=placement)
        chamfer, surface = compare_with_simulation(env, obs, turned.points[0], turned.point_counts[0])
        jaw = abs(float(obs.jaw) - float(source.jaw[0]))
        out.append(FloorSample(chamfer, surface, jaw, np.r_[placement.shift, 0.0, phi]))
    return out


__all__ = [
    "audit_episode",
    "compare_with_simulation",
    "fused_clouds",
    "identity_replay",
    "rotated_views",
    "view_floor",
]
