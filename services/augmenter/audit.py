"""`mea audit`: replay augmented episodes through real physics and check that they are valid.

MEA claims that an augmented copy is what the simulator would have produced from the augmented
initial state under the augmented actions. The audit tests that claim transition by transition:

1. Put the simulator into the augmented initial state: ``env.reset(source.seed)`` (the same object
   placement and the same hidden movable/fixed choice, both drawn from the seed), teleport the arm
   so that its pivot is at ``aug.gripper_pose[0]`` (x, y, z, yaw) with the jaw at the recorded
   opening, and let the world rest as many physics steps as ``env.reset`` does.
2. Replay ``aug.actions`` step by step through ``env.step`` (IK, motors, contacts: real physics).
3. Compare every simulated observation with the augmented one, per segment (gripper, each
   object). Observed points are a random draw of P points from what the cameras see, so clouds
   have no point-to-point correspondence; they are compared as sets:

   * ``chamfer``: symmetric Chamfer distance (mean nearest-neighbour distance both ways, mm)
     between the simulated observation and the augmented one, both P-point draws. The replay draws
     from a sampling stream independent of the recording's, so this carries the sampling noise a
     policy sees between two draws of the same state (~1-7 mm depending on the segment's size);
   * ``surface``: mean distance (mm) from the augmented points to everything the cameras see of
     the segment in the simulation (the fused cloud before the draw). Sampling noise does not
     enter, so it resolves millimetre errors the Chamfer distance hides;

   and the visibility of each segment (seen / unseen) and the jaw opening must agree.
4. A transition t = (s_t, a_t, r_t, s_t+1) is valid when both of its observations are within
   tolerance on every segment, metric and the jaw, and the simulated reward and `terminated` flag
   equal the augmented ones. (`truncated` is a time limit on the env's step counter, not a property
   of the state; a copy cut to start later runs on a different clock, so it is not compared.)

Transitions are grouped by MEA phase: non-trivial (t < phase_split: the augmented part), trivial
(phase_split <= t < T-1: the recorded actions from the recorded state at H_p) and termination
(t = T-1). The privileged pivot pose error (simulated vs ``aug.gripper_pose``) is reported beside,
never used for validity (the policy does not see it).

Tolerances come from the noise floor, measured by the same code on un-augmented data:

* identity replays: each source demonstration replayed from its own recorded first pose with its
  own actions (resampling noise, physics and tracking repeatability);
* teleported views: the recorded first observation moved by a rigid offset the way physics says it
  moves (objects by -d in the gripper frame, the gripper turned by theta about its pivot; no MEA
  code), against the simulator with the arm teleported there: how far the camera pipeline itself
  (fixed views, occlusion, a world-aligned voxel grid) is from equivariant. A copy cannot be
  judged more finely than this.

``TASK_TOLERANCES`` holds 1.25x the largest free-space floor value per task, metric and kind of
segment (gripper / objects), rounded up (the numbers are beside it); ``mea audit`` prints the floor
it measures beside the tolerance in use, and ``tolerance_covers_floor`` in its meta.

Only MEA is audited (no isometric rotation): a scene rotated about the workspace centre can leave
the box workspace the simulated objects and arm live in, so a rotated copy has no simulated
counterpart to compare with.

``audit_episode(env, aug, source, tol)`` is the library entry point (the augmenter can audit a copy
given an env); ``run_audit`` records expert demonstrations, augments and audits them; ``main`` is
the CLI.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from proto.episode import Episode
from services.augmenter.core.mea import MeaSettings, augment

if TYPE_CHECKING:  # the env (pybullet) is imported only where the CLI builds one
    from services.actor.tasks.env import ManipulationEnv, Observation

PHASES = ("non_trivial", "trivial", "termination")
NON_TRIVIAL, TRIVIAL, TERMINATION = range(3)
METRICS = ("chamfer", "surface")
SETTLE_STEPS = 10  # physics steps env.reset lets the world rest after placing the arm; mirrored here
RESAMPLE_SALT = 0x5EED_A0D1  # offsets the replay's point-sampling stream from the recorded one
SAFETY = 1.25  # tolerance = SAFETY x the largest noise-floor value (then rounded up)


JAW_LEVEL = 1.0 / 255.0  # one step of the uint8 jaw channel the policy reads (projection.quantize)


@dataclass(frozen=True)
class AuditTolerance:
    """How far a simulated observation may be from the augmented one and still count as equal (mm
    unless stated). Per-task values: ``TASK_TOLERANCES``; these defaults are the loosest of them."""

    gripper_chamfer_mm: float = 9.5
    """Gripper segment: symmetric Chamfer distance between the simulated and augmented draws."""
    object_chamfer_mm: float = 8.0
    """Object segments: symmetric Chamfer distance between the simulated and augmented draws."""
    gripper_surface_mm: float = 5.0
    """Gripper segment: mean distance of the augmented points to the simulated fused cloud."""
    object_surface_mm: float = 1.5
    """Object segments: mean distance of the augmented points to the simulated fused cloud."""
    jaw: float = JAW_LEVEL
    """Jaw opening difference (0 closed .. 1 open)."""

    def limit(self, metric: str, segment: str) -> float:
        kind = "gripper" if segment == "gripper" else "object"
        return float(getattr(self, f"{kind}_{metric}_mm"))

    def limits(self, metric: str, segments: Sequence[str]) -> np.ndarray:
        return np.array([self.limit(metric, s) for s in segments])

    @classmethod
    def for_task(cls, task: str) -> AuditTolerance:
        return TASK_TOLERANCES.get(task, cls())


# The free-space noise floor (largest value; `mea audit --episodes 20 --copies 0` at seeds 0 and
# 1000: identity replays of 20 demonstrations before their first contact, ~12 per demo, plus 6
# teleported views per demo; about 250-290 observations per task and seed), in mm:
#
#                      gripper            objects
#                 chamfer  surface   chamfer  surface
#   block_pull      7.25     3.98      5.43     0.47
#   block_pick      7.45     3.50      2.25     1.01
#   drawer_open     7.07     3.57      6.27     0.74
#
# Tolerance = SAFETY (1.25) x that, rounded up to 0.5 mm (Chamfer) or 0.25 mm (surface); the
# gripper is the same body in every task, so it gets the largest over tasks. The Chamfer floor is
# the sampling noise between two independent P-point draws of one state (large, flat segments
# have more of it); the surface floor is the camera pipeline's non-equivariance (world-fixed voxel
# grid and views: the gripper turned by theta is not seen exactly as the turned recording, ~2-4
# mm; objects only lose points hidden by the gripper). The jaw reading's floor is below 1e-4 in
# free space, but it sags with arm accelerations (a few 1e-4 on motions the recording did not
# make), so its tolerance is one level of the uint8 jaw channel the policy reads (1/255).
# After contact, physics does not repeat exactly (a lifted cube sits up to ~3 mm differently, a
# squeezed jaw reads up to 0.03 apart); those observations are reported apart, not used here.
TASK_TOLERANCES: dict[str, AuditTolerance] = {
    "block_pull": AuditTolerance(9.5, 7.0, 5.0, 0.75),
    "block_pick": AuditTolerance(9.5, 3.0, 5.0, 1.5),
    "drawer_open": AuditTolerance(9.5, 8.0, 5.0, 1.0),
}


# --------------------------------------------------------------------------------------------
# comparing point sets
# --------------------------------------------------------------------------------------------


def _nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-neighbour distances (m) from each point of ``a`` to ``b`` and back."""
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d2 = (a64 * a64).sum(1)[:, None] + (b64 * b64).sum(1)[None, :] - 2.0 * a64 @ b64.T
    d2 = np.maximum(d2, 0.0)
    return np.sqrt(d2.min(axis=1)), np.sqrt(d2.min(axis=0))


