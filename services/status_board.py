"""`mea run`'s view of its services: the latest heartbeat per instance, exits and restarts, the
newest evaluation, rendered as a table and a progress line; the run's summary.json (one entry per
sitting, a resume being a new sitting, and their totals) and the summary printed when a run ends."""

from __future__ import annotations

import json
import logging
import math
import shlex
import time
from pathlib import Path
from statistics import NormalDist

from rich.table import Table

from proto.control import EvalReport, Heartbeat
from proto.topics import EVAL_REPORTS, STATUS
from services.common import run_key, weights_file
from services.common.bus.base import Bus
from services.evaluator.history import HISTORY, read_history
from services.plan import ChildSpec

log = logging.getLogger(__name__)

SUMMARY = "summary.json"
"""The run's summary, in its directory."""


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
            "env_steps": self.env_steps(),
            "updates": self._sum("learner", "updates"),
        }

    def save_summary(self, path: Path, episodes_recorded: int | None = None, sitting: int = 0) -> dict:
        """Write summary.json: this sitting's summary (``sitting``: the run's resume count) at the top
        level, every sitting's in ``sittings`` (the earlier ones from the file there) and their
        ``total``; returns what was written."""
        this = {**self.summary(episodes_recorded), "sitting": sitting}
        sittings = [s for s in earlier_sittings(path, sitting) if s.get("sitting") != sitting] + [this]
        out = {**this, "sittings": sittings, "total": totals(sittings)}
        try:
            path.write_text(json.dumps(out, indent=2, sort_keys=True) + "\n")
        except OSError as exc:
            log.warning("run summary not written", extra={"path": str(path), "error": str(exc)})
        return out

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


def earlier_sittings(path: Path, sitting: int) -> list[dict]:
    """The sittings a summary.json holds (one written before sittings were kept counts as the one
    before ``sitting``); [] without a readable one."""
    try:
        saved = json.loads(path.read_text())
    except FileNotFoundError:
        return []
    except (OSError, ValueError) as exc:
        log.warning(
            "earlier run summary unreadable; not carried on", extra={"path": str(path), "error": str(exc)}
        )
        return []
    if not isinstance(saved, dict):
        return []
    if isinstance(saved.get("sittings"), list):
        return [s for s in saved["sittings"] if isinstance(s, dict)]
    return [{**saved, "sitting": sitting - 1}]


def totals(sittings: list[dict]) -> dict:
    """Over every sitting: wall time, evaluations and episodes recorded add up; env steps and updates
    are the learner's own running counts (restored on resume), so the newest known one stands."""

    def add(key: str) -> float | None:
        known = [s[key] for s in sittings if isinstance(s.get(key), (int, float))]
        return sum(known) if known else None

    def newest(key: str) -> float | None:
        known = [s[key] for s in sittings if isinstance(s.get(key), (int, float))]
        return known[-1] if known else None

    elapsed = add("elapsed_seconds")
    return {"sittings": len(sittings), "elapsed_seconds": None if elapsed is None else round(elapsed, 1),
            "evaluations": add("evaluations"), "episodes_recorded": add("episodes_recorded"),
            "env_steps": newest("env_steps"), "updates": newest("updates")}  # fmt: skip


def reached_env_steps(run_dir: Path) -> int:
    """The env steps the run's learner had reached when its last sitting ended (summary.json's total;
    an older summary: its learner's counters), or its eval history's newest; 0 if neither says."""
    steps = [r["env_steps"] for r in read_run_history(run_dir) if isinstance(r.get("env_steps"), int)]
    try:
        saved = json.loads((run_dir / SUMMARY).read_text())
    except (OSError, ValueError):
        saved = None
    if isinstance(saved, dict):
        total = saved.get("total") if isinstance(saved.get("total"), dict) else {}
        instances = saved.get("instances") if isinstance(saved.get("instances"), dict) else {}
        learners = [i.get("counters") or {} for i in instances.values()
                    if isinstance(i, dict) and i.get("service") == "learner"]  # fmt: skip
        steps += [v for v in (total.get("env_steps"), *(c.get("env_steps") for c in learners))
                  if isinstance(v, (int, float))]  # fmt: skip
    return int(max(steps, default=0))


