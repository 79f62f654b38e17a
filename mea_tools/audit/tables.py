"""The tables ``mea audit`` prints: validity per kind of episode and phase, distances to the
simulation, the pivot error, and the noise floor beside the tolerance in use.

Kinds (``KINDS``): ``raw`` (the demonstrations themselves, replayed from their own first state:
the identity replays of the noise floor), ``isometric``, ``mea`` and ``mea+isometric`` copies. A
copy that cannot be placed in the simulator at all
(``services.augmenter.audit_placement.NotSimulableError``) is counted apart, per reason, never as
valid and never dropped silently.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from services.augmenter.core.audit_metrics import (
    METRICS,
    PHASES,
    SAFETY,
    AuditResult,
    AuditTolerance,
    FloorSample,
)

KINDS = ("raw", "isometric", "mea", "mea+isometric")


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


def kind_rows(
    results: Mapping[str, Sequence[AuditResult]], unsimulable: Mapping[str, Mapping[str, int]]
) -> list[dict[str, Any]]:
    """Per kind and over all kinds: episodes, simulated / not simulable, valid transitions."""
    rows = []
    for kind in (*KINDS, "all"):
        picked = [r for k in KINDS for r in results.get(k, ())] if kind == "all" else results.get(kind, [])
        skipped = sum(sum(unsimulable.get(k, {}).values()) for k in KINDS if kind in ("all", k))
        valid = np.concatenate([r.valid for r in picked] or [np.zeros(0, bool)])
        cons = np.concatenate([r.consistent for r in picked] or [np.zeros(0, bool)])
        rows.append({"kind": kind, "episodes": len(picked) + skipped, "simulated": len(picked),
                     "not simulable": skipped, "transitions": int(len(valid)), "valid": int(valid.sum()),
                     "valid %": _pct(valid), "reward+term consistent %": _pct(cons)})  # fmt: skip
    return rows


def kind_phase_rows(results: Mapping[str, Sequence[AuditResult]]) -> list[dict[str, Any]]:
    """``validity_rows`` of each kind, with the kind in front."""
    return [{"kind": k, **row} for k in KINDS if results.get(k) for row in validity_rows(results[k])]


def unsimulable_rows(unsimulable: Mapping[str, Mapping[str, int]]) -> list[dict[str, Any]]:
    return [
        {"kind": k, "reason": why, "copies": n} for k in KINDS for why, n in unsimulable.get(k, {}).items()
    ]


def failure_rows(results: Mapping[str, Sequence[AuditResult]]) -> list[dict[str, Any]]:
    """Per kind: invalid transitions, and how many of them fail each check (at either end)."""
    rows = []
    for kind in KINDS:
        picked = results.get(kind, [])
        if not picked:
            continue
        row: dict[str, Any] = {"kind": kind, "invalid": int(sum((~r.valid).sum() for r in picked))}
        for name in picked[0].checks:
            row[name] = int(sum((~(r.checks[name][:-1] & r.checks[name][1:])).sum() for r in picked))
        row["reward"] = int(sum((~r.reward_ok).sum() for r in picked))
        row["terminated"] = int(sum((~r.terminated_ok).sum() for r in picked))
        rows.append(row)
    return rows