def chamfer_mm(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric mean nearest-neighbour distance between two clouds, in mm (inf if one is empty)."""
    if len(a) == 0 or len(b) == 0:
        return math.inf
    ab, ba = _nearest(a, b)
    return float((ab.mean() + ba.mean()) / 2 * 1000.0)


def surface_mm(points: np.ndarray, cloud: np.ndarray) -> float:
    """Mean distance (mm) from ``points`` to their nearest neighbour in ``cloud`` (one-sided)."""
    if len(points) == 0 or len(cloud) == 0:
        return math.inf
    return float(_nearest(points, cloud)[0].mean() * 1000.0)


def distinct_points(points: np.ndarray, count: int) -> np.ndarray:
    """The distinct points of one sampled segment: ``sample_fixed`` puts all ``count`` distinct points
    first and pads with repeats when fewer than P were seen."""
    return points[: min(int(count), len(points))]


def fused_clouds(env: ManipulationEnv) -> list[np.ndarray]:
    """Everything the cameras see of each segment now (before the random draw of P points), in the
    gripper-centric frame, in segment order."""
    parts = {"gripper": env._gripper_parts(), **env.task.object_segments()}
    world = env.cameras.render_segments(parts)
    origin = env.robot.pivot()[0]
    return [world[name] - origin if len(world[name]) else world[name] for name in env.segment_names]


def compare_observation(
    obs: Observation, clouds: list[np.ndarray], points: np.ndarray, counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(chamfer (S,), surface (S,)) in mm of claimed ``points``/``counts`` against a simulated
    observation and its fused ``clouds``: 0 where both sides see nothing, inf where only one does."""
    S = len(counts)
    chamfer, surface = np.zeros(S), np.zeros(S)
    for s in range(S):
        mine = distinct_points(points[s], counts[s])
        theirs = distinct_points(obs.points[s], obs.point_counts[s])
        if len(mine) == 0 and len(theirs) == 0 and len(clouds[s]) == 0:
            continue
        chamfer[s] = chamfer_mm(theirs, mine)
        surface[s] = surface_mm(mine, clouds[s])
    return chamfer, surface


def _yaw_diff(a: float, b: float) -> float:
    return float(abs((a - b + math.pi) % (2 * math.pi) - math.pi))


# --------------------------------------------------------------------------------------------
# one episode
# --------------------------------------------------------------------------------------------


@dataclass
class AuditResult:
    """Per-observation and per-transition measurements of one replayed episode."""

    episode_id: str
    source_id: str
    segments: list[str]
    phase: np.ndarray  # (T,) NON_TRIVIAL / TRIVIAL / TERMINATION per transition
    chamfer: np.ndarray  # (T+1, S) mm, simulated vs augmented draw
    surface: np.ndarray  # (T+1, S) mm, augmented points to the simulated fused cloud
    jaw_error: np.ndarray  # (T+1,)
    obs_ok: np.ndarray  # (T+1,) every segment and metric within tolerance, jaw too
    reward_ok: np.ndarray  # (T,)
    terminated_ok: np.ndarray  # (T,)
    valid: np.ndarray  # (T,) obs_ok[t] & obs_ok[t+1] & reward_ok[t] & terminated_ok[t]
    pivot_error_mm: np.ndarray  # (T+1,) privileged: |simulated pivot - aug.gripper_pose|
    yaw_error_deg: np.ndarray  # (T+1,)
    touched: np.ndarray  # (T+1,) privileged: the recording had touched an object by this observation
    seconds: float

    @property
    def num_steps(self) -> int:
        return int(len(self.phase))

    def observation_phase(self) -> np.ndarray:
        """(T+1,) phase of each observation: that of the transition it ends (obs 0: of transition 0)."""
        return np.r_[self.phase[:1], self.phase]

    def valid_fraction(self, phase: int | None = None) -> float:
        sel = np.ones(self.num_steps, bool) if phase is None else self.phase == phase
        return float(self.valid[sel].mean()) if sel.any() else math.nan

    @property
    def consistent(self) -> np.ndarray:
        """(T,) reward and termination reproduced."""
        return self.reward_ok & self.terminated_ok


def phases(num_steps: int, phase_split: int) -> np.ndarray:
    """Phase of each transition: non-trivial before H_p, termination the last, trivial between."""
    out = np.full(num_steps, TRIVIAL, np.int8)
    out[-1] = TERMINATION
    out[: min(phase_split, num_steps)] = NON_TRIVIAL
    return out


def place(
    env: ManipulationEnv, seed: int, pose: np.ndarray, jaw: float, resample: bool = True
) -> Observation:
    """Reset the task from ``seed`` and teleport the arm to ``pose`` (pivot x, y, z, yaw) with the
    jaw at ``jaw``; the world then rests as long as after an ordinary reset.

    ``resample``: draw the observed points from a sampling stream independent of the recorded
    episode's. ``observe`` seeds its sampler with (env.seed, step), and env.seed serves nothing
    else once the reset has placed the objects, so replacing it changes only which points are
    drawn. Without it a replay whose fused clouds are bit-identical to the recording draws the very
    same points and the Chamfer distance is 0, a floor no augmented copy could share."""
    env.reset(seed)
    if resample:
        env.seed = (int(seed) + RESAMPLE_SALT) % 2**63
    pose = np.asarray(pose, np.float64)
    env.robot.reset(pose[:3], float(pose[3]), jaw=float(jaw))
    for _ in range(SETTLE_STEPS):
        env.step_physics()
    return env.observe()


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
    itself) is audited as the identity transform: all transitions trivial but the last."""
    t0 = time.perf_counter()
    if aug.task != env.task.name or source.task != env.task.name:
        raise ValueError(f"episode of task {aug.task!r} audited in a {env.task.name!r} env")
    tol = tol or AuditTolerance.for_task(aug.task)
    T, S = aug.num_steps, len(aug.segments)
    split = aug.augmentation.phase_split if aug.augmentation is not None else 0
    chamfer, surface = np.zeros((T + 1, S)), np.zeros((T + 1, S))
    jaw_err, pivot_err, yaw_err = np.zeros(T + 1), np.zeros(T + 1), np.zeros(T + 1)
    reward_ok, term_ok = np.zeros(T, bool), np.zeros(T, bool)

    def compare(i: int, obs: Observation) -> None:
        chamfer[i], surface[i] = compare_observation(
            obs, fused_clouds(env), aug.points[i], aug.point_counts[i]
        )
        jaw_err[i] = abs(float(obs.jaw) - float(aug.jaw[i]))
        pivot_err[i] = 1000.0 * float(np.linalg.norm(obs.gripper_pose[:3] - aug.gripper_pose[i, :3]))
        yaw_err[i] = math.degrees(_yaw_diff(float(obs.gripper_pose[3]), float(aug.gripper_pose[i, 3])))

    compare(0, place(env, source.seed, aug.gripper_pose[0], float(aug.jaw[0]), resample))
    for t in range(T):
        obs, reward, terminated, _, _ = env.step(np.asarray(aug.actions[t], np.float64))
        compare(t + 1, obs)
        reward_ok[t] = float(reward) == float(aug.rewards[t])
        term_ok[t] = bool(terminated) == bool(aug.terminated[t])
    obs_ok = (
        np.all(chamfer <= tol.limits("chamfer", aug.segments)[None, :], axis=1)
        & np.all(surface <= tol.limits("surface", aug.segments)[None, :], axis=1)
        & (jaw_err <= tol.jaw)
    )
    valid = obs_ok[:-1] & obs_ok[1:] & reward_ok & term_ok
    return AuditResult(
        episode_id=aug.episode_id, source_id=source.episode_id, segments=list(aug.segments),
        phase=phases(T, split), chamfer=chamfer, surface=surface, jaw_error=jaw_err, obs_ok=obs_ok,
        reward_ok=reward_ok, terminated_ok=term_ok, valid=valid, pivot_error_mm=pivot_err,
        yaw_error_deg=yaw_err, touched=np.logical_or.accumulate(aug.contacts.any(axis=1)),
        seconds=time.perf_counter() - t0,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# the noise floor
# --------------------------------------------------------------------------------------------


def identity_replay(
    env: ManipulationEnv, source: Episode, tol: AuditTolerance | None = None, resample: bool = True
) -> AuditResult:
    """Audit ``source`` against itself (no transform at all): resampling and replay noise."""
    return audit_episode(env, source, source, tol, resample)


@dataclass
class FloorSample:
    """The recorded first observation moved rigidly, against the simulator with the arm moved so."""

    chamfer: np.ndarray  # (S,) mm
    surface: np.ndarray  # (S,) mm
    jaw_error: float
    offset: np.ndarray  # (4,) dx, dy, dz (m), dtheta (rad) of the pivot


def moved_observation(points: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(S, P, 3) gripper-centric points after the pivot moves by offset[:3] and turns by offset[3]
    while nothing else moves: objects shift by -offset[:3], the gripper turns about the origin."""
    out = np.array(points, np.float64, copy=True)
    out[1:] -= offset[None, None, :3]
    c, s = math.cos(offset[3]), math.sin(offset[3])
    g = out[0].copy()
    out[0, :, 0], out[0, :, 1] = c * g[:, 0] - s * g[:, 1], s * g[:, 0] + c * g[:, 1]
    return out


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
        chamfer, surface = compare_observation(obs, fused_clouds(env), claimed, source.point_counts[0])
        out.append(FloorSample(chamfer, surface, abs(float(obs.jaw) - float(source.jaw[0])), offset))
    return out


