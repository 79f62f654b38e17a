"""When `mea run` restarts a service that exited on its own, and when it gives up: pure arithmetic
over crash times, kept apart from processes so it can be tested like math."""

from __future__ import annotations

from collections import defaultdict, deque
from dataclasses import dataclass


@dataclass(frozen=True)
class RestartSettings:
    """Restart with exponential backoff; give up on an instance after ``limit`` restarts within
    ``window_seconds`` (0: never restart)."""

    limit: int = 3
    window_seconds: float = 600.0
    first_delay: float = 1.0
    max_delay: float = 30.0

    def __post_init__(self) -> None:
        if self.limit < 0 or self.window_seconds <= 0 or not 0 < self.first_delay <= self.max_delay:
            raise ValueError("need limit >= 0, window_seconds > 0 and 0 < first_delay <= max_delay")


class RestartPolicy:
    """Per instance: each exit within the window counts; the n-th restart waits first_delay * 2^(n-1)
    seconds (capped); an exit that would be restart number limit + 1 within the window is final."""

    def __init__(self, settings: RestartSettings) -> None:
        self.settings = settings
        self._exits: dict[str, deque[float]] = defaultdict(deque)
        self.restarts: dict[str, int] = defaultdict(int)
        """Restarts so far, by instance (all of the run, not only the window)."""

    def on_exit(self, instance: str, now: float) -> float | None:
        """Seconds to wait before restarting ``instance``, which exited at ``now``; None: give up."""
        s, exits = self.settings, self._exits[instance]
        exits.append(now)
        while exits and now - exits[0] > s.window_seconds:
            exits.popleft()
        if len(exits) > s.limit:
            return None
        self.restarts[instance] += 1
        return min(s.first_delay * 2 ** (len(exits) - 1), s.max_delay)
