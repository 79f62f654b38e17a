"""The augmenter's Prometheus metrics (``mea_augmenter_*``): episodes in and out, timings, MEA guard
work and the input queue (``augmenter_metrics``), and the background audit's (``auditor_metrics``)."""

from __future__ import annotations

import math

from services.common.metrics import ServiceMetrics

_SECONDS = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


def augmenter_metrics(m: ServiceMetrics) -> dict:
    """The service loop's metrics, by short name."""
    return {
        "episodes_in": m.counter(
            "mea_augmenter_episodes_in",
            "Raw episodes received, by kind (processed, skipped_shard).",
            ["kind"],
        ),
        "episodes_out": m.counter(
            "mea_augmenter_episodes_out", "Episodes published, by kind (raw, isometric, mea).", ["kind"]
        ),
        "transitions_out": m.counter(
            "mea_augmenter_transitions_out", "Transitions in the published episodes."
        ),
        "augment_seconds": m.histogram(
            "mea_augmenter_augment_seconds", "Time to augment and re-project one raw episode.", _SECONDS
        ),
        "latency_seconds": m.histogram(
            "mea_augmenter_latency_seconds",
            "From a raw episode leaving the input queue to its last output published.",
            _SECONDS,
        ),
        "age_seconds": m.histogram(
            "mea_augmenter_episode_age_seconds",
            "Age of a raw episode (created_at, wall clock) when its last output is published.",
            (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0),
        ),
        "rejections": m.counter(
            "mea_augmenter_mea_rejections", "MEA group draws refused by the feasibility guards."
        ),
        "cuts": m.counter("mea_augmenter_mea_cut_copies", "MEA copies cut short by the feasibility guards."),
        "empty": m.counter(
            "mea_augmenter_mea_empty_copies",
            "MEA copies not made: no non-trivial step left after the guards.",
        ),
        "failed": m.counter(
            "mea_augmenter_failed_episodes", "Raw episodes whose augmentation or publication raised."
        ),
        "queue": m.gauge("mea_augmenter_queue_depth", "Raw episodes waiting in the input queue."),
    }


def auditor_metrics(m: ServiceMetrics) -> dict:
    """The background audit's metrics, by short name; the valid ratio starts at NaN (nothing audited)."""
    out = {
        "copies": m.counter(
            "mea_augmenter_audited_copies", "MEA copies audited, by result (done, error).", ["result"]
        ),
        "skipped": m.counter(
            "mea_augmenter_audit_skipped_copies",
            "MEA copies chosen for the audit but not queued (queue full).",
        ),
        "transitions": m.counter(
            "mea_augmenter_audited_transitions", "Transitions of audited MEA copies, by result.", ["result"]
        ),
        "valid_ratio": m.gauge(
            "mea_augmenter_audit_valid_ratio",
            "Fraction of audited MEA transitions the physics reproduces (NaN before the first audit).",
        ),
    }
    out["valid_ratio"].set(math.nan)
    return out


__all__ = ["auditor_metrics", "augmenter_metrics"]