# --------------------------------------------------------------------------------------------
# summaries
# --------------------------------------------------------------------------------------------


def _stats(x: np.ndarray) -> dict[str, Any]:
    x = np.asarray(x, np.float64)
    if len(x) == 0:
        return {"n": 0, "mean": None, "p50": None, "p95": None, "max": None}
    return {
        "n": int(len(x)),
        "mean": float(x.mean()),
        "p50": float(np.percentile(x, 50)),
        "p95": float(np.percentile(x, 95)),
        "max": float(x.max()),
    }


def _pct(x: np.ndarray) -> float | None:
    return 100.0 * float(np.mean(x)) if len(x) else None


def validity_rows(results: Sequence[AuditResult]) -> list[dict[str, Any]]:
    """Valid fraction and reward/termination consistency per phase and overall."""
    rows = []
    for p, name in [*enumerate(PHASES), (None, "all")]:
        sel = [(r, r.phase == p if p is not None else np.ones(r.num_steps, bool)) for r in results]
        valid = np.concatenate([r.valid[m] for r, m in sel] or [np.zeros(0, bool)])
        cons = np.concatenate([r.consistent[m] for r, m in sel] or [np.zeros(0, bool)])
        rows.append({"phase": name, "transitions": int(len(valid)), "valid": int(valid.sum()),
                     "valid %": _pct(valid), "reward+term consistent %": _pct(cons)})  # fmt: skip
    return rows


