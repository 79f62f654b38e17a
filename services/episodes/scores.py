"""Scores of one episode and of one evaluation (numpy and stdlib only): success, length, return,
the paper's grasp score, and their means over M episodes. Shared by the evaluator and `mea robot`,
so both score an episode the same way; curves over evaluations are ``services.evaluator.core.curves``.

Design notes: docs/architecture-notes.md, services/episodes/scores.py."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from proto.episode import succeeded

H_MAX = 50
"""The tasks' time limit in steps (the paper's H_max)."""


def grasp_score(success: bool, length: int, h_max: int = H_MAX) -> float:
    """The paper's s_g = (H_max - H) / H_max on success, 0 on failure (clipped to [0, 1])."""
    if h_max <= 0:
        raise ValueError(f"h_max must be positive, got {h_max}")
    if not success:
        return 0.0
    return float(min(1.0, max(0.0, (h_max - length) / h_max)))


@dataclass(frozen=True)
class EpisodeResult:
    """What an evaluation keeps of one episode."""

    success: bool
    length: int
    """H: env steps taken."""
    ret: float
    """Undiscounted return."""
    seed: int | None = None


def episode_result(
    rewards: Sequence[float], terminated: Sequence[bool], seed: int | None = None
) -> EpisodeResult:
    """An episode's result from its per-step rewards and terminal flags (success = the last step terminated,
    not with a negative reward: ``proto.episode.succeeded``)."""
    if len(rewards) != len(terminated):
        raise ValueError(f"{len(rewards)} rewards for {len(terminated)} terminal flags")
    success = succeeded(terminated, rewards)
    return EpisodeResult(success, len(rewards), float(np.sum(np.asarray(rewards, np.float64))), seed)


@dataclass(frozen=True)
class EvalSummary:
    """One evaluation of one policy version over M episodes."""

    episodes: int
    success_rate: float
    mean_return: float
    mean_length: float
    grasp_score: float
    """Mean of s_g over the episodes (failures count as 0)."""


def summarize(results: Sequence[EpisodeResult], h_max: int = H_MAX) -> EvalSummary:
    """Average M episode results (M >= 1)."""
    if not results:
        raise ValueError("no episodes to summarize")
    n = len(results)
    return EvalSummary(
        episodes=n,
        success_rate=sum(r.success for r in results) / n,
        mean_return=float(np.mean([r.ret for r in results])),
        mean_length=float(np.mean([r.length for r in results])),
        grasp_score=float(np.mean([grasp_score(r.success, r.length, h_max) for r in results])),
    )


__all__ = ["H_MAX", "EpisodeResult", "EvalSummary", "episode_result", "grasp_score", "summarize"]
