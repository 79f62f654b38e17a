"""Two `mea run` stacks on one host: different namespaces, routers and /metrics port bases, side by
side, each with every service serving /metrics; neither disturbs the other."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from tests.helpers import find_free_port_base

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
SECONDS = 65  # a minute side by side, plus start-up
OFFSETS = (0, 1, 2, 3, 10)  # launcher, learner, augmenter, evaluator, actor 0


def _scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
        return r.read().decode()


@pytest.mark.timeout(300)
def test_two_stacks_with_their_own_namespace_and_port_base_run_side_by_side(tmp_path, free_port):
    runs = []
    taken: set[int] = set()
    for name in ("a", "b"):
        base = find_free_port_base(OFFSETS, taken)
        taken |= {base + o for o in range(21)}
        cmd = [sys.executable, "-m", "services.cli", "run", "--demos", "1", "--env-steps", "0",
               "--learner-preset", "smoke", "--namespace", f"run-{name}", "--metrics-port", str(base),
               "--listen", f"tcp/127.0.0.1:{free_port()}", "--run-dir", str(tmp_path / name),
               "--duration-seconds", str(SECONDS), "--log-format", "text"]  # fmt: skip
        proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip
        runs.append((name, base, proc))
    try:
        # while both run, every service of each serves /metrics on its own run's ports
        deadline = time.monotonic() + SECONDS - 5
        seen: dict[str, set[int]] = {"a": set(), "b": set()}
        while time.monotonic() < deadline and any(len(s) < len(OFFSETS) for s in seen.values()):
            for name, base, proc in runs:
                assert proc.poll() is None, proc.stdout.read()[-3000:]
                for o in OFFSETS:
                    try:
                        if "mea_" in _scrape(base + o):
                            seen[name].add(o)
                    except OSError:
                        pass
            time.sleep(1.0)
        assert all(s == set(OFFSETS) for s in seen.values()), seen
        outs = {name: proc.communicate(timeout=120)[0] for name, _, proc in runs}
    finally:
        for _, _, proc in runs:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    for name, _, proc in runs:
        assert proc.returncode == 0, outs[name][-3000:]
        assert "duration reached" in outs[name] and "Address already in use" not in outs[name]
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        assert all(v["exitcode"] in (None, 0) for v in summary["instances"].values()), summary
        actor = summary["instances"]["actor-0"]["counters"]
        # each run recorded its own episodes only (namespaces keep the runs apart)
        assert summary["episodes_recorded"] == actor["episodes"] >= 1
