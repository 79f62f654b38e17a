"""Weights distribution: the learner serves the latest blob; consumers pull only newer versions.

The learner (``WeightsServer``) encodes each version once, answers queries on WEIGHTS_LATEST and
announces the version on WEIGHTS_ANNOUNCE. A consumer (``WeightsClient``) records announcements
in the transport thread (cheap) and pulls at a safe point of its own loop (e.g. between episodes),
only when an announced version is newer than the one it holds; it also asks once at start-up, so a
late joiner catches up without waiting for the next announcement. Large blobs are never pushed.
"""

from __future__ import annotations

import logging
import threading
import time

from proto.topics import WEIGHTS_ANNOUNCE, WEIGHTS_LATEST
from proto.weights import WeightsBlob
from services.common.bus.base import Bus

log = logging.getLogger(__name__)


class WeightsServer:
    def __init__(self, bus: Bus, source: str) -> None:
        self.bus, self.source = bus, source
        self._lock = threading.Lock()
        self._version = -1
        self._payload: bytes | None = None
        self._handle = bus.serve(WEIGHTS_LATEST, self._answer, source=source)

    def _answer(self, params: dict[str, str]) -> bytes | None:
        try:
            min_version = int(params.get("min_version", "0"))
        except ValueError:
            return None
        with self._lock:
            return self._payload if self._payload is not None and self._version >= min_version else None

    def publish(self, blob: WeightsBlob, payload: bytes | None = None) -> int:
        """Make ``blob`` the latest version and announce it; returns its encoded size. ``payload``:
        ``blob.encode()`` when the caller has it already."""
        payload = blob.encode() if payload is None else payload
        with self._lock:
            if blob.version <= self._version:
                raise ValueError(f"weights version {blob.version} is not newer than {self._version}")
            self._version, self._payload = blob.version, payload
        self.bus.publish(WEIGHTS_ANNOUNCE, blob.announcement(len(payload)), source=self.source)
        return len(payload)

    @property
    def version(self) -> int:
        return self._version

    def close(self) -> None:
        self._handle.close()


class WeightsClient:
    """Pull-if-newer consumer. ``poll()`` never blocks on the network unless a newer version exists."""

    def __init__(self, bus: Bus, timeout: float = 10.0) -> None:
        self.bus = bus
        self.timeout = timeout
        self.version = -1
        self.blob: WeightsBlob | None = None
        self._announced = -1
        self._asked_once = False
        self._sub = bus.subscribe(WEIGHTS_ANNOUNCE, capacity=64)
        self.last_pull_seconds = 0.0
        self.last_announce_to_loaded_seconds = 0.0

    def poll(self) -> WeightsBlob | None:
        """Return a newer blob if one is available (and keep it), else None."""
        announced_at = None
        for d in self._sub.drain():
            if d.message.version > self._announced:
                self._announced = d.message.version
                announced_at = d.message.created_at
        if self._asked_once and self._announced <= self.version:
            return None
        self._asked_once = True
        t0 = time.monotonic()
        reply = self.bus.query(WEIGHTS_LATEST, {"min_version": str(self.version + 1)}, timeout=self.timeout)
        if reply is None:
            return None
        blob = reply.message
        if blob.version <= self.version:
            return None
        self.last_pull_seconds = time.monotonic() - t0
        if announced_at is not None:
            self.last_announce_to_loaded_seconds = max(0.0, time.time() - announced_at)
        self.version, self.blob = blob.version, blob
        self._announced = max(self._announced, blob.version)
        log.info(
            "weights loaded", extra={"version": blob.version, "pull_s": round(self.last_pull_seconds, 4)}
        )
        return blob

    def absorb_announcements(self) -> None:
        """Empty the announcement queue, remembering the newest announced version, without pulling
        (for consumers that pull rarely, e.g. only when an evaluation is due: the queue is bounded)."""
        for d in self._sub.drain():
            self._announced = max(self._announced, d.message.version)

    def close(self) -> None:
        self._sub.close()
