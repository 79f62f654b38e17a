"""The learner's latest ``ReplayGate`` as seen by a consumer (actors follow it, the evaluator reads
the learner's env steps from it)."""

from __future__ import annotations

import time
from collections.abc import Callable

from proto.control import ReplayGate
from proto.topics import REPLAY_GATE
from services.common.bus.base import Bus, Subscription

MAX_CLOCK_SKEW = 5.0
"""Seconds a gate may be dated ahead of this host's clock (hosts' clocks differ a little)."""


class GateTracker:
    """Keeps the newest ``ReplayGate`` (by ``created_at``) from a subscription; ``update`` drains the
    bounded queue without blocking (unless asked to wait for a first gate)."""

    def __init__(self, sub: Subscription) -> None:
        self.sub = sub
        self.latest: ReplayGate | None = None
        self.seen_at = 0.0
        """``time.monotonic()`` when the latest gate was taken (0: none yet)."""
        self.future_dated = 0
        """Gates ignored because they were dated more than ``MAX_CLOCK_SKEW`` s ahead of this clock."""

    def _take(self, gate: ReplayGate) -> None:
        if gate.created_at > time.time() + MAX_CLOCK_SKEW:
            self.future_dated += 1  # it would shadow every real gate after it
            return
        if self.latest is None or gate.created_at >= self.latest.created_at:
            self.latest, self.seen_at = gate, time.monotonic()

    def update(self, first_wait: float = 0.0) -> ReplayGate | None:
        """Take every queued gate; with none known yet, wait up to ``first_wait`` s for one."""
        if self.latest is None and first_wait > 0:
            d = self.sub.recv(timeout=first_wait)
            if d is not None:
                self._take(d.message)
        for d in self.sub.drain():
            self._take(d.message)
        return self.latest

    @property
    def env_steps(self) -> int:
        """The learner's inserted env steps (-1: no gate seen)."""
        return -1 if self.latest is None else int(self.latest.inserted_steps)


class GateFollower:
    """Waits while the learner's latest ``ReplayGate`` says its allowance is used up."""

    def __init__(self, bus: Bus, stale_after: float, first_wait: float = 1.5) -> None:
        self.tracker = GateTracker(bus.subscribe(REPLAY_GATE, capacity=16))
        self.stale_after, self.first_wait = stale_after, first_wait
        self._first = True

    def blocked(self) -> bool:
        # before the first episode, give a running learner's gate (every ~0.5 s) a chance to arrive
        gate = self.tracker.update(self.first_wait if self._first else 0.0)
        self._first = False
        if gate is None or time.monotonic() - self.tracker.seen_at > self.stale_after:
            return False
        return gate.inserted_steps >= gate.allowed_steps

    def wait(self, stop, while_waiting: Callable[[], None] | None = None) -> float:
        """Wait until the gate opens (or goes stale, or ``stop`` is set), calling ``while_waiting``
        about every 0.05 s; returns seconds waited."""
        t0 = time.monotonic()
        while self.blocked() and not stop.wait(0.05):
            if while_waiting is not None:
                while_waiting()
        return time.monotonic() - t0

    def close(self) -> None:
        self.tracker.sub.close()