def metric_rows(results: Sequence[AuditResult], tol: AuditTolerance) -> list[dict[str, Any]]:
    """Distribution (mm) of each metric per observation phase and segment, with its tolerance."""
    if not results:
        return []
    rows = []
    for p, pname in enumerate(PHASES):
        masks = [r.observation_phase() == p for r in results]
        for metric in METRICS:
            for s, seg in enumerate(results[0].segments):
                vals = np.concatenate([getattr(r, metric)[m, s] for r, m in zip(results, masks, strict=True)])
                rows.append({"phase": pname, "metric": metric, "segment": seg, **_stats(vals),
                             "tolerance": tol.limit(metric, seg)})  # fmt: skip
        vals = np.concatenate([r.jaw_error[m] for r, m in zip(results, masks, strict=True)])
        rows.append(
            {"phase": pname, "metric": "jaw (0..1)", "segment": "—", **_stats(vals), "tolerance": tol.jaw}
        )
    return rows


def pivot_rows(results: Sequence[AuditResult]) -> list[dict[str, Any]]:
    rows = []
    for p, pname in enumerate(PHASES):
        pos = np.concatenate([r.pivot_error_mm[r.observation_phase() == p] for r in results] or [np.zeros(0)])
        yaw = np.concatenate([r.yaw_error_deg[r.observation_phase() == p] for r in results] or [np.zeros(0)])
        if len(pos):
            rows.append({
                "phase": pname, "observations": int(len(pos)), "pivot mean mm": float(pos.mean()),
                "pivot p95 mm": float(np.percentile(pos, 95)), "pivot max mm": float(pos.max()),
                "yaw mean deg": float(yaw.mean()), "yaw max deg": float(yaw.max()),
            })  # fmt: skip
    return rows


