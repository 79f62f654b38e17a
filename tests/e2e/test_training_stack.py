"""`mea run` end to end over real Zenoh on 127.0.0.1: demos and policy episodes flow, the augmenter
multiplies them, the learner publishes versions that actors and the evaluator pick up, an EvalReport
arrives, the env-step budget stops the run and no process is left behind."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest

from mea_tools.bench.system import connect_to_run
from proto.topics import EPISODES_AUGMENTED, EPISODES_RAW, EVAL_REPORTS, STATUS, WEIGHTS_ANNOUNCE
from services.common.mcap_io import read_recording
from services.learner import checkpoint

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
BUDGET = 400


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.timeout(300)
def test_mea_run_trains_end_to_end_and_stops_at_the_budget(tmp_path):
    port = _port()
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "services.cli", "run", "--task", "block_pull", "--demos", "1",
           "--actors", "1", "--env-steps", str(BUDGET), "--eval-every", "150", "--eval-episodes", "1",
           "--final-eval-episodes", "1",
           "--learner-preset", "smoke", "--listen", f"tcp/127.0.0.1:{port}", "--metrics-port", "0",
           "--run-dir", str(run_dir), "--final-eval-seconds", "90"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)  # fmt: skip
    bus = None
    raw, augmented, versions, reports = [], [], [], []
    policy_seen: dict[str, list[int]] = defaultdict(list)
    pids: set[int] = set()
    try:
        deadline = time.monotonic() + 60
        bus = connect_to_run(port, proc)
        subs = {
            "raw": bus.subscribe(EPISODES_RAW, capacity=1024),
            "aug": bus.subscribe(EPISODES_AUGMENTED, capacity=4096),
            "ann": bus.subscribe(WEIGHTS_ANNOUNCE, capacity=1024),
            "eval": bus.subscribe(EVAL_REPORTS, capacity=64),
            "status": bus.subscribe(STATUS, capacity=4096),
        }
        while proc.poll() is None:
            assert time.monotonic() < deadline + 240, "run did not finish"
            raw += [d.message for d in subs["raw"].drain()]
            augmented += [d.message for d in subs["aug"].drain()]
            versions += [d.message.version for d in subs["ann"].drain()]
            reports += [d.message for d in subs["eval"].drain()]
            for d in [subs["status"].recv(timeout=0.2), *subs["status"].drain()]:  # heartbeats pace the loop
                if d is None:
                    continue
                hb = d.message
                pids.add(hb.pid)
                if hb.service in ("actor", "evaluator"):
                    policy_seen[hb.service].append(hb.policy_version)
        out = proc.stdout.read()
        assert proc.returncode == 0, out[-4000:]
        assert "env-step budget reached" in out, out[-4000:]
    finally:
        if bus is not None:
            bus.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)

    # demos first, then episodes of the learned policy, with increasing weights versions
    assert raw and raw[0].is_demo and raw[0].policy_kind.startswith("expert_")
    learned = [ep for ep in raw if ep.policy_kind == "learned"]
    assert learned and learned[-1].policy_version >= learned[0].policy_version >= 0
    assert sum(ep.num_steps for ep in raw) >= BUDGET
    # the augmenter multiplies them: raw + 4 isometric each, + 6 MEA copies per demo (mea variant)
    # counted by id: a resent raw episode (not yet acknowledged) is augmented again into the same ids
    by_source = defaultdict(set)
    for ep in augmented:
        by_source[ep.episode_id if ep.augmentation is None else ep.augmentation.source_episode_id].add(
            ep.episode_id
        )
    by_source = {k: len(v) for k, v in by_source.items()}
    for ep in raw:
        if ep.episode_id in by_source:
            expected = 1 + 4 + (6 if ep.is_demo else 0)
            assert expected - (6 if ep.is_demo else 0) <= by_source[ep.episode_id] <= expected, ep.episode_id
    assert len(augmented) >= 4 * len(by_source)
    # versions: at least 3, increasing; actors and the evaluator report newer versions over time
    assert len(set(versions)) >= 3 and versions == sorted(versions)
    for service in ("actor", "evaluator"):
        seen = [v for v in policy_seen[service] if v >= 0]
        assert seen and max(seen) > min(seen), (service, policy_seen[service])
    assert reports and all(0.0 <= r.success_rate <= 1.0 for r in reports)
    assert max(r.env_steps for r in reports) >= BUDGET  # the final evaluation at the budget
    # nothing left behind (the launcher has exited; its children are reaped within a moment)
    deadline = time.monotonic() + 5.0
    while [p for p in pids if _alive(p)] and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [p for p in pids if _alive(p)], "service processes outlived the launcher"
    # the run directory
    cfg = json.loads((run_dir / "config.json").read_text())
    assert cfg["variant"] == "mea" and cfg["env_steps"] == BUDGET
    assert checkpoint.exists(run_dir / "learner" / "checkpoints")
    history = (run_dir / "eval" / "history.jsonl").read_text().splitlines()
    assert len(history) == len(reports)
    assert (run_dir / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    recorded = list(read_recording(run_dir / "episodes"))
    # every raw episode once, in order: an actor resends one not yet acknowledged (a loaded machine)
    assert [m.episode_id for _, m in recorded] == list(dict.fromkeys(ep.episode_id for ep in raw))
