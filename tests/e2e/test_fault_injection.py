"""Faults injected into a live `mea run` over real Zenoh on 127.0.0.1 (the run authenticates its bus,
the default): a process without the run's key impersonates the learner, the evaluator, an actor and
the augmenter, and the augmenter is SIGKILLed while it holds an episode. The run goes on to its
budget, nothing forged is accepted (every attempt is counted), the augmenter is restarted and every
raw episode the actor published reaches the learner's replay exactly once; a SIGKILLed actor is
restarted too, and training goes on."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from mea_tools.bench.system import connect_to_run
from proto.control import EvalReport, Heartbeat, ReplayGate
from proto.topics import (
    EPISODES_AUGMENTED,
    EPISODES_RAW,
    EVAL_REPORTS,
    REPLAY_GATE,
    STATUS,
    WEIGHTS_ANNOUNCE,
    WEIGHTS_LATEST,
)
from services.learner import checkpoint
from tests.helpers import build_weights, find_free_port, find_free_port_base
from tests.helpers.learner import learner_episode

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
BUDGET = 480
ACTOR_MARGIN = 160  # env steps left for the restarted actor to produce
OFFSETS = {"launcher": 0, "learner": 1, "augmenter": 2, "evaluator": 3, "actor": 10}
ROGUE_VERSION = 1_000_000


def scrape(port: int) -> dict[tuple[str, str], float]:
    """``mea_bus_unauthenticated_messages_total`` by topic (and the rejected total) at one /metrics."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
        text = r.read().decode()
    out: dict[tuple[str, str], float] = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            if s.name in ("mea_bus_unauthenticated_messages_total", "mea_bus_rejected_messages_total"):
                out[(s.name, s.labels["topic"])] = s.value
    return out


def inject(rogue, now: float) -> None:
    """Everything the issue's rogue did, without the run's key, each on the key of a real sender."""
    rogue.publish(STATUS, Heartbeat(service="learner", instance_id="learner-0", pid=1, state="running",
                                    started_at=now, created_at=now, policy_version=ROGUE_VERSION,
                                    counters={"env_steps": 1e9, "updates": 1e9}),
                  service="learner", instance="learner-0")  # fmt: skip
    rogue.publish(EVAL_REPORTS, EvalReport(evaluator_id="evaluator-0", run_id="rogue", task="block_pull",
                                           policy_version=ROGUE_VERSION, env_steps=10**9, episodes=50,
                                           success_rate=1.0, mean_return=1.0, mean_length=1.0, grasp_score=1.0,
                                           created_at=now), source="evaluator-0")  # fmt: skip
    blob = build_weights(ROGUE_VERSION, run_id="rogue", algorithm="equi_rsac")
    rogue.publish(WEIGHTS_ANNOUNCE, blob.announcement(1), source="learner-0")
    for k in range(5):
        ep = dataclasses.replace(learner_episode(900 + k, T=10), episode_id=f"rogue-{k}", actor_id="actor-0",
                                 rewards=np.full(10, 1e30, np.float32))  # fmt: skip
        rogue.publish(EPISODES_RAW, ep, source="actor-0")
        rogue.publish(EPISODES_AUGMENTED, ep, source="augmenter-0")
    for k in range(3000):  # a gate flood, dated in the future
        gate = ReplayGate(learner_id="learner-0", run_id="rogue", inserted_steps=10**9, allowed_steps=10**9,
                          updates=k, policy_version=ROGUE_VERSION, replay_transitions=0, created_at=now + 1e6)  # fmt: skip
        rogue.publish(REPLAY_GATE, gate, source="learner-0")


class Faults:
    """What the test observed (the run's own sealed heartbeats and raw episodes) and the fault
    schedule: inject forgeries, scrape the counters, kill the actor, and once its restart reported in,
    stop then kill the augmenter. The order is fixed by events, not by a clock: while the actor
    restarts nothing is produced, and while the augmenter is down the learner inserts nothing, so
    neither fault can be outrun by a fast machine reaching the budget first."""

    def __init__(self, rogue, base: int) -> None:
        self.rogue, self.base = rogue, base
        self.published: list[tuple[str, float]] = []  # raw episode ids as they went out (repeats included)
        self.actor_versions: list[int] = []
        self.pids: dict[str, list[int]] = {"actor": [], "augmenter": []}
        self.counts: dict[str, dict] = {}
        self.learner_steps = self.steps_at_actor_kill = 0
        self.injected_at = self.stopped_at = self.killed_at = self.restarted_at = self.actor_killed_at = None

    def beat(self, hb) -> None:
        if hb.service == "actor":
            self.actor_versions.append(hb.policy_version)
        if hb.service == "learner":
            self.learner_steps = int(hb.counters.get("env_steps", 0))
        pids = self.pids.get(hb.service)
        if pids is not None and hb.pid not in pids:
            pids.append(hb.pid)
            if hb.service == "augmenter" and self.killed_at is not None and self.restarted_at is None:
                self.restarted_at = time.time()

    def step(self, fresh: list[str], now: float) -> None:
        self.published += [(eid, now) for eid in fresh]
        if self.injected_at is None and len(self.published) >= 2:
            inject(self.rogue, now)
            self.injected_at = now
        elif self.injected_at is not None and not self.counts and now > self.injected_at + 5:
            self.counts = {svc: scrape(self.base + off) for svc, off in OFFSETS.items()}
        elif self.counts and self.actor_killed_at is None:  # early, so its restart surely reports in
            os.kill(self.pids["actor"][-1], signal.SIGKILL)
            self.actor_killed_at, self.steps_at_actor_kill = now, self.learner_steps
        elif len(self.pids["actor"]) >= 2 and self.stopped_at is None:
            # the augmenter stops: what comes now it cannot take
            os.kill(self.pids["augmenter"][-1], signal.SIGSTOP)
            self.stopped_at = now
        elif self.stopped_at is not None and self.killed_at is None and fresh and now > self.stopped_at + 0.5:
            os.kill(self.pids["augmenter"][-1], signal.SIGKILL)
            self.killed_at = now


