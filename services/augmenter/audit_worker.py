"""The augmenter's background physics audit (``--audit-fraction f``).

A background thread replays a fraction f of the MEA copies through the simulator with
``services.augmenter.audit_physics.audit_episode`` (imported lazily, in that thread: it pulls in
pybullet) and exports the fraction of audited transitions found valid
(``mea_augmenter_audit_valid_ratio``). Copies are chosen by a stable hash of their id. The audit
sees the MEA copy before the shared isometric rotation (regenerated from its recorded seed),
because a rotated scene has no simulated counterpart. Its queue is bounded and a copy that finds
it full is not audited (counted), so the audit never slows augmentation.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import zlib
from collections.abc import Callable, Sequence

import numpy as np

from proto.episode import Episode
from services.augmenter.core.mea_discrete import DISCRETE_MEA_TASKS
from services.augmenter.core.pipeline import AugmentSettings, mea_copy
from services.augmenter.core.routing import MEA_KINDS
from services.augmenter.metrics import auditor_metrics
from services.common.metrics import ServiceMetrics

log = logging.getLogger(__name__)

AuditFn = Callable[[Episode, Episode], np.ndarray]
"""``audit(copy, source) -> (T,) bool``: which transitions of the MEA copy the physics reproduces."""


class PhysicsAudit:
    """The default audit: ``services.augmenter.audit_physics.audit_episode`` in one env per (task, points)
    (``surgical_grasp_any``: ``services.augmenter.audit_surgical.audit_surgical``).

    Everything is imported and built lazily, on the audit thread, at the first copy audited."""

    def __init__(self) -> None:
        self._audit = None
        self._envs: dict = {}

    def __call__(self, copy: Episode, source: Episode) -> np.ndarray:
        if copy.task in DISCRETE_MEA_TASKS:  # Surgical Grasp Any: its own replay of each transition
            from services.augmenter.audit_surgical import audit_surgical  # pulls in pybullet

            env = self._env(copy)
            return np.asarray(
                audit_surgical(env, copy, source, copy.augmentation.phase_split).valid, dtype=bool
            )
        if self._audit is None:
            from services.augmenter.audit_physics import audit_episode  # pulls in pybullet

            self._audit = audit_episode
        return np.asarray(self._audit(self._env(copy), copy, source).valid, dtype=bool)

    def _env(self, copy: Episode):
        key = (copy.task, int(copy.points.shape[2]))
        env = self._envs.get(key)
        if env is None:
            from services.tasks import EnvSettings, make_env  # deferred: pybullet, on the audit thread
            from services.tasks.camera import CameraSettings

            env = make_env(copy.task, EnvSettings(camera=CameraSettings(points_per_segment=key[1])))
            self._envs[key] = env
        return env

    def close(self) -> None:
        for env in self._envs.values():
            with contextlib.suppress(Exception):
                env.close()
        self._envs.clear()


class Auditor:
    """Replays a stable-hash-chosen fraction of MEA copies through ``audit`` on a background thread.

    ``audit(copy, source)`` returns the (T,) validity of the copy's transitions; the default is
    :class:`PhysicsAudit`. Tests inject a stub here. The valid fraction (valid / audited
    transitions, cumulative) is exported as ``mea_augmenter_audit_valid_ratio`` (NaN before the
    first audit). If the audit cannot be imported or raises, that copy counts as an error.
    """

    def __init__(
        self,
        fraction: float,
        settings: AugmentSettings,
        metrics: ServiceMetrics,
        audit: AuditFn | None = None,
        capacity: int = 4,
    ) -> None:
        self.fraction = fraction
        self.settings = settings
        self._audit = audit
        self._q: queue.Queue = queue.Queue(maxsize=capacity)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.copies = self.errors = self.skipped = self.valid = self.transitions = 0
        self._mx = auditor_metrics(metrics)

    @property
    def enabled(self) -> bool:
        return self.fraction > 0.0

    @property
    def valid_fraction(self) -> float:
        return self.valid / self.transitions if self.transitions else math.nan

    def chosen(self, episode_id: str) -> bool:
        """Stable choice of ``fraction`` of the copies (same ids, same choice, in every process)."""
        return zlib.crc32(episode_id.encode()) < self.fraction * 2**32

    def start(self) -> Auditor:
        if self.enabled and self._thread is None:
            self._thread = threading.Thread(target=self._work, name="audit", daemon=True)
            self._thread.start()
        return self

    def offer(self, source: Episode, outputs: Sequence[Episode]) -> int:
        """Queue the chosen MEA copies among ``outputs`` (never blocks); returns how many were queued."""
        if not self.enabled:
            return 0
        queued = 0
        for ep in outputs:
            aug = ep.augmentation
            if aug is None or aug.kind not in MEA_KINDS or not self.chosen(ep.episode_id):
                continue
            try:
                self._q.put_nowait((source, ep))
                queued += 1
            except queue.Full:
                self.skipped += 1
                self._mx["skipped"].inc()
        return queued

    def unrotated(self, source: Episode, copy: Episode) -> Episode | None:
        """The MEA copy as the physics sees it: regenerated from its seed when it was also rotated."""
        aug = copy.augmentation
        if aug.kind == "mea":
            return copy
        again, _ = mea_copy(source, self.settings.mea, aug.seed, aug.copy_index, episode_id=copy.episode_id)
        return again

    def _work(self) -> None:
        audit = self._audit
        try:
            while not self._stop.is_set():
                try:
                    source, copy = self._q.get(timeout=0.2)
                except queue.Empty:
                    continue
                try:
                    if audit is None:
                        audit = self._audit = PhysicsAudit()
                    self._audit_one(audit, source, copy)
                finally:
                    self._q.task_done()
        finally:
            if isinstance(audit, PhysicsAudit):
                audit.close()

    def _audit_one(self, audit: AuditFn, source: Episode, copy: Episode) -> None:
        try:
            target = self.unrotated(source, copy)
            valid = np.asarray(audit(target, source), dtype=bool) if target is not None else None
        except Exception:  # noqa: BLE001 - a failing audit must not take the augmenter down
            log.exception("audit failed", extra={"episode_id": copy.episode_id})
            self.errors += 1
            self._mx["copies"].labels("error").inc()
            return
        if valid is None:
            return
        n, ok = int(valid.size), int(valid.sum())
        self.copies += 1
        self.valid += ok
        self.transitions += n
        self._mx["copies"].labels("done").inc()
        self._mx["transitions"].labels("valid").inc(ok)
        self._mx["transitions"].labels("invalid").inc(n - ok)
        if self.transitions:
            self._mx["valid_ratio"].set(self.valid_fraction)

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every queued copy was audited (bounded); True if the queue emptied."""
        if self._thread is None:
            return True
        with self._q.all_tasks_done:  # queue.Queue.join, with a timeout
            return self._q.all_tasks_done.wait_for(lambda: not self._q.unfinished_tasks, timeout)

    def close(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None


__all__ = ["AuditFn", "Auditor", "PhysicsAudit"]
