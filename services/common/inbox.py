"""Items received but not yet handled: a FIFO bounded by bytes, between the thread that reads a
subscription and the thread that handles what it read (the learner's inserts into its replay, the
launcher's recording).

Why: a thread that reads a subscription and then waits (on the replay's lock during a checkpoint, on
a slow disk) lets the subscription fill, and Zenoh's reader waits with it; a reader that waits past
Zenoh's lease (about 10 s) has its transport closed and what it held is lost (docs/results.md). With
the inbox the reading thread keeps reading while the handling thread waits. Past ``max_bytes`` the
reading thread waits too (backpressure, as without the inbox)."""

from __future__ import annotations

import threading
from collections import deque
from typing import TYPE_CHECKING, Generic, TypeVar

if TYPE_CHECKING:
    from services.common.bus.base import Delivery, Subscription

T = TypeVar("T")


class Inbox(Generic[T]):
    """Thread-safe FIFO of items with a size in bytes, holding at most ``max_bytes`` (one item larger
    than that is still taken when the inbox is empty, so that nothing can wait forever)."""

    def __init__(self, max_bytes: int) -> None:
        if max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        self.max_bytes = max_bytes
        self._items: deque[tuple[T, int]] = deque()
        self._bytes = 0
        self._cond = threading.Condition()
        self.peak_bytes = 0
        """The most bytes held at once since the start."""

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    @property
    def nbytes(self) -> int:
        with self._cond:
            return self._bytes

    def put(self, item: T, size: int, timeout: float | None = None) -> bool:
        """Append ``item`` (``size`` bytes), waiting up to ``timeout`` s (None: for ever) while it would
        not fit; False if it still does not."""
        if size < 0:
            raise ValueError(f"size must be >= 0, got {size}")
        with self._cond:
            fits = self._cond.wait_for(
                lambda: not self._items or self._bytes + size <= self.max_bytes, timeout
            )
            if not fits:
                return False
            self._items.append((item, size))
            self._bytes += size
            self.peak_bytes = max(self.peak_bytes, self._bytes)
            self._cond.notify_all()
            return True

    def get(self, timeout: float | None = None) -> T | None:
        """The oldest item, waiting up to ``timeout`` s (None: for ever) for one; None if none came."""
        with self._cond:
            if not self._cond.wait_for(lambda: bool(self._items), timeout):
                return None
            item, size = self._items.popleft()
            self._bytes -= size
            self._cond.notify_all()
            return item


def receive_into(
    sub: Subscription, inbox: Inbox[Delivery], stop: threading.Event, poll_s: float = 0.1
) -> None:
    """Read ``sub`` into ``inbox`` until ``stop`` is set (a receiving thread's body). A delivery that
    does not fit waits until it does or ``stop`` comes; one left then is not taken, and its sender,
    unacknowledged, sends it again."""
    while not stop.is_set():
        d = sub.recv(timeout=poll_s)
        while d is not None and not inbox.put(d, d.size, timeout=0.1):
            if stop.is_set():
                return


__all__ = ["Inbox", "receive_into"]
