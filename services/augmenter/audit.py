"""`mea audit`: replay augmented episodes through real physics and check that they are valid.

MEA claims that an augmented copy is what the simulator would have produced from the augmented
initial state under the augmented actions. The audit tests that claim directly, transition by
transition:

1. Put the simulator into the augmented initial state: ``env.reset(source.seed)`` (same object
   placement and the same hidden movable/fixed choice, both drawn from the seed), teleport the
   arm so that its pivot is at ``aug.gripper_pose[0]`` (x, y, z, yaw) with the jaw at the
   recorded opening, and let the world settle for as many physics steps as ``env.reset`` does.
2. Replay ``aug.actions`` step by step through ``env.step`` (IK, motors, contacts: real physics).
3. Compare every simulated observation with the augmented one. Points are resampled at random in
   every observation (the sampling generator depends on the episode seed and step), so the
   clouds have no point-to-point correspondence: each segment (gripper, every object) is compared
   as a set, by the symmetric Chamfer distance (mean nearest-neighbour distance, mm), and its
   visibility (seen / unseen) must agree. The jaw opening is compared too.
4. A transition t (s_t, a_t, r_t, s_t+1) is valid when both of its observations are within
   tolerance on every segment and the jaw, and the simulated reward and `terminated` flag equal
   the augmented ones. (`truncated` is a time limit on the absolute step count, not a property of
   the state; a copy cut to start later has fewer steps on the env's clock, so it is not compared.)

Transitions are grouped by MEA phase: non-trivial (t < phase_split: the augmented part), trivial
(phase_split <= t < T-1: the recorded actions from the recorded state at H_p) and termination
(t = T-1). The privileged pivot pose error (simulated vs ``aug.gripper_pose``) is reported beside,
never used for validity (the policy does not see it).

The tolerance is not a guess: ``mea audit`` first replays every source demonstration from its own
recorded first pose with its own actions (the identity transform) and reports that noise floor
(point sampling, a few tenths of a millimetre of tracking error, views). The defaults of
``AuditTolerance`` are the largest per-segment Chamfer distance seen over the identity replays of
all three tasks, times a safety factor; see the field docstrings for the numbers.

Only MEA is audited (no isometric rotation): a scene rotated about the workspace centre can leave
the box workspace the simulator's objects and arm live in, so a rotated copy has no simulated
counterpart to compare with.

``audit_episode`` is the library entry point (the augmenter can audit a copy given an env);
``run_audit`` records expert demonstrations, augments and audits them; ``main`` is the CLI.
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
SETTLE_STEPS = 10  # physics steps env.reset lets the world rest after placing the arm; mirrored here
RESAMPLE_SALT = 0x5EED_A0D1  # offsets the replay's point-sampling stream from the recorded one


@dataclass(frozen=True)
class AuditTolerance:
    """How far a simulated observation may be from the augmented one and still count as equal.

    Noise floor (identity replays: each recorded expert demonstration replayed from its own first
    pose with its own actions; 10 demos per task, seed 0, every observation; Chamfer in mm):

    ============  ===================  ===================  ===================
    segment       block_pull p95/max   block_pick p95/max   drawer_open p95/max
    ============  ===================  ===================  ===================
    gripper       see README of audit  (filled from runs)   (filled from runs)
    ============  ===================  ===================  ===================

    The tolerances are 2x the largest floor value over all tasks and segments of a kind, rounded
    up; a 1 cm error of an object's position gives well over that (see tests/unit/test_audit.py).
    """

    gripper_chamfer_mm: float = 4.0
    """Gripper segment: largest Chamfer distance (mm) between the simulated and augmented clouds."""
    object_chamfer_mm: float = 4.0
    """Object segments: largest Chamfer distance (mm) between the simulated and augmented clouds."""
    jaw: float = 0.05
    """Largest difference of the jaw opening (0 closed .. 1 open)."""

    def chamfer_mm(self, segment: str) -> float:
        return self.gripper_chamfer_mm if segment == "gripper" else self.object_chamfer_mm


# --------------------------------------------------------------------------------------------
# comparing observations
# --------------------------------------------------------------------------------------------


def chamfer_mm(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric mean nearest-neighbour distance between two clouds, in mm (inf if one is empty)."""
    if len(a) == 0 or len(b) == 0:
        return math.inf
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d2 = (a64 * a64).sum(1)[:, None] + (b64 * b64).sum(1)[None, :] - 2.0 * a64 @ b64.T
    d = np.sqrt(np.maximum(d2, 0.0))
    return float((d.min(axis=1).mean() + d.min(axis=0).mean()) / 2 * 1000.0)


