"""When the evaluator evaluates, and on which held-out seeds: pure decisions (no clock, no transport).

Evaluations follow the learner's training env steps (a cadence, plus one at the budget), on the same
held-out seeds every time, so that a run's evaluations compare with each other and across runs.

Design notes: docs/architecture-notes.md, services/evaluator/core/schedule.py."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class Schedule:
    """The evaluator's cadence and evaluation sizes (validated by ``EvaluatorConfig``)."""

    episodes: int
    every_env_steps: int
    seed_base: int
    final_env_steps: int = 0
    """The run's env-step budget (0: none)."""
    final_episodes: int = 0
    """Episodes of an evaluation at or past the budget (0: ``episodes``)."""
    first_gate_wait: float
    """Seconds to wait for a gate before evaluating a first version with unknown env steps."""

    def at_budget(self, env_steps: int) -> bool:
        """Is a version pulled at ``env_steps`` the run's final evaluation (at or past the budget)?"""
        return 0 < self.final_env_steps <= env_steps

    def seeds_at(self, env_steps: int) -> tuple[int, ...]:
        """The held-out seeds of an evaluation of a version pulled at ``env_steps``: ``episodes`` of
        them, or ``final_episodes`` (when set) at the budget; always a prefix of one seed sequence."""
        n = self.final_episodes if self.at_budget(env_steps) and self.final_episodes > 0 else self.episodes
        return tuple(self.seed_base + k for k in range(n))

    def due(self, env_steps: int, last_env_steps: int | None, waited: float) -> bool:
        """Is it time to pull (and evaluate) the newest version?

        ``env_steps``: the learner's steps now (-1: no gate seen); ``last_env_steps``: those of the
        last evaluation (None: nothing evaluated yet, -1: it had none); ``waited``: seconds since
        the evaluator started."""
        if last_env_steps is None:  # nothing evaluated yet: as soon as a version exists
            return env_steps >= 0 or waited >= self.first_gate_wait
        if last_env_steps < 0:  # evaluations without steps (no learner gate): every new version
            return True
        if env_steps < 0:  # known before, not yet now (a restart or --resume): wait for the gate, never -1
            return False
        if env_steps < last_env_steps:  # the learner went back (restarted): start the cadence afresh
            return True
        if 0 < self.final_env_steps <= env_steps and last_env_steps < self.final_env_steps:
            return True  # the budget is reached: the run's last evaluation
        return env_steps - last_env_steps >= self.every_env_steps


def last_evaluated_env_steps(records: Iterable[Mapping]) -> int | None:
    """The env steps of the last evaluation in a history (file order), so the cadence survives a
    restart; None if no record has integer env steps."""
    known = [r["env_steps"] for r in records if isinstance(r.get("env_steps"), int)]
    return known[-1] if known else None


__all__ = ["Schedule", "last_evaluated_env_steps"]
