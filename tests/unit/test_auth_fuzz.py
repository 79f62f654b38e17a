"""10,000 mutated sealed messages per topic into an authenticated bus: none is accepted, none raises,
each is counted. Mutations: bit flips, truncation, insertion, a byte run overwritten, another key."""

from __future__ import annotations

import numpy as np
import pytest

from proto.seal import seal
from proto.topics import TOPICS, Kind, Topic, key
from services.common.bus.base import Credentials, Subscription
from services.common.bus.inproc import InProcBus
from tests.helpers.wire_samples import episode, sample

pytestmark = [pytest.mark.unit, pytest.mark.timeout(120)]

KEY = bytes(range(32))
N = 10_000
WRITER = {
    "episodes_raw": "actor",
    "episodes_augmented": "augmenter",
    "status": "test",
    "eval_reports": "evaluator",
}


def parts_of(topic: Topic) -> dict[str, str]:
    return {"source": "w-0"} if "source" in topic.placeholders else {"service": "test", "instance": "w-0"}


def message_for(topic: Topic):
    return episode() if topic.message.TYPE == "Episode" else sample(topic.message.TYPE)


def mutate(rng: np.random.Generator, payload: bytes) -> bytes:
    b = bytearray(payload)
    kind = rng.integers(0, 5)
    if kind == 0:  # 1-8 bit flips anywhere
        for at in rng.integers(0, len(b), rng.integers(1, 9)):
            b[at] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1:  # truncated
        del b[int(rng.integers(0, len(b))) :]
    elif kind == 2:  # bytes inserted
        at = int(rng.integers(0, len(b) + 1))
        b[at:at] = rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8).tobytes()
    elif kind == 3:  # a run overwritten
        at = int(rng.integers(0, len(b)))
        run = rng.integers(0, 256, min(len(b) - at, int(rng.integers(1, 32))), dtype=np.uint8).tobytes()
        b[at : at + len(run)] = run
    else:  # sealed again with a key that is not the run's
        return seal(rng.bytes(32), "x", "learner", "w-0", payload[-64:])
    return bytes(b)


@pytest.mark.parametrize("topic", [t for t in TOPICS if t.kind is not Kind.LIVELINESS], ids=lambda t: t.name)
def test_no_mutated_message_is_accepted(topic: Topic):
    bus = InProcBus()
    bus.authenticate(Credentials(KEY, "actor", "reader-0"))
    writer = WRITER.get(topic.name, topic.writers[0] if topic.writers else "test")
    parts = parts_of(topic)
    kx = key(topic, "default", **parts)
    msg = message_for(topic)
    genuine = seal(KEY, kx, writer, "w-0", msg.encode())
    rng = np.random.default_rng(7)
    sub = Subscription(bus, topic, capacity=N + 8)
    sub.push(kx, genuine)  # the genuine one is accepted: the rejections below are not a broken reader
    assert sub.recv(timeout=0.0) is not None
    mutated = 0
    for _ in range(N):
        m = mutate(rng, genuine)
        if m == genuine:
            continue
        mutated += 1
        if topic.kind is Kind.QUERY:
            assert bus.decode_delivery(topic, kx, m) is None
        else:
            sub.push(kx, m)
            assert sub.recv(timeout=0.0) is None
    assert mutated > N * 0.99
    assert bus.stats.bad[topic.name] == mutated
    assert bus.stats.unauthenticated[topic.name] == mutated  # every one failed the seal, not later
