"""An authenticated bus (the run's key + the sender's identity): the run's services reach each other;
a process without the key, with another run's key, or of a kind not allowed on a topic reaches no one,
and every refusal is counted."""

from __future__ import annotations

import pytest

from proto.control import EpisodeAck, ReplayGate
from proto.seal import seal
from proto.topics import (
    EPISODE_ACKS,
    EPISODES_RAW,
    REPLAY_GATE,
    STATUS,
    WEIGHTS_ANNOUNCE,
    WEIGHTS_LATEST,
    key,
)
from services.common.bus.base import Credentials
from services.common.bus.inproc import Hub, InProcBus
from tests.helpers.wire_samples import episode

pytestmark = [pytest.mark.unit, pytest.mark.timeout(30)]

KEY = bytes(range(32))
OTHER = bytes(32)


def gate(created_at: float = 5.0) -> ReplayGate:
    return ReplayGate(learner_id="learner-0", run_id="run-0", inserted_steps=1, allowed_steps=2, updates=0,
                      policy_version=0, replay_transitions=1, created_at=created_at)  # fmt: skip


@pytest.fixture
def hub():
    return Hub()


def member(hub: Hub, service: str, instance: str, key: bytes | None = KEY) -> InProcBus:
    bus = InProcBus(hub)
    if key is not None:
        bus.authenticate(Credentials(key, service, instance))
    return bus


def test_the_runs_services_reach_each_other_and_see_who_sent(hub):
    learner, actor = member(hub, "learner", "learner-0"), member(hub, "actor", "actor-0")
    sub = actor.subscribe(REPLAY_GATE)
    learner.publish(REPLAY_GATE, gate(), source="learner-0")
    d = sub.recv(timeout=1.0)
    assert d is not None and d.message == gate() and d.sender == "learner/learner-0"
    assert actor.stats.bad["replay_gate"] == 0


@pytest.mark.parametrize(
    ("who", "key"),
    [(("learner", "learner-0"), None), (("learner", "learner-0"), OTHER), (("actor", "learner-0"), KEY)],
    ids=["no-key", "other-runs-key", "actor-posing-as-learner"],
)
def test_forged_gates_are_refused_and_counted(hub, who, key):
    actor = member(hub, "actor", "actor-0")
    sub = actor.subscribe(REPLAY_GATE)
    rogue = member(hub, *who, key=key)
    rogue.publish(REPLAY_GATE, gate(1e12), source="learner-0")
    member(hub, "learner", "learner-0").publish(REPLAY_GATE, gate(), source="learner-0")
    got = sub.drain()
    assert [d.message for d in got] == [gate()]  # only the real learner's
    assert actor.stats.bad["replay_gate"] == 1 and actor.stats.unauthenticated["replay_gate"] == 1


def test_a_sender_cannot_publish_under_another_instances_key(hub):
    learner = member(hub, "learner", "learner-0")
    sub = learner.subscribe(EPISODES_RAW)
    member(hub, "actor", "actor-1").publish(EPISODES_RAW, episode(), source="actor-0")
    member(hub, "actor", "actor-0").publish(EPISODES_RAW, episode(), source="actor-0")
    assert len(sub.drain()) == 1 and learner.stats.unauthenticated["episodes_raw"] == 1


def test_a_sealed_message_replayed_on_another_key_is_refused(hub):
    """Bytes sealed for one key expression do not verify on another (e.g. a gate moved to acks)."""
    actor = member(hub, "actor", "actor-0")
    sub = actor.subscribe(EPISODE_ACKS)
    ack = EpisodeAck(learner_id="learner-0", run_id="run-0", episode_ids=["e-1"], created_at=1.0)
    sealed = seal(KEY, key(EPISODE_ACKS, source="learner-1"), "learner", "learner-1", ack.encode())
    sub.push(key(EPISODE_ACKS, source="learner-0"), sealed)
    sub.push(key(EPISODE_ACKS, source="learner-1"), sealed)
    got = sub.drain()
    assert [d.parts["source"] for d in got] == ["learner-1"]
    assert actor.stats.unauthenticated["episode_acks"] == 1


def test_weights_replies_are_accepted_from_the_runs_learner_only(hub, make_weights):
    actor = member(hub, "actor", "actor-0")
    rogue = member(hub, "learner", "learner-9", key=OTHER)
    rogue.serve(WEIGHTS_LATEST, lambda p: make_weights(1_000_000), source="learner-9")
    assert actor.query(WEIGHTS_LATEST) is None
    assert actor.stats.unauthenticated["weights_latest"] == 1
    real = member(hub, "learner", "learner-0")
    real.serve(WEIGHTS_LATEST, lambda p: make_weights(3), source="learner-0")
    d = actor.query(WEIGHTS_LATEST)
    assert d is not None and d.message.version == 3 and d.sender == "learner/learner-0"


def test_status_must_come_from_the_instance_it_names(hub):
    launcher = member(hub, "launcher", "launcher")
    sub = launcher.subscribe(STATUS)
    from tests.unit.test_inproc_bus import heartbeat

    hb = heartbeat("learner-0")
    member(hub, "actor", "actor-0").publish(STATUS, hb, service="learner", instance="learner-0")
    member(hub, "test", "learner-0").publish(STATUS, hb, service="test", instance="learner-0")
    assert [d.parts["service"] for d in sub.drain()] == ["test"]
    assert launcher.stats.unauthenticated["status"] == 1


def test_an_unauthenticated_bus_reads_sealed_messages_without_verifying(hub):
    """Mixed setups (a tool without the key) still read; the sender is then unverified."""
    plain = member(hub, "test", "t", key=None)
    sub = plain.subscribe(WEIGHTS_ANNOUNCE)
    member(hub, "learner", "learner-0").publish(WEIGHTS_ANNOUNCE, b"not even a message", source="learner-0")
    assert sub.recv(timeout=0.5) is None and plain.stats.bad["weights_announce"] == 1
    assert plain.stats.unauthenticated["weights_announce"] == 0  # the seal was readable; the body was not