def distinct_points(points: np.ndarray, count: int) -> np.ndarray:
    """The distinct points of one sampled segment: ``sample_fixed`` puts all ``count`` distinct points
    first and pads with repeats when fewer than P were seen."""
    return points[: min(int(count), len(points))]


def segment_chamfers(sim_points, sim_counts, aug_points, aug_counts) -> np.ndarray:
    """(S,) Chamfer distance per segment (mm): 0 when both sides see nothing, inf when one does."""
    out = np.zeros(len(sim_counts))
    for i, (ns, na) in enumerate(zip(sim_counts, aug_counts, strict=True)):
        if ns == 0 and na == 0:
            continue
        out[i] = chamfer_mm(distinct_points(sim_points[i], ns), distinct_points(aug_points[i], na))
    return out


def surface_mm(points: np.ndarray, cloud: np.ndarray) -> float:
    """Mean distance (mm) from ``points`` to their nearest neighbour in ``cloud`` (one-sided)."""
    if len(points) == 0 or len(cloud) == 0:
        return math.inf
    a64, b64 = np.asarray(points, np.float64), np.asarray(cloud, np.float64)
    d2 = (a64 * a64).sum(1)[:, None] + (b64 * b64).sum(1)[None, :] - 2.0 * a64 @ b64.T
    return float(np.sqrt(np.maximum(d2.min(axis=1), 0.0)).mean() * 1000.0)


