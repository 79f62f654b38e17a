"""The physics audit of Surgical Grasp Any: replay each transition of an MEA copy in the simulator
and check that it does what the copy claims.

Design notes: docs/architecture-notes.md, services/augmenter/audit_surgical.py."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from proto.episode import Episode
from services.augmenter.core.audit_metrics import NON_TRIVIAL, phases, yaw_diff

if TYPE_CHECKING:  # pybullet is imported only where an env exists
    from services.tasks.surgical.env import SurgicalGraspEnv

SIM_PER_METRE = 5.0
"""Sim units per real metre (``services.tasks.surgical.settings.SCALING``)."""
CHECKS = ("pivot", "yaw", "jaw", "object", "reward", "terminated")


@dataclass(frozen=True)
class SurgicalTolerance:
    """What a replayed transition may differ by and still be valid, justified by the noise floor (the
    same replay of the raw demonstrations; measured over 100 oracle demonstrations, seeds 200-299,
    and printed beside these by ``mea audit --task surgical_grasp_any``). Free space: the
    non-trivial transitions (t < H_p); contact: the grasp and the lift (t >= H_p), whose physics
    does not repeat exactly."""

    pivot_mm: float = 0.08
    """Pivot position (real mm), every transition: twice the drive's settling tolerance (a step ends
    within 2e-4 sim = 0.04 mm real of its goal, not at rest, so a recorded and a replayed end may
    differ by twice that; a copy's turned move lags along its own direction while its claimed end
    keeps the source's lag). Floor: raw replays at most 0.037 mm in free space and 0.065 in
    contact; copies' free-space moves 0.059. A move the object blocks misses by millimetres."""
    yaw_deg: float = 0.5
    """Wrist yaw (degrees). Floor: 0.004 in free space, 0.34 in contact."""
    jaw: float = 0.02
    """Jaw opening (0 closed .. 1 open) in free space. Floor: 0 (no jaw moves before H_p)."""
    object_mm: float = 0.05
    """Object position (real mm) in free space: it stays put. Floor: 0 (held on the tray)."""
    contact_jaw: float = 0.2
    """Jaw opening in contact (closing on the object). Floor: at most 0.11."""
    contact_object_mm: float = 1.0
    """Object position (real mm) in contact (grasped and lifted). Floor: at most 0.42."""


@dataclass
class SurgicalAuditResult:
    """Per transition of one audited episode (T transitions)."""

    episode_id: str
    source_id: str
    phase: np.ndarray  # (T,) int8: audit_metrics.NON_TRIVIAL / TRIVIAL / TERMINATION
    moved: np.ndarray  # (T,) bool: the copy moved the instrument at t or t + 1 (D != 0)
    pivot_mm: np.ndarray  # (T,) float64
    yaw_deg: np.ndarray
    jaw_error: np.ndarray
    object_mm: np.ndarray
    checks: dict[str, np.ndarray] = field(default_factory=dict)  # CHECKS -> (T,) bool, True = passed
    valid: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    seconds: float = 0.0


def moved_rows(ep: Episode, source: Episode) -> np.ndarray:
    """(T + 1,) bool: rows whose pivot differs from the source's row (the copy moved the instrument)."""
    aug = ep.augmentation
    start = 0 if aug is None else int(aug.params["start"][0])
    theirs = source.gripper_pose[start : start + ep.num_steps + 1, :3]
    return np.any(ep.gripper_pose[:, :3] != theirs, axis=1)


