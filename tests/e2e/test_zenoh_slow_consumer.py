"""A consumer that stops reading for longer than Zenoh's default patience loses nothing.

Episodes go with BLOCK congestion control and a full subscriber queue makes Zenoh's receiving thread
wait, so a learner busy writing a checkpoint pushes back on the augmenter through the router. With
Zenoh's default (``block/wait_before_close`` 5 s) the router then closed the transport to the
learner for good: what it held was lost and nothing arrived afterwards, a run stalled at its replay
gate (docs/results.md). The sessions now wait ``BLOCK_WAIT_US``. A pause past Zenoh's lease (10 s)
still closes the transport (a 14 s pause lost 38 of 300), so the learner never makes its reader wait
that long: tests/e2e/test_learner_checkpoint_pause.py."""

from __future__ import annotations

import json
import threading
import time

import pytest

from proto.topics import EPISODES_AUGMENTED
from services.common.bus.zenoh_bus import BLOCK_WAIT_KEY, BLOCK_WAIT_US, ZenohBus, ZenohConfig
from tests.helpers import build_episode, find_free_port

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(120)]

PAUSE_S = 8.0  # past Zenoh's 5 s default patience, within its 10 s lease (see the module docstring)
SENT = 300  # episodes of 50 steps with images: far more than the queue and the socket buffers hold


def _receive(sub, want: int, seconds: float) -> int:
    """Episodes received, up to ``want``, within ``seconds``."""
    got, deadline = 0, time.monotonic() + seconds
    while got < want and sub.recv(timeout=max(0.0, deadline - time.monotonic())) is not None:
        got += 1
    return got


def test_every_session_waits_on_a_slow_reader_far_longer_than_zenohs_default():
    for mode in ("router", "peer", "client"):
        assert json.loads(ZenohConfig(mode=mode).to_zenoh().get_json(BLOCK_WAIT_KEY)) == BLOCK_WAIT_US
    assert BLOCK_WAIT_US >= 60_000_000


def test_a_consumer_pausing_past_zenohs_default_patience_loses_nothing_and_hears_on():
    endpoint = f"tcp/127.0.0.1:{find_free_port()}"
    router = ZenohBus(ZenohConfig(mode="router", listen=(endpoint,), connect=()))
    buses = [router]
    try:
        consumer = ZenohBus(ZenohConfig(mode="peer", connect=(endpoint,)))
        buses.append(consumer)
        sub = consumer.subscribe(EPISODES_AUGMENTED, capacity=4)
        producer = ZenohBus(ZenohConfig(mode="peer", connect=(endpoint,)))
        buses.append(producer)
        episode = build_episode(T=50, with_images=True)
        deadline = time.monotonic() + 15.0  # routes are up once one episode crosses
        crossed = False
        while not crossed and time.monotonic() < deadline:
            producer.publish(EPISODES_AUGMENTED, episode, source="producer")
            crossed = sub.recv(timeout=0.2) is not None
        assert crossed, "no episode crossed the router"
        while sub.recv(timeout=0.5) is not None:  # warm-up repeats still in flight, until quiet
            pass

        sender = threading.Thread(
            target=lambda: [
                producer.publish(EPISODES_AUGMENTED, episode, source="producer") for _ in range(SENT)
            ],
            daemon=True,
        )
        sender.start()
        # the consumer is busy (the behaviour under test, not a wait): its queue fills, Zenoh's reader waits
        time.sleep(PAUSE_S)
        assert _receive(sub, SENT, 30.0) == SENT
        sender.join(5.0)
        producer.publish(EPISODES_AUGMENTED, episode, source="producer")
        assert _receive(sub, 1, 5.0) == 1  # the path is still open
    finally:
        for bus in reversed(buses):
            bus.close()
