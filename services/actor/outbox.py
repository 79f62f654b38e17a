"""Published episodes an actor keeps until the learner acknowledges them (pure: no transport).

An episode published while the augmenter or the learner is down (or in one of them when it is
killed) never reaches replay. The actor therefore keeps each episode until an ``EpisodeAck`` names
it, and publishes it again when a consumer (re)starts or when no ack came for ``resend_after``
seconds; the learner stores an id once, so a repeat costs work, never a duplicate.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass
class _Pending(Generic[T]):
    item: T
    sent_at: float
    sends: int = 1


class Outbox(Generic[T]):
    def __init__(self, capacity: int, resend_after: float) -> None:
        if capacity < 1 or resend_after <= 0:
            raise ValueError("capacity must be >= 1 and resend_after > 0")
        self.capacity, self.resend_after = capacity, resend_after
        self._pending: OrderedDict[str, _Pending[T]] = OrderedDict()  # oldest first
        self.acked = 0
        self.resent = 0
        self.evicted = 0

    def __len__(self) -> int:
        return len(self._pending)

    def __contains__(self, episode_id: str) -> bool:
        return episode_id in self._pending

    @property
    def full(self) -> bool:
        return len(self._pending) >= self.capacity

    def sent(self, episode_id: str, item: T, now: float) -> None:
        """``item`` was published; keep it until acknowledged. When full (nobody acknowledges,
        e.g. a run without a learner), the oldest is let go and counted."""
        if episode_id in self._pending:
            self._pending[episode_id].sent_at = now
            return
        while self.full:
            self._pending.popitem(last=False)
            self.evicted += 1
        self._pending[episode_id] = _Pending(item, now)

    def ack(self, episode_ids: list[str]) -> int:
        """Forget every episode named; returns how many were pending."""
        n = 0
        for eid in episode_ids:
            if self._pending.pop(eid, None) is not None:
                n += 1
        self.acked += n
        return n

    def due(self, now: float, consumer_restarted_at: float | None = None) -> list[tuple[str, T]]:
        """Episodes to publish again, oldest first: sent before a consumer (re)started at
        ``consumer_restarted_at``, or unacknowledged for ``resend_after`` s. Each is marked sent now."""
        out = []
        for eid, p in self._pending.items():
            restarted = consumer_restarted_at is not None and p.sent_at <= consumer_restarted_at
            if restarted or now - p.sent_at >= self.resend_after:
                p.sent_at, p.sends = now, p.sends + 1
                out.append((eid, p.item))
        self.resent += len(out)
        return out
