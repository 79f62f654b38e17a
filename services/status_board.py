"""`mea run`'s view of its services: the latest heartbeat per instance, exits and restarts, the
newest evaluation, rendered as a table and a progress line, and the run's summary.json."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from rich.table import Table

from proto.control import EvalReport, Heartbeat
from proto.topics import EVAL_REPORTS, STATUS
from services.common.bus.base import Bus
from services.plan import ChildSpec

log = logging.getLogger(__name__)


class StatusBoard:
    """Latest heartbeat per instance, liveliness and evaluation reports, rendered as a table with a
    progress line (env steps, augmented transitions, updates, weights version, success, ETA)."""

    KEY_COUNTERS = 4
    RATE_WINDOW = 120.0

    def __init__(self, specs: list[ChildSpec], budget: int = 0, bus: Bus | None = None) -> None:
        self.expected = [(s.service, s.instance) for s in specs]
        self.beats: dict[tuple[str, str], Heartbeat] = {}
        self.exits: dict[str, int] = {}
        """Instances that exited and are not running again (their counters are stale)."""
        self.restarts: dict[str, int] = {}
        self._dead_pids: set[int] = set()
        self.budget = budget
        self.report: EvalReport | None = None
        self.reports = 0
        self._steps: list[tuple[float, float]] = []  # (time, env steps) for the rate
        self.started = time.time()
        self._subs = (
            (bus.subscribe(STATUS, capacity=1024), bus.subscribe(EVAL_REPORTS, capacity=256)) if bus else None
        )

    def take(self, settle: float = 0.0) -> None:
        """Take the heartbeats and reports received so far (waiting ``settle`` s for stragglers)."""
        if self._subs is None:
            return
        if settle:
            time.sleep(settle)
        beats, reports = self._subs
        for d in beats.drain():
            self.update(d.message)
        for d in reports.drain():
            self.add_report(d.message)

    def close(self) -> None:
        for sub in self._subs or ():
            sub.close()

    def summary(self, episodes_recorded: int | None = None) -> dict:
        """What the run did, from each instance's last heartbeat: counters per instance, evaluations,
        the newest report, and the raw episodes recorded (None: not recorded)."""
        return {
            "instances": {
                inst: {
                    "service": svc,
                    "exitcode": self.exits.get(inst),
                    "restarts": self.restarts.get(inst, 0),
                    "counters": dict(self.beats[(svc, inst)].counters) if (svc, inst) in self.beats else {},
                }
                for svc, inst in self.expected
            },  # fmt: skip
            "evaluations": self.reports,
            "last_report": None
            if self.report is None
            else {
                "env_steps": self.report.env_steps,
                "success_rate": self.report.success_rate,
                "policy_version": self.report.policy_version,
            },  # fmt: skip
            "episodes_recorded": episodes_recorded,
            "elapsed_seconds": round(time.time() - self.started, 1),
        }

    def save_summary(self, path: Path, episodes_recorded: int | None = None) -> None:
        try:
            path.write_text(json.dumps(self.summary(episodes_recorded), indent=2, sort_keys=True) + "\n")
        except OSError as exc:
            log.warning("run summary not written", extra={"path": str(path), "error": str(exc)})

    def update(self, hb: Heartbeat) -> None:
        if hb.pid in self._dead_pids:  # a late heartbeat of a process that has exited
            return
        self.beats[(hb.service, hb.instance_id)] = hb

    def mark_exited(self, instance: str, exitcode: int, pid: int | None) -> None:
        """``instance`` exited: its counters are stale (kept for the table, not summed as live)."""
        self.exits[instance] = exitcode
        if pid:
            self._dead_pids.add(pid)

    def restarted(self, instance: str, restarts: int) -> None:
        self.exits.pop(instance, None)
        self.restarts[instance] = restarts
        for who in [w for w in self.beats if w[1] == instance]:
            del self.beats[who]  # the new process starts its counters afresh

    def add_report(self, r: EvalReport) -> None:
        self.reports += 1
        if self.report is None or r.policy_version >= self.report.policy_version:
            self.report = r

    def _sum(self, service: str, key: str) -> float | None:
        values = [
            hb.counters[key]
            for (svc, inst), hb in self.beats.items()
            if svc == service and key in hb.counters and inst not in self.exits
        ]
        return sum(values) if values else None

    def env_steps(self) -> float | None:
        """The learner's count of inserted env steps (else the actors' own)."""
        learner = self._sum("learner", "env_steps")
        return learner if learner is not None else self._sum("actor", "env_steps")

    def progress(self, started: float, now: float | None = None) -> dict[str, float | str | None]:
        now = time.time() if now is None else now
        steps = self.env_steps()
        eta = None
        if steps is not None:
            self._steps = [(t, v) for t, v in self._steps if now - t <= self.RATE_WINDOW] + [(now, steps)]
            (t0, v0), (t1, v1) = self._steps[0], self._steps[-1]
            if self.budget and v1 > v0 and t1 > t0:
                eta = max(0.0, (self.budget - v1) / ((v1 - v0) / (t1 - t0)))
        r = self.report
        return {
            "env_steps": steps,
            "augmented": self._sum("augmenter", "transitions_out"),
            "updates": self._sum("learner", "updates"),
            "version": self._sum("learner", "version"),
            "success": None if r is None else r.success_rate,
            "success_at": None if r is None else r.env_steps,
            "elapsed": now - started,
            "eta": eta,
        }

    def progress_line(self, started: float) -> str:
        p = self.progress(started)

        def n(v) -> str:
            return "—" if v is None else f"{v:,.0f}"

        budget = f"/{self.budget:,}" if self.budget else ""
        success = "—" if p["success"] is None else f"{p['success']:.0%} (at {n(p['success_at'])} steps)"
        eta = "—" if p["eta"] is None else f"{p['eta'] / 60:,.0f} min"
        restarts = sum(self.restarts.values())
        return (f"env steps {n(p['env_steps'])}{budget} · augmented transitions {n(p['augmented'])} · "
                f"updates {n(p['updates'])} · weights v{n(p['version'])} · success {success} · "
                f"elapsed {p['elapsed'] / 60:,.1f} min · ETA {eta}"
                + (f" · restarts {restarts}" if restarts else ""))  # fmt: skip

    def table(self, alive: set[tuple[str, str]], started: float) -> Table:
        t = Table(title=f"mea run — {time.time() - started:,.0f} s", caption=self.progress_line(started))
        for col in ("service", "instance", "alive", "state", "policy", "counters"):
            t.add_column(col)
        for who in self.expected:
            hb = self.beats.get(who)
            if who[1] in self.exits:
                state = f"exited ({self.exits[who[1]]}), stale"
            else:
                state = hb.state if hb else "starting"
            if self.restarts.get(who[1]):
                state += f", restarts {self.restarts[who[1]]}"
            counters = ""
            if hb:
                counters = "  ".join(
                    f"{k}={v:,.3g}" if abs(v) < 10 else f"{k}={v:,.0f}"
                    for k, v in list(hb.counters.items())[: self.KEY_COUNTERS]
                )
            t.add_row(
                who[0],
                who[1],
                "yes" if who in alive else "no",
                state,
                str(hb.policy_version) if hb else "—",
                counters,
            )
        return t