def _floor_values(
    replays: Sequence[AuditResult], views: Sequence[FloorSample], metric: str, idx: Sequence[int]
) -> dict[str, np.ndarray]:
    """Floor values of one metric over segments ``idx``: identity replays before and after the
    recording first touched an object, teleported views, and free space (untouched + views)."""
    get = (lambda r: r.jaw_error[:, None]) if metric == "jaw" else (lambda r: getattr(r, metric)[:, idx])
    free = np.concatenate([get(r)[~r.touched].ravel() for r in replays] or [np.zeros(0)])
    contact = np.concatenate([get(r)[r.touched].ravel() for r in replays] or [np.zeros(0)])
    if metric == "jaw":
        view = np.array([v.jaw_error for v in views])
    else:
        view = np.array([getattr(v, metric)[i] for v in views for i in idx])
    return {"identity replays, untouched": free, "teleported views": view,
            "free space (both)": np.r_[free, view], "identity replays, after contact": contact}  # fmt: skip


def _kinds(segments: Sequence[str]) -> dict[str, list[int]]:
    return {"gripper": [0], "objects": [s for s, name in enumerate(segments) if name != "gripper"]}


def floor_rows(
    replays: Sequence[AuditResult], views: Sequence[FloorSample], segments: Sequence[str], tol: AuditTolerance
) -> list[dict[str, Any]]:
    """Noise floor per metric and kind of segment, with SAFETY x the largest free-space value beside
    the tolerance in use. Observations after the recording touched something are listed apart:
    contact physics does not repeat exactly, and MEA's non-trivial phase is free space by design."""
    rows = []
    for metric in (*METRICS, "jaw"):
        kinds = _kinds(segments) if metric != "jaw" else {"—": [0]}
        for kind, idx in kinds.items():
            for source, vals in _floor_values(replays, views, metric, idx).items():
                row = {"metric": metric, "segment": kind, "floor": source, **_stats(vals),
                       f"{SAFETY}x max": None, "tolerance": None}  # fmt: skip
                if source == "free space (both)":
                    top = float(vals.max()) if len(vals) else math.nan
                    limit = (
                        tol.jaw
                        if metric == "jaw"
                        else tol.limit(metric, "gripper" if kind == "gripper" else "o")
                    )
                    row |= {f"{SAFETY}x max": SAFETY * top, "tolerance": limit}
                rows.append(row)
    return rows


