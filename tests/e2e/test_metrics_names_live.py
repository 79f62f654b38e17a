"""The metric names the Grafana dashboards and the Prometheus rules query exist: a small real stack on
127.0.0.1 (`mea run` of Block Pull, plus `mea serve` following its learner and `mea robot --sim`
driving through it, both Zenoh clients of the run's router sealed with its key) is scraped on every
documented /metrics port (launcher BASE, learner +1, augmenter +2, evaluator +3, actor 0 +10, the
server's and the robot's own), and every name used by deploy/grafana/dashboards/*.json and every
`mea_*` name in deploy/prometheus/rules/*.yml is exported by some process.

Names come from the exposition's `# TYPE` lines (a collector is listed there from its registration,
before it has any sample): a histogram NAME exports NAME_bucket, NAME_sum and NAME_count, a counter
NAME exports NAME_total; sample lines add what they name."""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
import yaml

from deploy.grafana import dashboards as gen
from tests.helpers import find_free_port, find_free_port_base

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
OFFSETS = {"launcher": 0, "learner": 1, "augmenter": 2, "evaluator": 3, "actor-0": 10}
"""`mea run --metrics-port BASE` layout (README "Metrics endpoints")."""
SCRAPE_SECONDS = 110
"""How long to keep scraping for the names still missing (start-up of five processes on two cores)."""


def dashboard_names() -> set[str]:
    names: set[str] = set()
    for path in sorted((ROOT / "deploy" / "grafana" / "dashboards").glob("*.json")):
        for expr in gen.expressions(json.loads(path.read_text())):
            names |= gen.metric_names(expr)
    return names


def rule_names() -> set[str]:
    """The `mea_*` names the Prometheus rules read (not those they record). The rules directory is
    another part of the deployment; while it does not exist there is nothing to check here, and only
    the dashboards' names are checked."""
    used, recorded = set(), set()
    for path in sorted((ROOT / "deploy" / "prometheus" / "rules").glob("*.y*ml")):
        for group in (yaml.safe_load(path.read_text()) or {}).get("groups", []):
            for rule in group.get("rules", []):
                used |= gen.metric_names(str(rule["expr"]))
                if "record" in rule:
                    recorded.add(rule["record"])
    return {n for n in used - recorded if n.startswith("mea_")}


def exported_names(text: str) -> set[str]:
    """Metric names in a Prometheus text exposition."""
    names: set[str] = set()
    for line in text.splitlines():
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split(maxsplit=3)
            names.add(name)
            if kind == "histogram":
                names |= {f"{name}_bucket", f"{name}_sum", f"{name}_count"}
            elif kind == "summary":
                names |= {f"{name}_sum", f"{name}_count"}
            elif kind == "counter" and not name.endswith("_total"):
                names.add(f"{name}_total")
        elif line and not line.startswith("#"):
            m = re.match(r"[a-zA-Z_:][\w:]*", line)
            if m:
                names.add(m.group())
    return names


def _scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=3) as r:
        return r.read().decode()


def _start(args: list[str], log: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    with log.open("w") as out:  # the child keeps its own copy of the descriptor
        return subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=ROOT, env=env, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip


def _stop(procs: list[subprocess.Popen], grace: float = 25.0) -> None:
    """SIGTERM to each, then SIGKILL to each one's process group (its children too) if still there."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace
    for p in procs:
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(p.pid, signal.SIGKILL)  # what is left of its group (the launcher's children)
        p.wait(timeout=10)


def _tail(path: Path, n: int = 3000) -> str:
    return path.read_text(errors="replace")[-n:] if path.exists() else ""


def test_the_promql_reader_and_the_exposition_reader():
    assert exported_names("# TYPE a_seconds histogram\n# TYPE b counter\n# TYPE c gauge\nd_total 1\n") == {
        "a_seconds", "a_seconds_bucket", "a_seconds_sum", "a_seconds_count", "b", "b_total", "c", "d_total"}  # fmt: skip
    assert "mea_service_info" in dashboard_names() and "process_resident_memory_bytes" in dashboard_names()


@pytest.mark.timeout(170)
def test_every_dashboard_and_rule_metric_is_exported_by_a_live_stack(tmp_path):
    required = dashboard_names() | rule_names()
    router, serve_port, robot_port = find_free_port(), find_free_port(), find_free_port()
    base = find_free_port_base(tuple(OFFSETS.values()), {router, serve_port, robot_port})
    namespace = f"grafana-{secrets.token_hex(4)}"
    run_dir = tmp_path / "run"
    endpoint = f"tcp/127.0.0.1:{router}"
    logs = {name: tmp_path / f"{name}.log" for name in ("run", "serve", "robot")}
    targets = {name: base + o for name, o in OFFSETS.items()} | {"inference": serve_port, "robot": robot_port}
    procs: list[subprocess.Popen] = []
    try:
        run = _start(["run", "--task", "block_pull", "--demos", "1", "--env-steps", "600", "--learner-preset", "smoke",
                      "--metrics-port", str(base), "--listen", endpoint, "--namespace", namespace,
                      "--run-dir", str(run_dir), "--log-format", "text"], logs["run"])  # fmt: skip
        procs.append(run)
        deadline = time.monotonic() + 60
        while not (run_dir / "run.key").exists():
            assert run.poll() is None and time.monotonic() < deadline, _tail(logs["run"])
            time.sleep(0.2)
        common = ["--service.zenoh.mode", "client", "--service.zenoh.connect", endpoint,
                  "--service.zenoh.namespace", namespace, "--service.run-key-file", str(run_dir / "run.key"),
                  "--service.log-format", "text"]  # fmt: skip
        procs.append(_start(["serve", *common, "--service.metrics-port", str(serve_port)], logs["serve"]))
        procs.append(_start(["robot", "--sim", "--task", "block_pull", "--episodes", "3", "--wait-for-server", "90",
                             *common, "--service.metrics-port", str(robot_port)], logs["robot"]))  # fmt: skip

        # every process registers its collectors soon after it serves /metrics: scrape until the
        # union of what they export covers the required names (or time is up)
        exported: dict[str, set[str]] = {name: set() for name in targets}
        deadline = time.monotonic() + SCRAPE_SECONDS
        while True:
            for name, port in targets.items():
                with contextlib.suppress(OSError):
                    exported[name] |= exported_names(_scrape(port))
            union = set().union(*exported.values())
            if (required <= union and all(exported.values())) or time.monotonic() > deadline:
                break
            assert run.poll() is None, _tail(logs["run"])
            time.sleep(1.0)
    finally:
        _stop(procs[::-1])
    silent = sorted(name for name, names in exported.items() if "mea_service_info" not in names)
    assert not silent, f"no /metrics from {silent} ({ {n: targets[n] for n in silent} })\n" + "\n".join(
        f"--- {n}\n{_tail(p, 1500)}" for n, p in logs.items()
    )
    missing = sorted(required - union)
    assert not missing, f"queried but exported by no process: {missing}"
