"""`mea audit` on the general tasks (block_pull, block_pick, drawer_open): record expert
demonstrations, augment them as the augmenter does, replay every demonstration and copy through
physics, and count the transitions the simulator reproduces.

Only orchestration and reports: the replay and what counts as valid are the augmenter's.

Design notes: docs/architecture-notes.md, mea_tools/audit/general.py."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from mea_tools.audit import tables as rep
from mea_tools.audit.config import AuditConfig
from proto.episode import Episode
from services.actor.config import ActorConfig
from services.actor.rollout import RolloutActor
from services.augmenter.audit_isotropy import drag_isotropy, spread
from services.augmenter.audit_physics import audit_episode, identity_replay, rotated_views, view_floor
from services.augmenter.audit_placement import NotSimulableError, rotation_of
from services.augmenter.core.audit_metrics import NON_TRIVIAL, AuditResult
from services.augmenter.core.isometric import compose_with_mea
from services.augmenter.core.pipeline import (
    AugmentStats,
    episode_seed,
    isometric_copies,
    kept_mea_copies,
    shared_rotation,
)
from services.tasks import ManipulationEnv


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
    seed = episode_seed(cfg.seed, ep.episode_id)
    guards = AugmentStats()
    made = kept_mea_copies(ep, cfg.mea, cfg.mea_copies, seed, guards)
    counts["guard rejections"] += guards.rejections
    counts["cut"] += guards.cuts
    counts["empty"] += guards.mea_empty
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


def run_general_audit(cfg: AuditConfig) -> tuple[dict[str, list[dict[str, Any]]], dict[str, Any]]:
    """Record, measure the floor, augment and audit; returns (sections, meta) for ``emit``."""
    t_start = time.perf_counter()
    tol, rtol = cfg.tolerance(), cfg.tolerance(rotated=True)
    actor = RolloutActor(ActorConfig(task=cfg.task, policy="expert", seed_base=cfg.seed), "audit")
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
            "copies requested": len(demos) * (cfg.isometric + cfg.mea_copies * (1 + cfg.mea_isometric)),
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
        "copies": cfg.mea_copies,
        "isometric": cfg.isometric,
    }
    return sections, meta


__all__ = ["audit_copies", "record_demos", "run_general_audit"]