def read_run_history(run_dir: Path) -> list[dict]:
    """The run's eval history records ([] without one)."""
    try:
        return read_history(run_dir / HISTORY)
    except FileNotFoundError:
        return []


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """The Wilson score interval of a success rate from ``successes`` of ``n`` episodes: it stays
    inside [0, 1] and is not empty at 0 % or 100 %, where the normal approximation fails."""
    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n and n >= 1, got {successes} of {n}")
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    p, z2 = successes / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def _successes(record: dict) -> tuple[int, int] | None:
    """(successes, episodes) of an eval history record; None if it does not say."""
    flags = record.get("successes")
    if isinstance(flags, list) and flags:
        return sum(bool(f) for f in flags), len(flags)
    n, rate = record.get("episodes"), record.get("success_rate")
    if isinstance(n, int) and n > 0 and isinstance(rate, (int, float)):
        return round(rate * n), n
    return None


def _n(v: object) -> str:
    return "—" if not isinstance(v, (int, float)) else f"{v:,.0f}"


def end_of_run(run_dir: Path, summary: dict, reason: str, authenticated: bool = True) -> str:
    """What a run achieved, printed when it ends: the final evaluation's success with its 95 % CI
    (Wilson) over its episodes, the best evaluation, env steps, updates, wall time, where the curves,
    the recording and the weights are, and the command that serves the policy."""
    records = [r for r in read_run_history(run_dir) if _successes(r) is not None]
    total = summary.get("total") or {}
    lines = [f"mea run: stopped ({reason or 'stopped'}). Summary of {run_dir}:"]
    if records:
        final = next((r for r in reversed(records) if r.get("at_budget")), records[-1])
        k, n = _successes(final)  # type: ignore[misc]
        lo, hi = wilson_interval(k, n)
        label = "final success" if final.get("at_budget") else "newest success"
        lines.append(f"  {label:<15} {k / n:.0%} ({k} of {n} episodes at {_n(final.get('env_steps'))} env steps, "
                     f"weights v{_n(final.get('version'))}); 95% CI {lo:.0%}-{hi:.0%} (Wilson)")  # fmt: skip
        best = max(records, key=lambda r: r.get("success_rate", -1.0))
        bk, bn = _successes(best)  # type: ignore[misc]
        lines.append(f"  {'best evaluation':<15} {bk / bn:.0%} ({bk} of {bn}) at {_n(best.get('env_steps'))} env "
                     f"steps, weights v{_n(best.get('version'))} ({len(records)} evaluations)")  # fmt: skip
    else:
        lines.append(f"  {'evaluations':<15} none")
    minutes = (summary.get("elapsed_seconds") or 0) / 60
    wall = f"{minutes:,.1f} min"
    if (total.get("sittings") or 1) > 1:
        wall += f" (this sitting; {(total.get('elapsed_seconds') or 0) / 60:,.1f} min over {total['sittings']} sittings)"
    lines.append(f"  {'env steps':<15} {_n(total.get('env_steps', summary.get('env_steps')))} · updates "
                 f"{_n(total.get('updates', summary.get('updates')))} · wall time {wall}")  # fmt: skip
    curves = run_dir / "curves.png"
    lines.append(f"  {'curves':<15} {curves if curves.exists() else 'none (no evaluation to draw)'}")
    segments = sorted((run_dir / "episodes").glob("*.mcap"))
    size = sum(p.stat().st_size for p in segments) / 2**20
    recording = (
        f"{run_dir / 'episodes'} ({len(segments)} file{'s' * (len(segments) != 1)}, {size:,.1f} MiB)"
        if segments
        else "none"
    )
    lines.append(f"  {'recording':<15} {recording}")
    found = weights_file.versions(run_dir / weights_file.LEARNER)
    weights = f"{found[-1][1]} (newest of {len(found)})" if found else "none written"
    lines.append(f"  {'weights':<15} {weights}")
    serve = f"mea serve --weights {shlex.quote(str(run_dir))}"
    if authenticated:
        serve += f" --service.run-key-file {shlex.quote(str(run_dir / run_key.FILE_NAME))}"
    lines.append(f"  {'serve it':<15} {serve}" if found else f"  {'serve it':<15} (no weights yet)")
    return "\n".join(lines)
