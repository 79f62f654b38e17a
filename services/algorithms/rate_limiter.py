"""Sample-to-insert ratio limiting between env-step producers (actors) and gradient updates.

Design notes: docs/architecture-notes.md, services/algorithms/rate_limiter.py."""

from __future__ import annotations

import math
import numbers
import sys
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any, Protocol


class RateLimiter(Protocol):
    """What the learner loop needs from a limiter."""

    inserts: int
    samples: int

    def can_sample(self, n: int = 1) -> bool: ...
    def can_insert(self, n: int = 1) -> bool: ...
    def sampled(self, n: int = 1) -> None: ...
    def inserted(self, n: int) -> None: ...
    def samples_allowed(self) -> int: ...
    def inserts_allowed(self) -> int: ...
    def state_dict(self) -> dict[str, Any]: ...
    def load_state_dict(self, state: dict[str, Any]) -> None: ...


UNLIMITED = sys.maxsize
"""``samples_allowed``/``inserts_allowed`` when a side is not limited."""


def _is_real(x: object) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)


def _count(name: str, n: int) -> int:
    if isinstance(n, bool) or int(n) != n or n < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {n!r}")
    return int(n)


@dataclass
class SampleToInsertRatio:
    """Keep gradient updates per inserted env step near ``samples_per_insert`` (docs/architecture-notes.md)."""

    samples_per_insert: float
    """Target updates per inserted env step (> 0)."""
    min_size_to_sample: int
    """Env steps inserted before the first update (>= 1)."""
    error_buffer: float
    """Allowed deviation, in updates, from the target on either side (>= max(1, samples_per_insert))."""
    inserts: int = field(default=0, init=False)
    samples: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        spi, eb = self.samples_per_insert, self.error_buffer
        if not (_is_real(spi) and spi > 0):
            raise ValueError(f"samples_per_insert must be a finite number > 0, got {spi!r}")
        if (
            isinstance(self.min_size_to_sample, bool)
            or int(self.min_size_to_sample) != self.min_size_to_sample
        ):
            raise ValueError(f"min_size_to_sample must be an integer, got {self.min_size_to_sample!r}")
        if self.min_size_to_sample < 1:
            raise ValueError(f"min_size_to_sample must be >= 1, got {self.min_size_to_sample}")
        if not (_is_real(eb) and eb >= max(1.0, spi)):
            raise ValueError(
                f"error_buffer must be >= max(1, samples_per_insert) = {max(1.0, spi)}, got {eb!r}: "
                "a smaller buffer can block sampling and inserting at the same time"
            )
        self.min_size_to_sample = int(self.min_size_to_sample)
        self._spi = Fraction(spi)
        offset = self._spi * self.min_size_to_sample
        self._min_diff = offset - Fraction(eb)
        self._max_diff = offset + Fraction(eb)

    @property
    def min_diff(self) -> float:
        return float(self._min_diff)

    @property
    def max_diff(self) -> float:
        return float(self._max_diff)

    @property
    def diff(self) -> float:
        """Updates owed: ``inserts * samples_per_insert - samples``."""
        return float(self._diff())

    def _diff(self) -> Fraction:
        return self._spi * self.inserts - self.samples

    def can_sample(self, n: int = 1) -> bool:
        """Whether ``n`` more updates may run now."""
        n = _count("n", n)
        return self.inserts >= self.min_size_to_sample and self._diff() - n >= self._min_diff

    def can_insert(self, n: int = 1) -> bool:
        """Whether ``n`` more env steps may be inserted without getting ahead of the learner."""
        n = _count("n", n)
        return self._spi * (self.inserts + n) - self.samples <= self._max_diff

    def samples_allowed(self) -> int:
        """The largest ``n`` with ``can_sample(n)`` (0 when none)."""
        if self.inserts < self.min_size_to_sample:
            return 0
        return max(0, math.floor(self._diff() - self._min_diff))

    def inserts_allowed(self) -> int:
        """The largest ``n`` with ``can_insert(n)``: env steps producers may add before waiting."""
        return max(0, math.floor((self._max_diff + self.samples) / self._spi) - self.inserts)

    def sampled(self, n: int = 1) -> None:
        self.samples += _count("n", n)

    def inserted(self, n: int) -> None:
        self.inserts += _count("n", n)

    def state_dict(self) -> dict[str, Any]:
        return {
            "inserts": self.inserts,
            "samples": self.samples,
            "samples_per_insert": float(self.samples_per_insert),
            "min_size_to_sample": self.min_size_to_sample,
            "error_buffer": float(self.error_buffer),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the counters; the parameters stay those of this instance (they may be retuned on resume)."""
        self.inserts = _count("inserts", state["inserts"])
        self.samples = _count("samples", state["samples"])


@dataclass
class MinSize:
    """Samples any time once ``min_size`` env steps are in; never blocks inserts (tests, benchmarks)."""

    min_size: int
    inserts: int = field(default=0, init=False)
    samples: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        self.min_size = _count("min_size", self.min_size)

    def can_sample(self, n: int = 1) -> bool:
        _count("n", n)
        return self.inserts >= self.min_size

    def can_insert(self, n: int = 1) -> bool:
        _count("n", n)
        return True

    def samples_allowed(self) -> int:
        return UNLIMITED if self.inserts >= self.min_size else 0

    def inserts_allowed(self) -> int:
        return UNLIMITED

    def sampled(self, n: int = 1) -> None:
        self.samples += _count("n", n)

    def inserted(self, n: int) -> None:
        self.inserts += _count("n", n)

    def state_dict(self) -> dict[str, Any]:
        return {"inserts": self.inserts, "samples": self.samples, "min_size": self.min_size}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.inserts = _count("inserts", state["inserts"])
        self.samples = _count("samples", state["samples"])
