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

Every kind the augmenter stores is audited: raw demonstrations (the identity replays above),
isometric copies, MEA copies and MEA∘isometric copies, drawn exactly as the pipeline draws them.
A rotated copy is the source scene turned about a vertical axis; the gripper-centric observation
is the same for every axis, so ``audit_placement`` picks the one that keeps the turned gripper
path and objects inside the workspace, the arm's reach and the wrist's range, turns the sim's
objects (and the arm's start pose) accordingly, then the actions are replayed as for MEA. A copy
with no such placement is counted as *not simulable*, apart from valid and invalid. Once objects
slide, a turned scene's future is not the turned future in pybullet, whose friction depends on a
body's yaw (``audit_isotropy``, reported beside). Turned objects
move in the world, so the fixed cameras sample them through other pixels and voxels: rotated
copies are judged against their own floor (``rotated_views``, ``TASK_ROTATED_TOLERANCES``).

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
from services.augmenter.audit_isotropy import drag_isotropy, spread
from services.augmenter.audit_placement import NotSimulableError, place, plan_placement, rotation_of
from services.augmenter.core.isometric import isometric_copy
from services.augmenter.core.mea import MeaSettings

if TYPE_CHECKING:  # the env (pybullet) is imported only where the CLI builds one
    from services.tasks.env import ManipulationEnv, Observation

PHASES = ("non_trivial", "trivial", "termination")
NON_TRIVIAL, TRIVIAL, TERMINATION = range(3)
METRICS = ("chamfer", "surface")
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
    def for_task(cls, task: str, rotated: bool = False) -> AuditTolerance:
        """The task's tolerance; ``rotated``: for copies turned about the vertical (isometric)."""
        return (TASK_ROTATED_TOLERANCES if rotated else TASK_TOLERANCES).get(task, cls())


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

# Rotated copies (isometric, MEA∘isometric) move the objects in the world, so the fixed cameras
# sample them through other pixels and voxels (~6 mm pixel footprint, 4 mm voxels), and see other
# sides of them: the recording's first observation turned by a random angle, against the
# simulator with the scene turned so (``rotated_views``, no dynamics, no augmentation error), is
# 2-3 mm from the simulated object surface where an un-moved object is < 1 mm. The rotated floor
# (largest value, `mea audit --episodes 10` at seed 0, 6 rotated views per demo; mm):
#
#                      gripper            objects
#                 chamfer  surface   chamfer  surface
#   block_pull      6.83     2.56      5.69     2.93
#   block_pick      6.81     2.63      3.73     3.11
#   drawer_open     6.80     2.60      6.55     3.40
#
# Tolerance: the task's, with SAFETY x the rotated floor (rounded up likewise) where larger. A
# rotated copy is judged more coarsely than an MEA copy (a few mm), still far below the error of
# a clipped diagonal action (up to 20 mm per step).
TASK_ROTATED_TOLERANCES: dict[str, AuditTolerance] = {
    "block_pull": AuditTolerance(9.5, 7.5, 5.0, 3.75),
    "block_pick": AuditTolerance(9.5, 5.0, 5.0, 4.0),
    "drawer_open": AuditTolerance(9.5, 8.5, 5.0, 4.5),
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
    world = env.segment_clouds()
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
    checks: dict[str, np.ndarray] = field(default_factory=dict)  # check name -> (T+1,) passed

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
        chamfer[i], surface[i] = compare_observation(
            obs, fused_clouds(env), aug.points[i], aug.point_counts[i]
        )
        jaw_err[i] = abs(float(obs.jaw) - float(aug.jaw[i]))
        pivot_err[i] = 1000.0 * float(np.linalg.norm(obs.gripper_pose[:3] - aug.gripper_pose[i, :3]))
        yaw_err[i] = math.degrees(_yaw_diff(float(obs.gripper_pose[3]), float(aug.gripper_pose[i, 3])))

    compare(0, place(env, source.seed, aug.gripper_pose[0], float(aug.jaw[0]), resample, placement))
    for t in range(T):
        obs, reward, terminated, _, _ = env.step(np.asarray(aug.actions[t], np.float64))
        compare(t + 1, obs)
        reward_ok[t] = float(reward) == float(aug.rewards[t])
        term_ok[t] = bool(terminated) == bool(aug.terminated[t])
    checks = {"jaw": jaw_err <= tol.jaw}
    for metric, values in (("chamfer", chamfer), ("surface", surface)):
        ok = values <= tol.limits(metric, aug.segments)[None, :]
        checks[f"gripper {metric}"], checks[f"object {metric}"] = ok[:, 0], ok[:, 1:].all(axis=1)
    obs_ok = np.logical_and.reduce(list(checks.values()))
    valid = obs_ok[:-1] & obs_ok[1:] & reward_ok & term_ok
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
        chamfer, surface = compare_observation(
            obs, fused_clouds(env), turned.points[0], turned.point_counts[0]
        )
        jaw = abs(float(obs.jaw) - float(source.jaw[0]))
        out.append(FloorSample(chamfer, surface, jaw, np.r_[placement.shift, 0.0, phi]))
    return out


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AuditConfig:
    """Record expert demonstrations, make their isometric, MEA and MEA∘isometric copies as the
    augmenter does, replay every demonstration and copy through physics, and report how many
    transitions the simulator reproduces, per kind (after measuring the noise floor)."""

    task: str = "block_pull"
    """Task: block_pull, block_pick or drawer_open."""
    episodes: int = 10
    """Successful expert demonstrations to augment (alternating probe/direct, as the actor)."""
    copies: int = 6
    """MEA copies per demonstration (the paper's Equi-RSAC setting)."""
    isometric: int = 4
    """Isometric copies per demonstration (each with its own angle, as the augmenter's)."""
    mea_isometric: bool = True
    """Also audit the MEA copies turned by their shared angle (G_t x G, what the augmenter stores)."""
    seed: int = 0
    """First demonstration seed, and the base seed of the group draws (as the augmenter's)."""
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
        if self.episodes < 1 or self.max_attempts < 1 or min(self.copies, self.isometric, self.views) < 0:
            raise ValueError("episodes and max_attempts must be >= 1; copies, isometric and views >= 0")

    def tolerance(self, rotated: bool = False) -> AuditTolerance:
        """The task's tolerance (``rotated``: for turned copies), with the values given here."""
        base = AuditTolerance.for_task(self.task, rotated)
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


def audit_copies(
    env: ManipulationEnv, ep: Episode, cfg: AuditConfig, counts: dict[str, int]
) -> tuple[dict[str, list[AuditResult]], dict[str, dict[str, int]]]:
    """The isometric, MEA and MEA∘isometric copies of one demonstration, drawn exactly as the
    augmenter's pipeline draws them, each audited; (results per kind, not simulable per kind and
    reason). ``counts`` accumulates the MEA guards' work."""
    from services.augmenter.core.isometric import compose_with_mea
    from services.augmenter.core.pipeline import episode_seed, isometric_copies, mea_copies, shared_rotation

    seed = episode_seed(cfg.seed, ep.episode_id)
    made = []
    for copy, draw in mea_copies(ep, cfg.mea, cfg.copies, seed):
        counts["guard rejections"] += draw.rejections
        counts["cut"] += int(draw.cut)
        counts["empty"] += copy is None
        made += [copy] if copy is not None else []
    todo = [("isometric", c) for c in isometric_copies(ep, cfg.isometric, seed)] + [("mea", c) for c in made]
    if cfg.mea_isometric and made:
        phi = shared_rotation(seed, made)
        todo += [("mea+isometric", compose_with_mea(c, phi)) for c in made]
    results: dict[str, list[AuditResult]] = {}
    skipped: dict[str, dict[str, int]] = {}
    for kind, copy in todo:
        try:
            tol = cfg.tolerance(rotated=rotation_of(copy) != 0.0)
            results.setdefault(kind, []).append(audit_episode(env, copy, ep, tol))
        except NotSimulableError as e:
            reasons = skipped.setdefault(kind, {})
            why = str(e).split(":")[0]
            reasons[why] = reasons.get(why, 0) + 1
    return results, skipped


def run_audit(cfg: AuditConfig) -> tuple[dict[str, list[dict[str, Any]]], dict[str, Any]]:
    """Record, measure the floor, augment and audit; returns (sections, meta) for ``emit``."""
    from services.actor.config import ActorConfig
    from services.actor.rollout import Actor
    from services.augmenter import audit_report as rep

    t_start = time.perf_counter()
    tol, rtol = cfg.tolerance(), cfg.tolerance(rotated=True)
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
        turned = [v for i, ep in enumerate(demos) for v in rotated_views(env, ep, np.random.default_rng([cfg.seed, i, 8]),
                                                                          cfg.views)]  # fmt: skip
        timing["floor s"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        results: dict[str, list[AuditResult]] = {kind: [] for kind in rep.KINDS}
        results["raw"] = replays  # the demonstrations replayed from their own first state
        skipped: dict[str, dict[str, int]] = {}
        counts = {"empty": 0, "cut": 0, "guard rejections": 0}
        for ep in demos:
            got, why = audit_copies(env, ep, cfg, counts)
            for kind, rs in got.items():
                results[kind] += rs
            for kind, reasons in why.items():
                for reason, n in reasons.items():
                    skipped.setdefault(kind, {})[reason] = skipped.get(kind, {}).get(reason, 0) + n
        timing["audit s"] = time.perf_counter() - t0
        isotropy = drag_isotropy(env, cfg.seed)
    finally:
        env.close()

    segments = list(env.segment_names)
    mea, rotated = results["mea"], results["isometric"] + results["mea+isometric"]
    copies = [r for k in rep.KINDS[1:] for r in results[k]]
    nontrivial = [int((r.phase == NON_TRIVIAL).sum()) for r in mea]
    timing["total s"] = time.perf_counter() - t_start
    by_kind = rep.kind_rows(results, skipped)
    sections = {
        "validity per kind (raw demonstrations, isometric, MEA, MEA∘isometric copies)": by_kind,
        "validity per kind and phase": rep.kind_phase_rows(results),
        "invalid transitions per kind: how many fail each check": rep.failure_rows(results),
        "copies that cannot be placed in the simulator (not simulable)": rep.unsimulable_rows(skipped),
        "MEA copies: distance to the simulation per observation phase, segment and metric (mm)": rep.metric_rows(
            mea, tol
        ),
        "rotated copies (isometric, MEA∘isometric): distance to the simulation (mm)": rep.metric_rows(rotated, tol),
        "pivot pose error per kind (privileged; not used for validity)": [
            {"kind": k, **row} for k in rep.KINDS for row in rep.pivot_rows(results[k])
        ],
        "noise floor (un-augmented data) and the tolerance": rep.floor_rows(replays, views, segments, tol),
        "rotated noise floor (turned first states) and the rotated copies' tolerance": [
            {**row, "floor": row["floor"].replace("teleported", "rotated")}
            for row in rep.floor_rows([], turned, segments, rtol)
            if row["n"]
        ],
        "simulator isotropy: the movable object pushed along its own axis, turned by yaw (the floor "
        "of rotated copies once objects slide)": isotropy,
        "copies and runtime": [{
            "demos": len(demos), "expert attempts": attempts,
            "copies requested": len(demos) * (cfg.isometric + cfg.copies * (1 + cfg.mea_isometric)),
            "audited": len(copies), "not simulable": sum(sum(r.values()) for r in skipped.values()), **counts,
            "non-trivial steps / MEA copy": float(np.mean(nontrivial)) if nontrivial else 0.0,
            "s / audited copy": timing["audit s"] / max(1, len(copies)), **timing,
        }],
    }  # fmt: skip
    meta = {
        "task": cfg.task,
        "augmentation": "raw demonstrations, isometric copies, MEA copies and MEA copies turned by their "
        "shared angle (MEA∘isometric), drawn as the augmenter's pipeline draws them; a rotated copy is "
        "played in the source scene turned about a vertical axis chosen to keep it in the workspace",
        "valid_pct": {row["kind"]: row["valid %"] for row in by_kind},
        "not_simulable": {row["kind"]: row["not simulable"] for row in by_kind},
        "valid": "both observations within tolerance (every segment: Chamfer and surface; the jaw), "
        "reward and terminated equal",
        "tolerance": dataclasses.asdict(tol),
        "tolerance_covers_floor": rep.floor_covered(replays, views, segments, tol),
        "rotated_tolerance": dataclasses.asdict(rtol),
        "rotated_tolerance_covers_floor": rep.floor_covered([], turned, segments, rtol),
        "rotated_views": len(turned),
        "simulator_isotropy": spread(isotropy),
        "notes": "tolerances: 1.25x the free-space floor (identity replays before any contact + teleported "
        "views); trivial/termination transitions involve contact, whose physics does not repeat exactly: "
        "compare their validity with the raw demonstrations' (the arm is redundant, so a copy reaches the "
        "H_p pose with a slightly different, unobserved joint configuration)",
        "mea": dataclasses.asdict(cfg.mea),
        "seed": cfg.seed,
        "episodes": cfg.episodes,
        "copies": cfg.copies,
        "isometric": cfg.isometric,
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
    "TASK_ROTATED_TOLERANCES",
    "TASK_TOLERANCES",
    "AuditConfig",
    "AuditResult",
    "AuditTolerance",
    "audit_copies",
    "audit_episode",
    "chamfer_mm",
    "identity_replay",
    "main",
    "rotated_views",
    "run_audit",
    "surface_mm",
    "view_floor",
]
