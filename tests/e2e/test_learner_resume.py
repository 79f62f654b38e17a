"""SIGKILL the learner mid-run, restart it with --resume: the version lineage, replay and training go on."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time

import pytest

from proto.topics import EPISODES_AUGMENTED, STATUS, WEIGHTS_ANNOUNCE
from services.common.bus.zenoh_bus import ZenohBus
from services.learner import checkpoint
from tests.helpers.learner import learner_child, learner_episode
from tests.helpers.zenoh_peer import peer_config

pytestmark = pytest.mark.e2e
CTX = mp.get_context("spawn")
TIMEOUT = 60.0


def start(endpoint: str, run_dir, resume: bool) -> mp.Process:
    p = CTX.Process(target=learner_child, args=(endpoint, str(run_dir), resume, "learner-0"), daemon=True)
    p.start()
    return p


def next_beat(status, proc, pred, what: str):
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        d = status.recv(timeout=0.5)
        if d is not None and pred(d.message):
            return d.message
        assert proc.is_alive(), f"learner exited ({proc.exitcode}) while waiting for {what}"
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.timeout(240)
def test_sigkill_then_resume_continues_version_replay_and_training(zenoh_router, tmp_path):
    bus = ZenohBus(peer_config(zenoh_router, "client"))
    procs: list[mp.Process] = []
    try:
        status = bus.subscribe(STATUS, capacity=4096, service="learner")
        announces = bus.subscribe(WEIGHTS_ANNOUNCE, capacity=4096)
        watch = bus.watch_alive("learner")
        procs.append(start(zenoh_router, tmp_path, resume=False))
        assert watch.wait_for(lambda alive: ("learner", "learner-0") in alive, TIMEOUT)
        # 4 raw episodes x 10 steps (+ a copy each): 40 env steps, 80 transitions; 40 + 20 updates allowed
        for k in range(4):
            raw = learner_episode(k, T=10, demo=k == 0)
            bus.publish(EPISODES_AUGMENTED, raw, source="augmenter-0")
            bus.publish(
                EPISODES_AUGMENTED, learner_episode(50 + k, copy_of=raw.episode_id), source="augmenter-0"
            )
        before = next_beat(status, procs[0], lambda h: h.counters.get("updates", 0) >= 16, "16 updates")
        losses_before = before.counters["critic_loss"]
        os.kill(procs[0].pid, signal.SIGKILL)
        procs[0].join(10)
        assert procs[0].exitcode == -signal.SIGKILL
        pre = [d.message for d in announces.drain()]
        run_id = pre[-1].run_id
        recorded_run, recorded_version = checkpoint.last_published(tmp_path / "checkpoints")
        assert recorded_run == run_id and recorded_version >= max(a.version for a in pre)

        learner, replay, meta = checkpoint.load(tmp_path / "checkpoints")
        ckpt_updates, ckpt_version = learner["sac"]["updates"], meta["version"]
        assert ckpt_updates >= 15 and ckpt_updates % 5 == 0  # checkpoint_every 5
        assert meta["run_id"] == run_id and meta["env_steps"] == 40

        status.drain()
        procs.append(start(zenoh_router, tmp_path, resume=True))
        # no new data is published: everything below comes from the restored checkpoint
        first = announces.recv(timeout=TIMEOUT)
        assert first is not None, "no weights announced after resume"
        # versions announced after the checkpoint are not announced again: the lineage goes on past them
        assert first.message.version == recorded_version + 1 and first.message.run_id == run_id
        assert first.message.version > max(a.version for a in pre) >= ckpt_version
        after = next_beat(status, procs[1], lambda h: h.counters.get("updates", 0) > ckpt_updates + 3,
                          "updates after resume")  # fmt: skip
        assert after.counters["replay_transitions"] == 80  # replay restored, not empty
        assert after.counters["env_steps"] == 40
        assert after.policy_version > ckpt_version
        # no spike: the restored buffer is the same data the loss was converging on
        assert after.counters["critic_loss"] < 5.0 * losses_before + 0.1
        os.kill(procs[1].pid, signal.SIGTERM)  # clean stop: final checkpoint, version goes on
        procs[1].join(TIMEOUT)
        assert procs[1].exitcode == 0
        post = [first.message] + [d.message for d in announces.drain()]
        versions = [a.version for a in pre + post]
        assert versions == sorted(set(versions)), "a version was announced twice"
        _, _, final = checkpoint.load(tmp_path / "checkpoints")
        assert final["version"] >= first.message.version and final["run_id"] == run_id
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
            p.join(10)
        bus.close()