def fused_clouds(env: ManipulationEnv) -> list[np.ndarray]:
    """Everything the cameras see of each segment now (before the random draw of P points), in the
    gripper-centric frame, in segment order."""
    parts = {"gripper": env._gripper_parts(), **env.task.object_segments()}
    world = env.cameras.render_segments(parts)
    origin = env.robot.pivot()[0]
    return [world[name] - origin if len(world[name]) else world[name] for name in env.segment_names]


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
    chamfer: np.ndarray  # (T+1, S) mm per observation and segment
    surface: np.ndarray  # (T+1, S) mm: augmented points to the simulated fused cloud
    obs_ok: np.ndarray  # (T+1,) every segment within tolerance, visibility and jaw agree
    jaw_error: np.ndarray  # (T+1,)
    reward_ok: np.ndarray  # (T,)
    terminated_ok: np.ndarray  # (T,)
    valid: np.ndarray  # (T,) obs_ok[t] & obs_ok[t+1] & reward_ok[t] & terminated_ok[t]
    pivot_error_mm: np.ndarray  # (T+1,) privileged: |simulated pivot - aug.gripper_pose|
    yaw_error_deg: np.ndarray  # (T+1,)
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
    episode's. ``observe`` seeds its sampler with (env.seed, step), and env.seed is used for
    nothing else after the reset has placed the objects, so replacing it changes only which points
    are drawn. Without it a replay whose fused clouds are bit-identical to the recording draws the
    very same points and the Chamfer distance is 0, a floor no augmented copy (whose clouds differ)
    can share."""
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
    tol: AuditTolerance = AuditTolerance(),
    resample: bool = True,
) -> AuditResult:
    """Replay ``aug`` through ``env``'s physics from its first state and compare, step by step.

    ``source`` is the raw episode ``aug`` was made from (its seed places the objects). An episode
    without ``augmentation`` (e.g. ``source`` itself) is audited as the identity transform: every
    transition counts as trivial except the last."""
    t0 = time.perf_counter()
    if aug.task != env.task.name or source.task != env.task.name:
        raise ValueError(f"episode of task {aug.task!r} audited in a {env.task.name!r} env")
    T, S = aug.num_steps, len(aug.segments)
    split = aug.augmentation.phase_split if aug.augmentation is not None else 0
    chamfer = np.zeros((T + 1, S))
    surface = np.zeros((T + 1, S))
    jaw_err = np.zeros(T + 1)
    pivot_err = np.zeros(T + 1)
    yaw_err = np.zeros(T + 1)
    reward_ok = np.zeros(T, bool)
    term_ok = np.zeros(T, bool)
    limits = np.array([tol.chamfer_mm(name) for name in aug.segments])

    def compare(i: int, obs: Observation) -> None:
        chamfer[i] = segment_chamfers(obs.points, obs.point_counts, aug.points[i], aug.point_counts[i])
        for s, cloud in enumerate(fused_clouds(env)):
            n = int(aug.point_counts[i, s])
            surface[i, s] = (
                0.0 if n == 0 and len(cloud) == 0 else surface_mm(distinct_points(aug.points[i, s], n), cloud)
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
    obs_ok = np.all(chamfer <= limits[None, :], axis=1) & (jaw_err <= tol.jaw)
    valid = obs_ok[:-1] & obs_ok[1:] & reward_ok & term_ok
    return AuditResult(
        episode_id=aug.episode_id, source_id=source.episode_id, segments=list(aug.segments),
        phase=phases(T, split), chamfer=chamfer, surface=surface, obs_ok=obs_ok, jaw_error=jaw_err, reward_ok=reward_ok,
        terminated_ok=term_ok, valid=valid, pivot_error_mm=pivot_err, yaw_error_deg=yaw_err,
        seconds=time.perf_counter() - t0,
    )  # fmt: skip


def identity_replay(
    env: ManipulationEnv, source: Episode, tol: AuditTolerance = AuditTolerance(), resample: bool = True
) -> AuditResult:
    """Audit ``source`` against itself: the noise floor of the audit (no transform at all)."""
    return audit_episode(env, source, source, tol, resample)


# --------------------------------------------------------------------------------------------
# summaries
# --------------------------------------------------------------------------------------------


def _stats(x: np.ndarray) -> dict[str, float]:
    x = np.asarray(x, np.float64)
    if len(x) == 0:
        return {"n": 0, "mean": None, "p50": None, "p95": None, "max": None}
    finite = x[np.isfinite(x)]
    mean = float(finite.mean()) if len(finite) == len(x) else math.inf
    return {
        "n": int(len(x)),
        "mean": mean,
        "p50": float(np.percentile(x, 50)),
        "p95": float(np.percentile(x, 95)),
        "max": float(x.max()),
    }


def validity_rows(results: Sequence[AuditResult]) -> list[dict[str, Any]]:
    rows = []
    for p, name in enumerate(PHASES):
        valid = np.concatenate([r.valid[r.phase == p] for r in results]) if results else np.zeros(0)
        cons = np.concatenate([r.consistent[r.phase == p] for r in results]) if results else np.zeros(0)
        rows.append({
            "phase": name,
            "transitions": int(len(valid)),
            "valid": int(valid.sum()),
            "valid %": 100.0 * float(valid.mean()) if len(valid) else None,
            "reward+term consistent %": 100.0 * float(cons.mean()) if len(cons) else None,
        })  # fmt: skip
    every = np.concatenate([r.consistent for r in results]) if results else np.zeros(0)
    valid_all = np.concatenate([r.valid for r in results]) if results else np.zeros(0)
    rows.append({
        "phase": "all",
        "transitions": int(len(valid_all)),
        "valid": int(valid_all.sum()),
        "valid %": 100.0 * float(valid_all.mean()) if len(valid_all) else None,
        "reward+term consistent %": 100.0 * float(every.mean()) if len(every) else None,
    })  # fmt: skip
    return rows


def chamfer_rows(results: Sequence[AuditResult], tol: AuditTolerance, by_phase: bool = True) -> list[dict]:
    """Chamfer distribution (mm) per phase (of the observations) and segment."""
    if not results:
        return []
    segments = results[0].segments
    groups = list(enumerate(PHASES)) if by_phase else [(None, "all")]
    rows = []
    for p, pname in groups:
        for s, seg in enumerate(segments):
            vals = np.concatenate([
                r.chamfer[:, s] if p is None else r.chamfer[r.observation_phase() == p, s] for r in results
            ])  # fmt: skip
            rows.append({"phase": pname, "segment": seg, **_stats(vals), "tolerance": tol.chamfer_mm(seg)})
        if True:
            vals = np.concatenate([
                r.jaw_error if p is None else r.jaw_error[r.observation_phase() == p] for r in results
            ])  # fmt: skip
            rows.append({"phase": pname, "segment": "jaw (0..1)", **_stats(vals), "tolerance": tol.jaw})
    return rows


def pivot_rows(results: Sequence[AuditResult]) -> list[dict[str, Any]]:
    rows = []
    for p, pname in enumerate(PHASES):
        pos = np.concatenate([r.pivot_error_mm[r.observation_phase() == p] for r in results] or [np.zeros(0)])
        yaw = np.concatenate([r.yaw_error_deg[r.observation_phase() == p] for r in results] or [np.zeros(0)])
        if not len(pos):
            continue
        rows.append({
            "phase": pname, "observations": int(len(pos)), "pivot mean mm": float(pos.mean()),
            "pivot p95 mm": float(np.percentile(pos, 95)), "pivot max mm": float(pos.max()),
            "yaw mean deg": float(yaw.mean()), "yaw max deg": float(yaw.max()),
        })  # fmt: skip
    return rows


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AuditConfig:
    """Record expert demonstrations, make MEA copies, replay every copy through physics, and
    report how many augmented transitions the simulator reproduces."""

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
    gripper_chamfer_mm: float = AuditTolerance.gripper_chamfer_mm
    """Tolerance: gripper segment Chamfer distance (mm)."""
    object_chamfer_mm: float = AuditTolerance.object_chamfer_mm
    """Tolerance: object segment Chamfer distance (mm)."""
    jaw: float = AuditTolerance.jaw
    """Tolerance: jaw opening difference (0..1)."""
    mea: MeaSettings = field(default_factory=MeaSettings)
    """MEA settings audited (phases, group ranges, feasibility guards)."""

    def __post_init__(self) -> None:
        if self.episodes < 1 or self.copies < 0 or self.max_attempts < 1:
            raise ValueError("episodes and max_attempts must be >= 1, copies >= 0")

    @property
    def tolerance(self) -> AuditTolerance:
        return AuditTolerance(self.gripper_chamfer_mm, self.object_chamfer_mm, self.jaw)


def run_audit(cfg: AuditConfig) -> tuple[dict[str, list[dict[str, Any]]], dict[str, Any]]:
    """Record, augment and audit; returns (sections, meta) for ``emit``."""
    from services.actor.main import Actor, ActorConfig
    from services.augmenter.core.pipeline import episode_seed

    t_start = time.perf_counter()
    tol = cfg.tolerance
    actor = Actor(ActorConfig(task=cfg.task, policy="expert", seed_base=cfg.seed), "audit")
    env = actor.env
    try:
        demos: list[Episode] = []
        attempts = 0
        t0 = time.perf_counter()
        while len(demos) < cfg.episodes and attempts < cfg.episodes * cfg.max_attempts:
            b = actor.expert_episode(len(demos))
            attempts += 1
            if b.success:
                demos.append(b.finish(actor.episode_id(b)))
        record_s = time.perf_counter() - t0

        t0 = time.perf_counter()
        floor = [identity_replay(env, ep, tol) for ep in demos]
        floor_s = time.perf_counter() - t0

        t0 = time.perf_counter()
        results: list[AuditResult] = []
        made = empty = cut = rejections = 0
        for ep in demos:
            seed = episode_seed(cfg.seed, ep.episode_id)
            for k in range(cfg.copies):
                rng = np.random.default_rng([seed, 1_000_001 + k])
                copy, draw = augment(
                    ep, cfg.mea, rng, seed=seed, copy_index=k, episode_id=f"{ep.episode_id}.mea{k}"
                )
                rejections += draw.rejections
                cut += int(draw.cut)
                if copy is None:
                    empty += 1
                    continue
                made += 1
                results.append(audit_episode(env, copy, ep, tol))
        audit_s = time.perf_counter() - t0
    finally:
        env.close()

    nontrivial = [int((r.phase == NON_TRIVIAL).sum()) for r in results]
    sections = {
        "validity of MEA copies (per phase)": validity_rows(results),
        "Chamfer distance of MEA copies, mm (per observation phase and segment)": chamfer_rows(results, tol),
        "pivot error of MEA copies (privileged, not used for validity)": pivot_rows(results),
        "noise floor: identity replays (validity)": validity_rows(floor),
        "noise floor: identity replays, Chamfer mm": chamfer_rows(floor, tol, by_phase=False),
        "copies": [{
            "demos": len(demos), "expert attempts": attempts, "copies requested": len(demos) * cfg.copies,
            "audited": made, "empty": empty, "cut": cut, "guard rejections": rejections,
            "non-trivial steps / copy": float(np.mean(nontrivial)) if nontrivial else 0.0,
            "record s": record_s, "floor s": floor_s, "audit s": audit_s,
            "total s": time.perf_counter() - t_start,
        }],
    }  # fmt: skip
    meta = {
        "task": cfg.task,
        "augmentation": "MEA only (no isometric rotation: a rotated scene can leave the box workspace)",
        "tolerance": dataclasses.asdict(tol),
        "valid": "both observations within tolerance on every segment and the jaw, reward and terminated equal",
        "mea": dataclasses.asdict(cfg.mea),
        "seed": cfg.seed,
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
    "AuditConfig",
    "AuditResult",
    "AuditTolerance",
    "audit_episode",
    "chamfer_mm",
    "identity_replay",
    "main",
    "run_audit",
]
