"""ZenohBus across real OS processes on 127.0.0.1, through a router on a free port.

The test process is one side (``parent``) and a spawned child the other (``child``); see
``tests.helpers.zenoh_peer`` for the child entry points and the readiness protocol (declare
everything, then the liveliness token; wait for the other side's token before sending).
"""

from __future__ import annotations

import os
import signal
import time

import pytest

from proto.topics import EPISODES_RAW, WEIGHTS_ANNOUNCE, WEIGHTS_LATEST
from services.common.bus.zenoh_bus import ZenohBus
from tests.helpers import assert_messages_equal, build_weights
from tests.helpers.zenoh_peer import (
    SERVICE,
    Child,
    episode_echo,
    fetch_if_newer,
    hold_token,
    peer_config,
    weights_exchange,
    weights_handler,
)

pytestmark = pytest.mark.e2e

READY_S = 30.0  # child start-up (interpreter, imports, session) until its token is seen
STEP_S = 15.0  # any single exchange
WEIGHTS_BYTES = 5 * 1024 * 1024


def _check_fetch(report: dict, *, source: str, version: int, digest: str, size: int) -> None:
    assert report["source"] == source
    assert report["newer"] is True
    assert (report["ann_version"], report["ann_digest"], report["ann_byte_size"]) == (version, digest, size)
    blob = report["blob"]
    assert blob is not None, f"query for {source}'s weights v{version} got no reply"
    assert blob["version"] == version
    assert blob["digest"] == blob["recomputed_digest"] == digest
    assert blob["size"] == size
    assert blob["run_id"] == f"run-{source}"
    assert report["too_new_reply"] is None, "min_version above the served version must get no reply"


@pytest.mark.timeout(60)
def test_episode_crosses_both_ways(zenoh_router, make_episode) -> None:
    ns, T = "e2e-episode", 12
    sent = make_episode(T=T, seed=101, with_images=True, actor_id="parent")
    with ZenohBus(peer_config(zenoh_router, "peer", ns)) as bus:
        from_child = bus.subscribe(EPISODES_RAW, source="child")
        watch = bus.watch_alive(SERVICE)
        bus.declare_alive(SERVICE, "parent")
        with Child(episode_echo, zenoh_router, "client", ns, "child", "parent", 202, T) as child:
            child.wait_token(watch, "child", READY_S)

            # parent -> child
            n = bus.publish(EPISODES_RAW, sent, source="parent")
            key, parts, size, got = child.expect("episode", STEP_S)
            assert key == bus.key(EPISODES_RAW, source="parent")
            assert parts == {"source": "parent"}
            assert size == n == len(sent.encode())
            assert_messages_equal(got, sent)

            # child -> parent
            d = from_child.recv(timeout=STEP_S)
            assert d is not None, "no episode from the child"
            assert d.parts == {"source": "child"}
            assert d.size == child.expect("published", STEP_S)
            assert_messages_equal(d.message, make_episode(T=T, seed=202, with_images=True, actor_id="child"))
            assert d.message.images is not None and d.message.terminated[-1]

            assert child.finish() == 0
    assert bus.stats.bad["episodes_raw"] == 0


