"""`mea bench soak`: run `mea run` for an hour and watch every service's memory.

The RSS of every service, sampled from /proc over the run: growth after warm-up must stay under 5%.

Design notes: docs/architecture-notes.md, mea_tools/bench/soak.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mea_tools.bench.harness import free_port
from mea_tools.bench.report import emit
from mea_tools.bench.system import connect_to_run, stop_run
from proto.topics import STATUS

ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class SoakBenchConfig:
    """RSS of every service of a long `mea run`, before and after warm-up."""

    minutes: float = 60.0
    """How long the stack runs."""
    warmup_minutes: float = 10.0
    """Growth is measured from the end of this (start-up, demos, first replay fill)."""
    sample_seconds: float = 10.0
    """RSS sampling period."""
    run_dir: Path = Path("runs/bench-soak")
    run_args: tuple[str, ...] = ("--task", "block_pull", "--demos", "2", "--env-steps", "0")
    """Further `mea run` flags (default: `make run`'s stack, stopped by time rather than a budget)."""
    limit_percent: float = 5.0
    """Allowed RSS growth after warm-up."""
    window_minutes: float = 5.0
    """RSS after warm-up and at the end are medians over this long (single samples catch transients)."""
    samples: Path | None = None
    """Tabulate a finished soak's RUN_DIR/soak-rss.json again instead of running one."""
    json: bool = False
    """Print exactly one JSON object instead of tables."""


def _log(msg: str) -> None:
    print(f"[bench soak] {msg}", file=sys.stderr, flush=True)


def rss_bytes(pid: int) -> int | None:
    """Resident set size of ``pid`` from /proc (None once it has exited)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


@dataclass
class Series:
    """RSS samples of one process: (seconds since start, bytes, replay bytes filled or 0)."""

    name: str
    pid: int
    samples: list[tuple[float, int, float]]

    def at_or_after(self, t: float) -> tuple[float, int, float] | None:
        return next((s for s in self.samples if s[0] >= t), None)


def _median_in(
    samples: list[tuple[float, int, float]], lo: float, hi: float
) -> tuple[float, float, float] | None:
    inside = [x for x in samples if lo <= x[0] <= hi]
    if not inside:
        return None
    return (inside[0][0], float(np.median([x[1] for x in inside])), float(np.median([x[2] for x in inside])))


def growth_rows(
    series: list[Series], warmup: float, limit: float, window: float = 300.0
) -> list[dict[str, Any]]:
    """Per series: median RSS over the ``window`` s after the warm-up against the median over the
    last ``window`` s (single samples catch transients: an episode being augmented, a checkpoint)."""
    rows = []
    for s in series:
        end = s.samples[-1][0] if s.samples else 0.0
        first = _median_in(s.samples, warmup, warmup + window)
        last = _median_in(s.samples, end - window, end)
        if first is None or last is None or end - window <= warmup:
            rows.append({"instance": s.name, "pid": s.pid, "RSS after warm-up MB": None, "RSS at end MB": None,
                         "growth %": None, "replay filled MB": None, "growth net of replay %": None,
                         "minutes measured": 0.0, "ok": None})  # fmt: skip  # exited during warm-up
            continue
        grow = 100.0 * (last[1] - first[1]) / first[1]
        net = 100.0 * (last[1] - first[1] - (last[2] - first[2])) / first[1]
        rows.append({"instance": s.name, "pid": s.pid, "RSS after warm-up MB": first[1] / 1e6,
                     "RSS at end MB": last[1] / 1e6, "growth %": grow,
                     "replay filled MB": (last[2] - first[2]) / 1e6, "growth net of replay %": net,
                     "minutes measured": (end - warmup) / 60, "ok": net < limit})  # fmt: skip
    return rows


def from_samples(path: Path) -> list[Series]:
    """The series a run saved (RUN_DIR/soak-rss.json), to tabulate again."""
    data = json.loads(Path(path).read_text())
    return [Series(name.rsplit("@", 1)[0], int(name.rsplit("@", 1)[1]), [tuple(x) for x in v])
            for name, v in data.items()]  # fmt: skip


def run(cfg: SoakBenchConfig) -> dict:
    if cfg.samples is not None:
        rows = growth_rows(
            from_samples(cfg.samples), cfg.warmup_minutes * 60, cfg.limit_percent, cfg.window_minutes * 60
        )
        meta = {
            "samples": str(cfg.samples),
            "warmup_minutes": cfg.warmup_minutes,
            "window_minutes": cfg.window_minutes,
        }
        return emit("soak", {"RSS growth after warm-up": rows}, measured={}, as_json=cfg.json, meta=meta)
    port = free_port()
    stack_dir = cfg.run_dir / f"stack-{int(time.time())}"  # a fresh run dir each soak: mea run reuses none
    cmd = [sys.executable, "-m", "services.cli", "run", *cfg.run_args, "--run-dir", str(stack_dir),
           "--listen", f"tcp/127.0.0.1:{port}", "--duration-seconds", str(cfg.minutes * 60),
           "--log-format", "json"]  # fmt: skip
    _log(" ".join(cmd[2:]))
    cfg.run_dir.mkdir(parents=True, exist_ok=True)
    log = open(cfg.run_dir / "soak-stack.log", "w")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip
    series: dict[int, Series] = {proc.pid: Series("launcher", proc.pid, [])}
    replay_filled: dict[int, float] = {}
    t0 = time.monotonic()
    bus = None
    try:
        bus = connect_to_run(port, proc)
        status = bus.subscribe(STATUS, capacity=4096)
        next_sample = 0.0
        while proc.poll() is None:
            for d in status.drain():
                hb = d.message
                if hb.pid not in series:
                    series[hb.pid] = Series(f"{hb.service}/{hb.instance_id}", hb.pid, [])
                if hb.service == "learner":
                    replay_filled[hb.pid] = float(hb.counters.get("replay_bytes_filled", 0.0))
            now = time.monotonic() - t0
            if now >= next_sample and now < cfg.minutes * 60 - 5:  # not the shutdown (final checkpoint)
                for pid, s in series.items():
                    rss = rss_bytes(pid)
                    if rss is not None:
                        s.samples.append((now, rss, replay_filled.get(pid, 0.0)))
                next_sample = now + cfg.sample_seconds
                if int(now) % 300 < cfg.sample_seconds:
                    _log(f"{now / 60:.0f} min: " + ", ".join(f"{s.name} {s.samples[-1][1] / 1e6:.0f} MB"
                                                          for s in series.values() if s.samples))  # fmt: skip
            time.sleep(0.5)
    finally:
        if bus is not None:
            bus.close()
        stop_run(proc, 120.0)
        log.close()
    rows = growth_rows(
        list(series.values()), cfg.warmup_minutes * 60, cfg.limit_percent, cfg.window_minutes * 60
    )
    (cfg.run_dir / "soak-rss.json").write_text(json.dumps(
        {s.name + f"@{s.pid}": s.samples for s in series.values()}) + "\n")  # fmt: skip
    meta = {"minutes": round((time.monotonic() - t0) / 60, 1), "warmup_minutes": cfg.warmup_minutes,
            "stack": " ".join(cfg.run_args), "exit code": proc.returncode, "run_dir": str(cfg.run_dir),
            "limit %": cfg.limit_percent}  # fmt: skip
    return emit("soak", {"RSS growth after warm-up": rows}, measured={}, as_json=cfg.json, meta=meta)
