"""`mea audit --task surgical_grasp_any`: oracle demonstrations, their discrete MEA copies drawn as
the augmenter draws them, every transition replayed in the simulator
(``services.augmenter.audit_surgical``), and how many the simulator reproduces.

Kinds: ``raw`` (the demonstrations replayed the same way: the noise floor the tolerances rest on)
and ``mea`` (the copies). Each is reported over all transitions, per phase (non-trivial: the
instrument placed at each moved state; trivial and termination: the grasp and the lift rolled out
from H_p) and over the transitions a copy actually moved (``moved``: D_t or D_{t+1} nonzero).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from mea_tools.audit.config import AuditConfig
from mea_tools.audit.general import record_demos
from services.actor.config import ActorConfig
from services.actor.rollout import RolloutActor
from services.augmenter.audit_surgical import (
    CHECKS,
    SurgicalAuditResult,
    SurgicalTolerance,
    audit_surgical,
    floor_covered,
    worst_errors,
)
from services.augmenter.core.audit_metrics import PHASES
from services.augmenter.core.mea_discrete import DiscreteCounts, mea_discrete_copies, phase_split
from services.augmenter.core.pipeline import episode_seed

KINDS = ("raw", "mea")
ERRORS = (("pivot mm", "pivot_mm"), ("yaw deg", "yaw_deg"), ("jaw", "jaw_error"), ("object mm", "object_mm"))


def _pct(x: np.ndarray) -> float | None:
    return 100.0 * float(np.mean(x)) if len(x) else None


def _cat(results: list[SurgicalAuditResult], name: str, mask=None) -> np.ndarray:
    parts = [np.asarray(getattr(r, name))[mask(r)] if mask else np.asarray(getattr(r, name)) for r in results]
    return np.concatenate(parts) if parts else np.zeros(0)


def _selections():
    yield "all", None
    for p, name in enumerate(PHASES):
        yield name, (lambda r, p=p: r.phase == p)
    yield "moved", (lambda r: r.moved)


def validity_rows(results: dict[str, list[SurgicalAuditResult]]) -> list[dict[str, Any]]:
    rows = []
    for kind, rs in results.items():
        for sel, mask in _selections():
            valid = _cat(rs, "valid", mask).astype(bool)
            if sel != "all" and not len(valid):
                continue
            rows.append({"kind": kind, "transitions": sel, "n": int(len(valid)), "valid": int(valid.sum()),
                         "valid %": _pct(valid)})  # fmt: skip
    return rows


def failure_rows(results: dict[str, list[SurgicalAuditResult]]) -> list[dict[str, Any]]:
    rows = []
    for kind, rs in results.items():
        invalid = ~_cat(rs, "valid").astype(bool)
        row: dict[str, Any] = {"kind": kind, "invalid": int(invalid.sum())}
        for check in CHECKS:
            row[check] = int((~np.concatenate([r.checks[check] for r in rs] or [np.ones(0, bool)])).sum())
        rows.append(row)
    return rows


def error_rows(results: dict[str, list[SurgicalAuditResult]]) -> list[dict[str, Any]]:
    rows = []
    for kind, rs in results.items():
        for sel, mask in _selections():
            if sel == "all":
                continue
            for label, name in ERRORS:
                x = _cat(rs, name, mask)
                if not len(x):
                    continue
                rows.append({"kind": kind, "transitions": sel, "error": label, "n": int(len(x)),
                             "p50": float(np.percentile(x, 50)), "p99": float(np.percentile(x, 99)),
                             "max": float(x.max())})  # fmt: skip
    return rows


def floor_rows(floor: list[SurgicalAuditResult], tol: SurgicalTolerance) -> list[dict[str, Any]]:
    free, contact = worst_errors(floor, False), worst_errors(floor, True)
    return [
        {"quantity": "pivot mm", "floor max (free space)": free["pivot_mm"],
         "floor max (contact)": contact["pivot_mm"], "tolerance": tol.pivot_mm},
        {"quantity": "yaw deg", "floor max (free space)": free["yaw_deg"],
         "floor max (contact)": contact["yaw_deg"], "tolerance": tol.yaw_deg},
        {"quantity": "jaw", "floor max (free space)": free["jaw"], "floor max (contact)": contact["jaw"],
         "tolerance": f"{tol.jaw} / {tol.contact_jaw} (contact)"},
        {"quantity": "object mm", "floor max (free space)": free["object_mm"],
         "floor max (contact)": contact["object_mm"], "tolerance": f"{tol.object_mm} / {tol.contact_object_mm} (contact)"},
    ]  # fmt: skip


def run_surgical_audit(cfg: AuditConfig) -> tuple[dict[str, list[dict[str, Any]]], dict[str, Any]]:
    """Record oracle demonstrations, replay them (the floor) and their MEA copies; (sections, meta)."""
    t_start = time.perf_counter()
    tol = SurgicalTolerance()
    settings = (
        cfg.mea_discrete if cfg.copies is None else dataclasses.replace(cfg.mea_discrete, copies=cfg.copies)
    )
    actor = RolloutActor(ActorConfig(task=cfg.task, policy="expert", seed_base=cfg.seed), "audit")
    env = actor.env
    timing: dict[str, float] = {}
    counts = DiscreteCounts()
    results: dict[str, list[SurgicalAuditResult]] = {kind: [] for kind in KINDS}
    try:
        t0 = time.perf_counter()
        demos, attempts = record_demos(actor, cfg.episodes, cfg.max_attempts)
        timing["record s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        results["raw"] = [audit_surgical(env, ep, ep, phase_split(ep, settings), tol) for ep in demos]
        timing["floor s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        for ep in demos:
            seed = episode_seed(cfg.seed, ep.episode_id)
            for copy in mea_discrete_copies(ep, settings, seed, None, counts=counts):
                results["mea"].append(audit_surgical(env, copy, ep, copy.augmentation.phase_split, tol))
        timing["audit s"] = time.perf_counter() - t0
    finally:
        env.close()
    timing["total s"] = time.perf_counter() - t_start
    mea = results["mea"]
    moved = _cat(mea, "moved").astype(bool)
    sections = {
        "validity per kind (raw demonstrations: the noise floor; MEA copies), all transitions, per phase "
        "and over the moved ones": validity_rows(results),
        "invalid transitions per kind: how many fail each check": failure_rows(results),
        "replay errors per kind and phase (pivot, object: real mm)": error_rows(results),
        "noise floor (raw demonstrations replayed the same way) and the tolerance": floor_rows(results["raw"], tol),
        "copies and runtime": [{
            "demos": len(demos), "expert attempts": attempts, "copies requested": len(demos) * settings.copies,
            "copies made": counts.made, "given up": counts.given_up, "redraws": counts.redraws, "cut": counts.cut,
            "moved transitions": int(moved.sum()), "transitions": int(len(moved)),
            "s / audited copy": timing["audit s"] / max(1, len(mea)), **timing,
        }],
    }  # fmt: skip
    valid = {kind: _pct(_cat(rs, "valid").astype(bool)) for kind, rs in results.items()}
    meta = {
        "task": cfg.task,
        "augmentation": "discrete MEA copies (services.augmenter.core.mea_discrete), drawn as the augmenter's "
        "pipeline draws them; every transition replayed in the simulator",
        "valid_pct": valid,
        "valid_pct_moved": _pct(_cat(mea, "valid", lambda r: r.moved).astype(bool)),
        "valid": "pivot, yaw, jaw and object within tolerance, reward and terminated equal",
        "tolerance": dataclasses.asdict(tol),
        "tolerance_covers_floor": floor_covered(results["raw"], tol),
        "notes": "non-trivial transitions: the instrument placed at the copy's state (measured pivot, yaw, jaw; "
        "the object where the seed put it), the copy's action stepped through the env's drive; trivial and "
        "termination transitions: rolled out from H_p (the grasp cannot be placed by hand). The floor is the "
        "raw demonstrations replayed the same way",
        "mea_discrete": dataclasses.asdict(settings),
        "seed": cfg.seed,
        "episodes": cfg.episodes,
        "copies": settings.copies,
    }
    return sections, meta


__all__ = ["KINDS", "run_surgical_audit"]