def floor_covered(
    replays: Sequence[AuditResult], views: Sequence[FloorSample], segments: Sequence[str], tol: AuditTolerance
) -> bool:
    """Every free-space noise-floor value within the tolerance (else un-augmented data would fail)."""
    for metric in METRICS:
        for kind, idx in _kinds(segments).items():
            limit = tol.limit(metric, "gripper" if kind == "gripper" else "object")
            vals = _floor_values(replays, views, metric, idx)["free space (both)"]
            if len(vals) and vals.max() > limit:
                return False
    jaws = _floor_values(replays, views, "jaw", [0])["free space (both)"]
    return not (len(jaws) and jaws.max() > tol.jaw)


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AuditConfig:
    """Record expert demonstrations, make MEA copies, replay every copy through physics, and report
    how many augmented transitions the simulator reproduces (after measuring the noise floor)."""

    task: str = "block_pull"
    """Task: block_pull, block_pick or drawer_open."""
    episodes: int = 10
    """Successful expert demonstrations to augment (alternating probe/direct, as the actor)."""
    copies: int = 6
    """MEA copies per demonstration (the paper's Equi-RSAC setting)."""
    seed: int = 0
    """First demonstration seed, and the base seed of the MEA draws (as the augmenter's)."""
    json: bool = False
    """Print exactly one JSON object on stdout."""
    max_attempts: int = 4
    """Expert attempts per requested demonstration before giving up (only successes are kept)."""
    views: int = 6
    """Teleported views per demonstration for the noise floor."""
    gripper_chamfer_mm: float | None = None
    """Tolerance: gripper Chamfer distance (mm); default: the task's (1.25x its noise floor)."""
    object_chamfer_mm: float | None = None
    """Tolerance: object Chamfer distance (mm); default: the task's."""
    gripper_surface_mm: float | None = None
    """Tolerance: gripper points to the simulated surface (mm); default: the task's."""
    object_surface_mm: float | None = None
    """Tolerance: object points to the simulated surface (mm); default: the task's."""
    jaw: float | None = None
    """Tolerance: jaw opening difference (0..1); default: the task's."""
    mea: MeaSettings = field(default_factory=MeaSettings)
    """MEA settings audited (phases, group ranges, feasibility guards)."""

    def __post_init__(self) -> None:
        if self.episodes < 1 or self.copies < 0 or self.max_attempts < 1 or self.views < 0:
            raise ValueError("episodes and max_attempts must be >= 1; copies and views >= 0")

    @property
    def tolerance(self) -> AuditTolerance:
        base = AuditTolerance.for_task(self.task)
        given = {f.name: getattr(self, f.name) for f in dataclasses.fields(AuditTolerance)}
        return dataclasses.replace(base, **{k: v for k, v in given.items() if v is not None})


def record_demos(actor, episodes: int, max_attempts: int) -> tuple[list[Episode], int]:
    """Successful expert demonstrations, alternating probe/direct as the actor does."""
    demos: list[Episode] = []
    attempts = 0
    while len(demos) < episodes and attempts < episodes * max_attempts:
        b = actor.expert_episode(len(demos))
        attempts += 1
        if b.success:
            demos.append(b.finish(actor.episode_id(b)))
    return demos, attempts


