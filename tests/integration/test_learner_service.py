"""The learner service on the in-process bus: rate limiting, weights versions, the gate, bad input."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from proto.topics import EPISODES_AUGMENTED, REPLAY_GATE, STATUS, WEIGHTS_ANNOUNCE
from services.algorithms.policy import PolicyRuntime
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig
from services.common.weights import WeightsClient
from services.learner import checkpoint
from services.learner.config import LearnerConfig
from tests.helpers.learner import SIZE, TINY_NET, learner_episode, start_learner, tiny_learner_config

pytestmark = pytest.mark.integration


def svc() -> ServiceConfig:
    return ServiceConfig(instance_id="learner-t", metrics_port=0, log_format="text", heartbeat_seconds=0.2)


def spi_config(tmp_path, max_updates: int, min_steps: int = 20, **kw) -> LearnerConfig:
    """A tiny learner at 0.5 samples per insert with an error buffer of 5: updates allowed =
    0.5 * steps - (0.5 * min_steps - 5)."""
    return tiny_learner_config(tmp_path, svc(), samples_per_insert=0.5, min_steps=min_steps, error_buffer=5.0,
                               max_updates=max_updates, **kw)  # fmt: skip


def wait_for(pred, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def test_learner_respects_the_ratio_publishes_versions_and_survives_bad_input(tmp_path):
    cfg = spi_config(tmp_path, max_updates=14)  # updates allowed = 0.5 * steps - 5
    hub = Hub()
    observer = InProcBus(hub)
    announces = observer.subscribe(WEIGHTS_ANNOUNCE, capacity=256)
    gates = observer.subscribe(REPLAY_GATE, capacity=4096)
    status = observer.subscribe(STATUS, capacity=256, service="learner")
    thread, result = start_learner(cfg, hub, observer)
    seen_gates: list = []

    def latest_gate():
        seen_gates.extend(d.message for d in gates.drain())
        return seen_gates[-1] if seen_gates else None

    # version 0 (initial weights) arrives before any data; a consumer can load and act with it
    first = wait_for(lambda: announces.drain(), 10, "version 0")
    assert first[0].message.version == 0
    client = WeightsClient(observer, timeout=5.0)
    policy = PolicyRuntime(deterministic=True)
    policy.load(client.poll())
    a = policy.act(np.zeros((2, SIZE, SIZE), np.uint8))
    assert a.shape == (5,) and np.all(np.abs(a) <= 1)

    # bad input: no images, wrong image size -> counted and skipped, not fatal
    bad_none = dataclasses.replace(learner_episode(90), images=None, episode_id="bad-none")
    bad_size = dataclasses.replace(
        learner_episode(91), images=np.zeros((11, 2, SIZE + 1, SIZE + 1), np.uint8), episode_id="bad-size"
    )
    for ep in (bad_none, bad_size):
        observer.publish(EPISODES_AUGMENTED, ep, source="augmenter-0")
    # 3 raw episodes of 10 steps (+1 copy each: copies are not env steps) -> 30 steps -> 10 updates
    for k in range(3):
        raw = learner_episode(k, T=10, demo=k == 0)
        observer.publish(EPISODES_AUGMENTED, raw, source="augmenter-0")
        observer.publish(
            EPISODES_AUGMENTED, learner_episode(100 + k, copy_of=raw.episode_id), source="augmenter-0"
        )
    wait_for(lambda: (g := latest_gate()) is not None and g.updates >= 10, 60, "10 updates")
    # the limiter must hold it there for good: no gate in the next second shows over-training
    hold_until = time.monotonic() + 1.0
    while time.monotonic() < hold_until:
        d = gates.recv(timeout=max(0.0, hold_until - time.monotonic()))
        if d is not None:
            seen_gates.append(d.message)
            assert d.message.updates <= 10, d.message
    g = latest_gate()
    assert g.updates == 10 and g.inserted_steps == 30 and g.replay_transitions == 60
    assert g.allowed_steps > g.inserted_steps  # producers may add more (max_diff = 0.5*20 + 5)
    assert thread.is_alive()
    # 10 more steps -> 15 allowed -> max_updates 14 reached -> the learner exits cleanly
    observer.publish(EPISODES_AUGMENTED, learner_episode(5, T=10), source="augmenter-0")
    thread.join(timeout=60)
    assert not thread.is_alive() and result["rc"] == 0

    versions = [d.message.version for d in first[1:] + announces.drain()]
    assert versions == sorted(versions) and len(set(versions)) == len(versions)
    assert max(versions) >= 7  # publish_every 2: 14 updates -> versions 1..7, plus a final one
    beats = [d.message for d in status.drain()]
    last = beats[-1].counters
    assert last["updates"] == 14 and last["rejected"] == 2 and last["env_steps"] == 40
    assert np.isfinite(last["critic_loss"])
    assert checkpoint.exists(tmp_path / "checkpoints")  # written on shutdown
    assert (tmp_path / "learner.json").exists()


def test_a_state_critic_learner_trains_on_privileged_rows_and_rejects_episodes_without_them(tmp_path):
    net = dataclasses.replace(TINY_NET, critic_input="state", state_critic_hidden=(16,))
    cfg = spi_config(tmp_path, max_updates=4, min_steps=10, net=net)
    hub = Hub()
    observer = InProcBus(hub)
    status = observer.subscribe(STATUS, capacity=256, service="learner")
    thread, result = start_learner(cfg, hub, observer)
    # an episode whose producer did not say which object is immovable cannot feed the state critic
    unknown = dataclasses.replace(learner_episode(90), episode_id="no-fixed-object")
    observer.publish(EPISODES_AUGMENTED, unknown, source="augmenter-0")
    for k in range(2):  # 20 steps -> 0.5 * 20 - (0.5 * 10 - 5) = 10 updates allowed, 4 wanted
        ep = dataclasses.replace(learner_episode(k, T=10, demo=k == 0), fixed_object=k % 2)
        observer.publish(EPISODES_AUGMENTED, ep, source="augmenter-0")
    thread.join(timeout=60)
    assert not thread.is_alive() and result["rc"] == 0
    last = [d.message for d in status.drain()][-1].counters
    assert last["updates"] == 4 and last["rejected"] == 1 and last["env_steps"] == 20
    assert np.isfinite(last["critic_loss"])


def test_the_learner_acknowledges_every_raw_episode_and_stores_a_repeat_once(tmp_path):
    from proto.topics import EPISODE_ACKS
    from services.learner import checkpoint

    cfg = spi_config(tmp_path, max_updates=2)
    hub = Hub()
    observer = InProcBus(hub)
    acks = observer.subscribe(EPISODE_ACKS, capacity=16)
    status = observer.subscribe(STATUS, capacity=256, service="learner")
    thread, result = start_learner(cfg, hub, observer)
    a, b = learner_episode(1, T=10), learner_episode(2, T=10)
    copy = learner_episode(3, T=10, copy_of=a.episode_id)
    for ep in (a, copy, a, copy):  # a repeated delivery (e.g. an actor publishing again after a restart)
        observer.publish(EPISODES_AUGMENTED, ep, source="augmenter-0")
    acked: list = []

    def both_acknowledged() -> bool:  # each ack lists every raw delivery taken so far: the newest says all
        acked.extend(d.message for d in acks.drain())
        return bool(acked) and acked[-1].episode_ids.count(a.episode_id) == 2

    wait_for(both_acknowledged, 10, "both deliveries acknowledged")
    assert acked[-1].episode_ids == [a.episode_id, a.episode_id]  # raw ids only, each delivery
    assert acked[-1].learner_id == "learner-t"
    observer.publish(EPISODES_AUGMENTED, b, source="augmenter-0")  # 20 raw steps: 5 updates allowed, 2 run
    thread.join(timeout=60)
    assert not thread.is_alive() and result["rc"] == 0
    last = [d.message for d in status.drain()][-1].counters
    assert last["env_steps"] == 20 and last["episodes_in"] == 3 and last["rejected"] == 2
    _, replay, _ = checkpoint.load(tmp_path / "checkpoints")
    ids = list(replay["episode_id"])
    assert sorted(ids) == sorted([a.episode_id, copy.episode_id, b.episode_id])  # each exactly once