def audit_surgical(
    env: SurgicalGraspEnv, ep: Episode, source: Episode, split: int, tol: SurgicalTolerance | None = None
) -> SurgicalAuditResult:
    """Replay ``ep`` (an MEA copy of ``source``, or ``source`` itself for the noise floor) with the
    non-trivial transitions ``t < split`` placed one by one and the rest rolled out from row
    ``split`` (module docstring); ``source.seed`` places the object."""
    t0 = time.perf_counter()
    tol = tol or SurgicalTolerance()
    T = ep.num_steps
    split = min(max(int(split), 0), T)
    pivot, yaw, jaw, obj = np.zeros(T), np.zeros(T), np.zeros(T), np.zeros(T)
    reward_ok, term_ok = np.zeros(T, bool), np.zeros(T, bool)
    home: np.ndarray | None = None  # the object's position in a fresh world of the seed
    fresh = False

    def place(t: int) -> None:
        nonlocal home, fresh
        env.place_state(source.seed, ep.gripper_pose[t, :3], float(ep.gripper_pose[t, 3]), bool(ep.jaw[t] > 0.5),
                        reset=not fresh)  # fmt: skip
        if not fresh:
            home = env.scene.object_pose()[:3]
        fresh = True

    def step(t: int) -> None:
        nonlocal fresh
        obs, reward, terminated, _, _ = env.step(np.asarray(ep.actions[t], np.float64))
        pivot[t] = np.linalg.norm(obs.gripper_pose[:3].astype(np.float64) - ep.gripper_pose[t + 1, :3])
        yaw[t] = math.degrees(yaw_diff(float(obs.gripper_pose[3]), float(ep.gripper_pose[t + 1, 3])))
        jaw[t] = abs(float(obs.jaw) - float(ep.jaw[t + 1]))
        obj[t] = np.linalg.norm(obs.object_poses[0, :3].astype(np.float64) - ep.object_poses[t + 1, 0, :3])
        reward_ok[t] = np.float32(reward) == ep.rewards[t]  # as the episode stores it
        term_ok[t] = bool(terminated) == bool(ep.terminated[t])
        fresh = fresh and np.linalg.norm(env.scene.object_pose()[:3] - home) <= 1e-9 and not env.grasped

    for t in range(split):
        place(t)
        step(t)
    if split < T:
        fresh = False  # the tail starts from the seed's world: the grasp needs the object undisturbed
        place(split)
        for t in range(split, T):
            step(t)
    to_mm = 1000.0 / SIM_PER_METRE
    pivot, obj = pivot * to_mm, obj * to_mm
    contact = np.arange(T) >= split
    checks = {
        "pivot": pivot <= tol.pivot_mm,
        "yaw": yaw <= tol.yaw_deg,
        "jaw": jaw <= np.where(contact, tol.contact_jaw, tol.jaw),
        "object": obj <= np.where(contact, tol.contact_object_mm, tol.object_mm),
        "reward": reward_ok,
        "terminated": term_ok,
    }
    valid = np.logical_and.reduce([checks[name] for name in CHECKS])
    moved = moved_rows(ep, source)
    return SurgicalAuditResult(
        episode_id=ep.episode_id, source_id=source.episode_id, phase=phases(T, split),
        moved=moved[:-1] | moved[1:], pivot_mm=pivot, yaw_deg=yaw, jaw_error=jaw, object_mm=obj,
        checks=checks, valid=valid, seconds=time.perf_counter() - t0,
    )  # fmt: skip


def worst_errors(results: list[SurgicalAuditResult], contact: bool) -> dict[str, float]:
    """The largest error of each kind over ``results``' free-space (t < H_p) or contact transitions."""
    out = {"pivot_mm": 0.0, "yaw_deg": 0.0, "jaw": 0.0, "object_mm": 0.0}
    for r in results:
        m = (r.phase != NON_TRIVIAL) if contact else (r.phase == NON_TRIVIAL)
        if m.any():
            for name, values in (("pivot_mm", r.pivot_mm), ("yaw_deg", r.yaw_deg), ("jaw", r.jaw_error),
                                 ("object_mm", r.object_mm)):  # fmt: skip
                out[name] = max(out[name], float(values[m].max()))
    return out


def floor_covered(floor: list[SurgicalAuditResult], tol: SurgicalTolerance) -> dict[str, bool]:
    """Whether each tolerance covers the largest error of the noise floor (the raw replays)."""
    free, contact = worst_errors(floor, False), worst_errors(floor, True)
    return {
        "pivot_mm": max(free["pivot_mm"], contact["pivot_mm"]) <= tol.pivot_mm,
        "yaw_deg": max(free["yaw_deg"], contact["yaw_deg"]) <= tol.yaw_deg,
        "jaw": free["jaw"] <= tol.jaw,
        "object_mm": free["object_mm"] <= tol.object_mm,
        "contact_jaw": contact["jaw"] <= tol.contact_jaw,
        "contact_object_mm": contact["object_mm"] <= tol.contact_object_mm,
    }


__all__ = [
    "CHECKS",
    "SurgicalAuditResult",
    "SurgicalTolerance",
    "audit_surgical",
    "floor_covered",
    "moved_rows",
    "worst_errors",
]