def run_audit(cfg: AuditConfig) -> tuple[dict[str, list[dict[str, Any]]], dict[str, Any]]:
    """Record, measure the floor, augment and audit; returns (sections, meta) for ``emit``."""
    from services.actor.main import Actor, ActorConfig
    from services.augmenter.core.pipeline import episode_seed

    t_start = time.perf_counter()
    tol = cfg.tolerance
    actor = Actor(ActorConfig(task=cfg.task, policy="expert", seed_base=cfg.seed), "audit")
    env = actor.env
    timing: dict[str, float] = {}
    try:
        t0 = time.perf_counter()
        demos, attempts = record_demos(actor, cfg.episodes, cfg.max_attempts)
        timing["record s"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        replays = [identity_replay(env, ep, tol) for ep in demos]
        views = [v for i, ep in enumerate(demos) for v in view_floor(env, ep, np.random.default_rng([cfg.seed, i, 7]),
                                                                     cfg.views, cfg.mea.lz)]  # fmt: skip
        timing["floor s"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        results: list[AuditResult] = []
        counts = {"audited": 0, "empty": 0, "cut": 0, "guard rejections": 0}
        for ep in demos:
            seed = episode_seed(cfg.seed, ep.episode_id)
            for k in range(cfg.copies):
                rng = np.random.default_rng([seed, 1_000_001 + k])  # as the augmenter's pipeline
                copy, draw = augment(
                    ep, cfg.mea, rng, seed=seed, copy_index=k, episode_id=f"{ep.episode_id}.mea{k}"
                )
                counts["guard rejections"] += draw.rejections
                counts["cut"] += int(draw.cut)
                if copy is None:
                    counts["empty"] += 1
                    continue
                counts["audited"] += 1
                results.append(audit_episode(env, copy, ep, tol))
        timing["audit s"] = time.perf_counter() - t0
    finally:
        env.close()

    segments = list(env.segment_names)
    nontrivial = [int((r.phase == NON_TRIVIAL).sum()) for r in results]
    timing["total s"] = time.perf_counter() - t_start
    sections = {
        "validity of MEA copies per phase": validity_rows(results),
        "MEA copies: distance to the simulation per observation phase, segment and metric (mm)": metric_rows(
            results, tol
        ),
        "MEA copies: pivot pose error (privileged; not used for validity)": pivot_rows(results),
        "noise floor (un-augmented data) and the tolerance": floor_rows(replays, views, segments, tol),
        "noise floor: identity replays, validity": validity_rows(replays),
        "copies and runtime": [{
            "demos": len(demos), "expert attempts": attempts, "copies requested": len(demos) * cfg.copies,
            **counts, "non-trivial steps / copy": float(np.mean(nontrivial)) if nontrivial else 0.0,
            "s / audited copy": timing["audit s"] / max(1, len(results)), **timing,
        }],
    }  # fmt: skip
    meta = {
        "task": cfg.task,
        "augmentation": "MEA only: no isometric rotation (a rotated scene can leave the box workspace)",
        "valid": "both observations within tolerance (every segment: Chamfer and surface; the jaw), "
        "reward and terminated equal",
        "tolerance": dataclasses.asdict(tol),
        "tolerance_covers_floor": floor_covered(replays, views, segments, tol),
        "notes": "tolerances: 1.25x the free-space floor (identity replays before any contact + teleported "
        "views); trivial/termination transitions involve contact, whose physics does not repeat exactly: "
        "compare their validity with the identity replays' (the arm is redundant, so a copy reaches the "
        "H_p pose with a slightly different, unobserved joint configuration)",
        "mea": dataclasses.asdict(cfg.mea),
        "seed": cfg.seed,
        "episodes": cfg.episodes,
        "copies": cfg.copies,
    }
    return sections, meta


def main(argv: Sequence[str]) -> int:
    from services.bench.report import emit
    from services.common import config

    cfg = config.parse(AuditConfig, {"default": AuditConfig()}, argv, "mea audit", AuditConfig.__doc__ or "")
    sections, meta = run_audit(cfg)
    emit("audit", sections, {}, cfg.json, meta)
    return 0


__all__ = [
    "PHASES",
    "TASK_TOLERANCES",
    "AuditConfig",
    "AuditResult",
    "AuditTolerance",
    "audit_episode",
    "chamfer_mm",
    "identity_replay",
    "main",
    "run_audit",
    "surface_mm",
    "view_floor",
]