@pytest.mark.timeout(420)
def test_forgeries_are_refused_and_a_killed_augmenter_loses_no_episode(tmp_path):
    port, base = find_free_port(), find_free_port_base(tuple(OFFSETS.values()))
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "services.cli", "run", "--task", "block_pull", "--demos", "1",
           "--env-steps", str(BUDGET), "--eval-every", "100000", "--final-eval-episodes", "1",
           "--final-eval-seconds", "60", "--learner-preset", "smoke", "--success-rotations", "4",
           "--listen", f"tcp/127.0.0.1:{port}", "--metrics-port", str(base), "--run-dir", str(run_dir),
           "--log-format", "text"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)  # fmt: skip
    bus = rogue = None
    try:
        bus = connect_to_run(port, proc)
        rogue = connect_to_run(port, proc)  # no run key: what any process on the network can do
        rogue.serve(
            WEIGHTS_LATEST, lambda p: build_weights(ROGUE_VERSION, run_id="rogue"), source="learner-9"
        )
        f = Faults(rogue, base)
        raw = bus.subscribe(EPISODES_RAW, capacity=1024)
        status = bus.subscribe(STATUS, capacity=4096)
        deadline = time.monotonic() + 360
        while proc.poll() is None:
            assert time.monotonic() < deadline, "run did not finish"
            for d in [status.recv(timeout=0.1), *status.drain()]:
                if d is not None and d.sender:  # only the run's own heartbeats (sealed; ours is not)
                    f.beat(d.message)
            f.step([d.message.episode_id for d in raw.drain() if d.sender], time.time())
        out = proc.stdout.read()
        assert proc.returncode == 0, out[-4000:]
        assert "env-step budget reached" in out, out[-4000:]
    finally:
        for b in (bus, rogue):
            if b is not None:
                b.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)

    assert f.killed_at is not None and f.restarted_at is not None, (f.killed_at, f.pids)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["instances"]["augmenter-0"]["restarts"] == 1, summary
    assert f.actor_killed_at is not None and summary["instances"]["actor-0"]["restarts"] == 1, summary
    assert f.steps_at_actor_kill <= BUDGET - ACTOR_MARGIN // 2, f.steps_at_actor_kill
    assert len(f.pids["actor"]) == 2  # the restarted actor reported in
    learner = summary["instances"]["learner-0"]["counters"]
    assert BUDGET <= learner["env_steps"] < 10**6  # the real budget ended the run, not a forged heartbeat
    # nothing forged was accepted: the actor never acted with the rogue's weights ...
    assert f.actor_versions and max(f.actor_versions) < ROGUE_VERSION
    # ... and every forgery was refused as unauthenticated where it arrived
    unauth = {svc: {t: v for (n, t), v in c.items() if n.endswith("unauthenticated_messages_total")}
              for svc, c in f.counts.items()}  # fmt: skip
    assert unauth["actor"].get("weights_announce", 0) >= 1, unauth
    assert unauth["actor"].get("replay_gate", 0) >= 3000, unauth
    assert unauth["augmenter"].get("episodes_raw", 0) >= 5, unauth
    assert unauth["learner"].get("episodes_augmented", 0) >= 5, unauth
    assert unauth["launcher"].get("status", 0) >= 1 and unauth["launcher"].get("eval_reports", 0) >= 1, unauth
    assert unauth["launcher"].get("episodes_raw", 0) >= 5, unauth  # the recorder
    # the killed augmenter's episode (and those published while it was down) went out again ...
    repeats = [eid for eid, n in Counter(eid for eid, _ in f.published).items() if n > 1]
    assert repeats, "no episode was published again after the augmenter was killed"
    # ... and every raw episode published before the restart settled is in replay exactly once
    _, replay, _ = checkpoint.load(run_dir / "learner" / "checkpoints")
    stored = Counter(
        str(e) for e, s in zip(replay["episode_id"], replay["source_episode_id"], strict=True) if e == s
    )
    assert all(n == 1 for n in stored.values())
    settled = {eid for eid, at in f.published if at < f.restarted_at + 8}
    assert settled and settled <= set(stored), sorted(settled - set(stored))
    assert not any(eid.startswith("rogue") for eid in stored)
