"""Training scalars for TensorBoard: means over a window of updates, written with torch's
``SummaryWriter`` (the tensorboard package) against env steps, CleanRL-style tags.

A service keeps one ``ScalarLog``; ``add`` is cheap (Python floats summed), ``flush_due`` writes every
``every`` calls, so a write never happens per update. Several services write into the same
directory (one event file each); a resumed run appends to it."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

TAG_PREFIXES = (
    ("batch_", "charts/"),
    ("updates_per_second", "perf/"),
    ("grad_norm", "diagnostics/"),
    ("bc_accept", "diagnostics/"),
    ("bc_weight", "diagnostics/"),
    ("q_rank_gap", "diagnostics/"),
    ("q_demo_minus_pi", "diagnostics/"),
)


def tag(name: str) -> str:
    """The TensorBoard tag of an info key: ``charts/``, ``perf/``, ``diagnostics/`` by the rules of
    ``TAG_PREFIXES`` (first that matches), ``losses/`` for every other training number."""
    for needle, prefix in TAG_PREFIXES:
        if needle in name:
            return prefix + name
    return "losses/" + name


class ScalarLog:
    """Means of named scalars over ``every`` calls of ``add``, written to ``log_dir`` at an env step."""

    def __init__(self, log_dir: Path, every: int, suffix: str) -> None:
        self.log_dir, self.suffix = log_dir, suffix
        self.every = max(1, every)
        self._writer: Any = None  # opened at the first write: importing tensorboard takes seconds
        self._sums: dict[str, float] = {}
        self._counts: dict[str, int] = {}
        self._calls = 0

    def add(self, values: Mapping[str, float], step: int) -> bool:
        """Accumulate ``values`` (non-finite ones skipped); every ``every`` calls write their means at
        ``step`` and return True."""
        for k, v in values.items():
            if isinstance(v, (int, float)) and math.isfinite(v):
                self._sums[k] = self._sums.get(k, 0.0) + float(v)
                self._counts[k] = self._counts.get(k, 0) + 1
        self._calls += 1
        if self._calls % self.every:
            return False
        self.write(step)
        return True

    @property
    def writer(self) -> Any:
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter  # deferred: a slow import, off start-up

            self._writer = SummaryWriter(str(self.log_dir), filename_suffix=f".{self.suffix}")
        return self._writer

    def write(self, step: int) -> None:
        for k, total in self._sums.items():
            self.writer.add_scalar(tag(k), total / self._counts[k], step)
        self._sums.clear()
        self._counts.clear()
        self.writer.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