@pytest.mark.timeout(90)
def test_weights_cross_both_ways(zenoh_router) -> None:
    """Each side serves its own ~5 MB blob and announces it; the other fetches it on announcement."""
    ns, parent_version, child_version = "e2e-weights", 4, 9
    blob = build_weights(parent_version, nbytes=WEIGHTS_BYTES, seed=1, run_id="run-parent")
    payload = blob.encode()
    assert len(payload) >= WEIGHTS_BYTES - 4096
    with ZenohBus(peer_config(zenoh_router, "peer", ns)) as bus:
        bus.serve(WEIGHTS_LATEST, weights_handler(payload, parent_version), source="parent")
        announcements = bus.subscribe(WEIGHTS_ANNOUNCE, source="child")
        watch = bus.watch_alive(SERVICE)
        bus.declare_alive(SERVICE, "parent")
        args = (zenoh_router, "peer", ns, "child", "parent", child_version, WEIGHTS_BYTES, 2)
        with Child(weights_exchange, *args) as child:
            child.wait_token(watch, "child", READY_S)

            # parent -> child: announce; the child (holding no version) fetches and reports
            bus.publish(WEIGHTS_ANNOUNCE, blob.announcement(len(payload)), source="parent")
            _check_fetch(
                child.expect("fetched", STEP_S * 2),
                source="parent",
                version=parent_version,
                digest=blob.digest,
                size=len(payload),
            )

            # child -> parent: the child announces after its fetch; the parent (holding none) fetches
            theirs = child.expect("announced", STEP_S)
            d = announcements.recv(timeout=STEP_S)
            assert d is not None, "no weights announcement from the child"
            report = fetch_if_newer(bus, d, have_version=0, timeout=STEP_S)
            _check_fetch(
                report,
                source="child",
                version=child_version,
                digest=theirs["digest"],
                size=theirs["byte_size"],
            )
            assert theirs["digest"] != blob.digest
            # an announcement of a version we already hold is not fetched
            assert fetch_if_newer(bus, d, have_version=child_version, timeout=STEP_S)["newer"] is False

            assert child.finish() == 0
    assert bus.stats.bad["weights_latest"] == 0


@pytest.mark.timeout(60)
@pytest.mark.parametrize("child_mode", ["peer", "client"])
def test_liveliness_token_vanishes_when_child_is_killed(zenoh_router, child_mode) -> None:
    ns = "e2e-alive"
    with ZenohBus(peer_config(zenoh_router, "client", ns)) as bus:
        watch = bus.watch_alive(SERVICE)
        with Child(hold_token, zenoh_router, child_mode, ns, "victim") as child:
            pid = child.expect("ready", READY_S)
            assert pid == child.pid
            child.wait_token(watch, "victim", READY_S)

            t0 = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            gone = watch.wait_for(lambda alive: (SERVICE, "victim") not in alive, timeout=15.0)
            elapsed = time.monotonic() - t0
            assert gone, "the killed child's liveliness token was still present after 15 s"
            child.proc.join(10.0)
            assert child.proc.exitcode == -signal.SIGKILL
            print(f"token of SIGKILLed {child_mode} child gone after {elapsed * 1000:.1f} ms")


@pytest.mark.timeout(30)
@pytest.mark.parametrize("mode", ["peer", "client"])
def test_mode_works_against_router(zenoh_router, make_episode, make_weights, mode) -> None:
    ns = f"e2e-mode-{mode}"
    blob = make_weights(2)
    with (
        ZenohBus(peer_config(zenoh_router, mode, ns)) as a,
        ZenohBus(peer_config(zenoh_router, mode, ns)) as b,
    ):
        for bus in (a, b):
            assert bus.cfg.mode == mode
            assert len(list(bus.session.info.routers_zid())) == 1, "not connected to the router"
        sub = b.subscribe(EPISODES_RAW, source="a")
        b.serve(WEIGHTS_LATEST, weights_handler(blob.encode(), 2), source="b")
        b.declare_alive(SERVICE, "b")
        watch = a.watch_alive(SERVICE)
        assert watch.wait_for(lambda alive: (SERVICE, "b") in alive, timeout=10.0)

        ep = make_episode(T=3, seed=5, actor_id="a")
        a.publish(EPISODES_RAW, ep, source="a")
        d = sub.recv(timeout=10.0)
        assert d is not None
        assert_messages_equal(d.message, ep)

        reply = a.query(WEIGHTS_LATEST, {"min_version": "2"}, timeout=10.0, source="b")
        assert reply is not None and reply.message.digest == blob.digest
        assert a.query(WEIGHTS_LATEST, {"min_version": "3"}, timeout=10.0, source="b") is None
