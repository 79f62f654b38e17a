"""One wiring, two topologies: `mea run --in-process` (every service a thread over the in-process
bus) and `mea run` (every service a process over Zenoh on 127.0.0.1) run the same services from the
same configs, and produce the same kinds of messages and counts for a small budget."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.common.mcap_io import read_recording

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
BUDGET = 200


def _run(run_dir: Path, port: int, *extra: str) -> dict:
    cmd = [sys.executable, "-m", "services.cli", "run", "--task", "block_pull", "--demos", "1", "--actors", "1",
           "--env-steps", str(BUDGET), "--eval-every", "100", "--eval-episodes", "1", "--final-eval-episodes", "1",
           "--learner-preset", "smoke", "--listen", f"tcp/127.0.0.1:{port}", "--metrics-port", "0",
           "--run-dir", str(run_dir), "--final-eval-seconds", "90", "--log-format", "text", *extra]  # fmt: skip
    out = subprocess.run(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True,
                         text=True, timeout=240)  # fmt: skip
    log = out.stdout + out.stderr
    assert out.returncode == 0, log[-4000:]
    assert "env-step budget reached" in log, log[-4000:]
    return json.loads((run_dir / "summary.json").read_text())


def _by_service(summary: dict) -> dict[str, dict]:
    return {v["service"]: v["counters"] for v in summary["instances"].values()}


@pytest.mark.timeout(600)
def test_in_process_and_zenoh_topologies_produce_the_same_kinds_and_counts(tmp_path, free_port):
    inproc = _run(tmp_path / "inproc", free_port(), "--in-process")
    zenoh = _run(tmp_path / "zenoh", free_port())

    # the same instances, each reporting the same counters
    assert sorted(inproc["instances"]) == sorted(zenoh["instances"]) == [
        "actor-0", "augmenter-0", "evaluator-0", "learner-0"]  # fmt: skip
    a, b = _by_service(inproc), _by_service(zenoh)
    for service in ("actor", "augmenter", "evaluator", "learner"):
        assert set(a[service]) == set(b[service]), service
    for summary, counters in ((inproc, a), (zenoh, b)):
        actor, aug, learner = counters["actor"], counters["augmenter"], counters["learner"]
        # every raw episode was recorded, reached the augmenter and came out multiplied (raw + 4
        # rotated copies each, + 6 MEA copies of the demo), and the learner accepted what it got
        assert summary["episodes_recorded"] == actor["episodes"] >= 2
        assert actor["env_steps"] >= BUDGET and learner["env_steps"] >= BUDGET
        # (the augmenter may stop before the episode an actor publishes while the run stops)
        assert actor["episodes"] - 1 <= aug["episodes_in"] <= actor["episodes"] and aug["failed"] == 0
        assert aug["episodes_out"] >= 5 * aug["episodes_in"] + 1
        assert learner["episodes_in"] > 0 and learner["rejected"] == 0 and learner["updates"] > 0
        assert learner["version"] >= 1
        # the evaluator evaluated, the last time at the budget
        assert summary["evaluations"] >= 1 and summary["last_report"]["env_steps"] >= BUDGET
        assert all(v["exitcode"] in (None, 0) for v in summary["instances"].values())

    # the demonstration (same seed, same expert) is the same episode in both
    demo = [next(iter(read_recording(tmp_path / d / "episodes")))[1] for d in ("inproc", "zenoh")]
    assert demo[0].is_demo and demo[1].is_demo and demo[0].seed == demo[1].seed
    np.testing.assert_array_equal(demo[0].actions, demo[1].actions)
    np.testing.assert_array_equal(demo[0].points, demo[1].points)
    # and each run saved the configs its services ran with
    for d in ("inproc", "zenoh"):
        saved = sorted(p.name for p in (tmp_path / d / "services").iterdir())
        assert saved == ["actor-0.json", "augmenter-0.json", "evaluator-0.json", "learner-0.json"]
    assert json.loads((tmp_path / "inproc" / "services" / "learner-0.json").read_text())["batch_size"] == 2
