"""The learner's Prometheus metrics: their definitions and how the trainer's outputs land in them."""

from __future__ import annotations

import re
from typing import Any

from services.algorithms.trainer import GateReading
from services.common.metrics import ServiceMetrics

LOSSES = {
    name: f"{name}_loss"
    for name in ("critic", "actor", "alpha", "bc", "model", "image", "reward", "discount")
}
LOSSES["kl"] = "kl"
"""``mea_learner_loss{loss}`` label -> the update info's key: SAC's (critic, actor, alpha, bc) and
GASv2's (its world model's model, image, reward and discount terms and its KL; its actor and critic)."""
RATE_WINDOW_SECONDS = 30.0
"""``mea_learner_updates_per_second`` counts the updates of this many recent seconds."""


def learner_metrics(m: ServiceMetrics) -> dict[str, Any]:
    """Every metric the learner exports, by short name."""
    return {
        "updates": m.counter("mea_learner_updates", "Gradient updates done."),
        "update_seconds": m.histogram(
            "mea_learner_update_seconds",
            "Wall time of one update (sample, transfer, losses, optimiser steps).",
            (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0),
        ),
        "loss": m.gauge("mea_learner_loss", "Latest loss by name (LOSSES: SAC and GASv2 terms).", ["loss"]),
        "alpha": m.gauge("mea_learner_alpha", "Entropy temperature."),
        "batch_demo_share": m.gauge(
            "mea_learner_batch_demo_share",
            "Share of the latest batch's episodes drawn from the demonstration set.",
        ),
        "batch_reward_transitions": m.gauge(
            "mea_learner_batch_reward_transitions", "Transitions with reward > 0 in the latest batch."
        ),
        "entropy": m.gauge(
            "mea_learner_policy_entropy",
            "Latest policy entropy estimate (SAC: -mean log pi; GASv2: the imagination actor's).",
        ),
        "q": m.gauge("mea_learner_q", "Latest mean Q values (q1, q2, target).", ["stat"]),
        "updates_per_second": m.gauge("mea_learner_updates_per_second", "Updates per second (recent)."),
        "wait": m.counter("mea_learner_wait_seconds", "Time the trainer waited for the limiter or data."),
        "episodes_in": m.counter("mea_learner_episodes_in", "Episodes inserted, by kind.", ["kind"]),
        "rejected": m.counter(
            "mea_learner_rejected_episodes", "Episodes the replay refused, by reason.", ["reason"]
        ),
        "env_steps": m.gauge("mea_learner_env_steps", "Raw env steps inserted (the limiter's inserts)."),
        "replay_transitions": m.gauge("mea_learner_replay_transitions", "Transitions stored in replay."),
        "replay_episodes": m.gauge("mea_learner_replay_episodes", "Episodes stored in replay."),
        "replay_bytes": m.gauge("mea_learner_replay_bytes", "Bytes reserved by the replay arrays."),
        "can_sample": m.gauge("mea_learner_limiter_can_sample", "1 if the limiter allows an update now."),
        "samples_allowed": m.gauge("mea_learner_limiter_samples_allowed", "Updates the limiter allows now."),
        "inserts_allowed": m.gauge(
            "mea_learner_limiter_inserts_allowed", "Env steps producers may still add before waiting."
        ),
        "version": m.gauge("mea_learner_weights_version", "Latest weights version published."),
        "episode_lag": m.histogram(
            "mea_learner_episode_lag_updates",
            "Updates the learner owed (inserted env steps x samples per insert, less updates made) when the "
            "weights that acted a learned episode were announced: data they had not yet learned from.",
            (0, 1, 10, 25, 50, 100, 150, 200, 300, 500, 1000),
        ),
        "publish_seconds": m.histogram(
            "mea_learner_weights_publish_seconds",
            "Export, encode and announce one weights version.",
            (0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0),
        ),
        "inbox_bytes": m.gauge(
            "mea_learner_inbox_bytes",
            "Bytes of received episodes waiting for the replay (while a checkpoint holds it).",
        ),
        "checkpoints": m.counter("mea_learner_checkpoints", "Checkpoints written."),
        "checkpoint_seconds": m.histogram(
            "mea_learner_checkpoint_seconds", "Time to write one checkpoint.", (0.1, 0.5, 1, 2, 5, 10, 30, 60)
        ),
    }


class UpdateRate:
    """Updates per second over the last ``RATE_WINDOW_SECONDS``."""

    def __init__(self) -> None:
        self._recent: list[float] = []

    def tick(self, now: float) -> float | None:
        """Count an update at ``now`` (monotonic seconds); the recent rate, None until there are two."""
        self._recent = [t for t in self._recent if now - t < RATE_WINDOW_SECONDS] + [now]
        if len(self._recent) > 1:
            return (len(self._recent) - 1) / max(1e-9, now - self._recent[0])
        return None


def record_update(mx: dict[str, Any], info: dict[str, float], seconds: float, rate: float | None) -> None:
    """One update's wall time, losses and statistics (``Trainer.step``'s info) and the recent rate."""
    mx["updates"].inc()
    mx["update_seconds"].observe(seconds)
    for name, key in LOSSES.items():
        if key in info:
            mx["loss"].labels(name).set(info[key])
    mx["batch_demo_share"].set(info["batch_demo_share"])
    mx["batch_reward_transitions"].set(info["batch_reward_transitions"])
    if "alpha" in info:  # SAC only
        mx["alpha"].set(info["alpha"])
    entropy = info.get("entropy", info.get("actor_entropy"))
    if entropy is not None:
        mx["entropy"].set(entropy)
    for stat, key in (("q1", "q1"), ("q2", "q2"), ("target", "target_q")):
        if key in info:
            mx["q"].labels(stat).set(info[key])
    if rate is not None:
        mx["updates_per_second"].set(rate)


def record_gate(mx: dict[str, Any], reading: GateReading) -> None:
    """The replay's and the limiter's state at a gate reading."""
    mx["env_steps"].set(reading.inserted)
    mx["replay_transitions"].set(reading.replay_transitions)
    mx["replay_episodes"].set(reading.replay_episodes)
    mx["inserts_allowed"].set(reading.inserts_allowed)
    mx["samples_allowed"].set(reading.samples_allowed)
    mx["can_sample"].set(int(reading.can_sample))


def rejection_reason(message: str) -> str:
    """A short, bounded metric label from a replay error ("images: ..." -> "images")."""
    head = message.split(":", 1)[0].strip().split()[0] if message.strip() else "invalid"
    return re.sub(r"[^a-z_]", "", head.lower())[:32] or "invalid"
