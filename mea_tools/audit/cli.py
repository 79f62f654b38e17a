"""`mea audit`: replay augmented episodes through physics and report their validity; the general
tasks' audit (``general``) or Surgical Grasp Any's (``surgical``), chosen by ``--task``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from mea_tools.audit.config import AuditConfig
from mea_tools.audit.general import run_general_audit
from mea_tools.audit.surgical import run_surgical_audit
from mea_tools.bench.report import emit
from services.augmenter.core.mea_discrete import DISCRETE_MEA_TASKS
from services.common import config


def run_audit(cfg: AuditConfig) -> tuple[dict[str, list[dict[str, Any]]], dict[str, Any]]:
    """Record, measure the floor, augment and audit; returns (sections, meta) for ``emit``."""
    if cfg.task in DISCRETE_MEA_TASKS:
        return run_surgical_audit(cfg)
    return run_general_audit(cfg)


def main(argv: Sequence[str]) -> int:
    cfg = config.parse(AuditConfig, {"default": AuditConfig()}, argv, "mea audit", AuditConfig.__doc__ or "")
    sections, meta = run_audit(cfg)
    emit("audit", sections, {}, cfg.json, meta)
    return 0
