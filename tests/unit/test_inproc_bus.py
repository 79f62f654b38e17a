"""InProcBus: routing, backpressure, bad payloads, query/serve, liveliness, namespaces, type checks."""

from __future__ import annotations

import threading

import pytest

from proto.control import Heartbeat
from proto.episode import Episode
from proto.msgpack_wire import ProtocolError, pack
from proto.topics import ALIVE, EPISODES_AUGMENTED, EPISODES_RAW, STATUS, WEIGHTS_ANNOUNCE, WEIGHTS_LATEST
from services.common.bus.inproc import Hub, InProcBus, key_matches
from tests.helpers import assert_messages_equal

pytestmark = [pytest.mark.unit, pytest.mark.timeout(30)]


@pytest.fixture
def bus():
    b = InProcBus(namespace="unit")
    try:
        yield b
    finally:
        b.close()


def heartbeat(instance: str = "hb-0") -> Heartbeat:
    return Heartbeat(
        service="test",
        instance_id=instance,
        pid=1,
        state="running",
        started_at=1.0,
        created_at=2.0,
        policy_version=-1,
        counters={"ticks": 3.0},
    )


# ------------------------------------------------------------------------------------------------
# key_matches
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("pattern", "key_expr", "expected"),
    [
        ("a/b/c", "a/b/c", True),
        ("a/b/c", "a/b/d", False),
        ("a/b", "a/b/c", False),
        ("a/b/c", "a/b", False),
        ("a/*/c", "a/x/c", True),
        ("a/*/c", "a/x/y/c", False),
        ("a/*", "a", False),
        ("a/**", "a/x/y/z", True),
        ("a/**", "a", True),
        ("a/**/z", "a/z", True),
        ("a/**/z", "a/x/y/z", True),
        ("a/**/z", "a/x/y", False),
        ("**", "anything/at/all", True),
        ("*/*", "a/b", True),
        ("*/*", "a/b/c", False),
        ("mea/v1/unit/episodes/raw/*", "mea/v1/unit/episodes/raw/actor-0", True),
        ("mea/v1/unit/episodes/raw/*", "mea/v1/other/episodes/raw/actor-0", False),
    ],
)
def test_key_matches(pattern: str, key_expr: str, expected: bool) -> None:
    assert key_matches(pattern, key_expr) is expected


# ------------------------------------------------------------------------------------------------
# pub/sub
# ------------------------------------------------------------------------------------------------


def test_wildcard_and_exact_subscriptions(bus, make_episode) -> None:
    any_source = bus.subscribe(EPISODES_RAW)
    only_a = bus.subscribe(EPISODES_RAW, source="actor-a")
    augmented = bus.subscribe(EPISODES_AUGMENTED)
    ep_a, ep_b = make_episode(T=3, seed=1, actor_id="actor-a"), make_episode(T=4, seed=2, actor_id="actor-b")

    n_a = bus.publish(EPISODES_RAW, ep_a, source="actor-a")
    n_b = bus.publish(EPISODES_RAW, ep_b, source="actor-b")

    got = any_source.drain()
    assert [d.parts for d in got] == [{"source": "actor-a"}, {"source": "actor-b"}]
    assert [d.key for d in got] == [bus.key(EPISODES_RAW, source=s) for s in ("actor-a", "actor-b")]
    assert [d.size for d in got] == [n_a, n_b] == [len(ep_a.encode()), len(ep_b.encode())]
    assert_messages_equal(got[0].message, ep_a)
    assert_messages_equal(got[1].message, ep_b)
    assert [d.message.episode_id for d in only_a.drain()] == [ep_a.episode_id]
    assert augmented.recv(timeout=0.0) is None
    assert bus.stats.published["episodes_raw"] == 2
    assert bus.stats.published_bytes["episodes_raw"] == n_a + n_b
    assert bus.stats.received["episodes_raw"] == 3  # two on `any_source`, one on `only_a`


def test_multi_placeholder_wildcard(bus) -> None:
    all_status = bus.subscribe(STATUS)
    actors = bus.subscribe(STATUS, service="actor")
    one = bus.subscribe(STATUS, instance="i-1")
    bus.publish(STATUS, heartbeat("i-0"), service="actor", instance="i-0")
    bus.publish(STATUS, heartbeat("i-1"), service="learner", instance="i-1")
    assert [d.parts for d in all_status.drain()] == [
        {"service": "actor", "instance": "i-0"},
        {"service": "learner", "instance": "i-1"},
    ]
    assert [d.parts["instance"] for d in actors.drain()] == ["i-0"]
    assert [d.parts["service"] for d in one.drain()] == ["learner"]


def test_recv_timeout_returns_none(bus) -> None:
    sub = bus.subscribe(EPISODES_RAW)
    assert sub.recv(timeout=0.0) is None
    assert sub.recv(timeout=0.05) is None
    assert sub.drain() == []


def test_closed_subscription_receives_nothing(bus, make_episode) -> None:
    sub = bus.subscribe(EPISODES_RAW)
    sub.close()
    bus.publish(EPISODES_RAW, make_episode(T=2), source="actor-0")
    assert sub.recv(timeout=0.0) is None


def test_backpressure_blocks_publisher_and_drops_nothing(bus, make_episode) -> None:
    capacity, n = 3, 12
    sub = bus.subscribe(EPISODES_RAW, capacity=capacity)
    episodes = [make_episode(T=2, seed=i) for i in range(n)]
    done = threading.Condition()
    published: list[int] = []
    errors: list[BaseException] = []

    def publisher() -> None:
        try:
            for i, ep in enumerate(episodes):
                bus.publish(EPISODES_RAW, ep, source="actor-0")
                with done:
                    published.append(i)
                    done.notify_all()
        except BaseException as exc:  # noqa: BLE001 - surfaced by the assertion below
            errors.append(exc)

    t = threading.Thread(target=publisher, daemon=True)
    t.start()
    try:
        with done:
            assert done.wait_for(lambda: len(published) >= capacity, timeout=10.0)
        # the queue is full: the next publish must be blocked inside push(), not dropped
        t.join(timeout=0.3)
        assert t.is_alive(), "publisher finished although the subscriber queue was full"
        assert len(published) == capacity
        assert sub.qsize() == capacity

        received = []
        for _ in range(n):
            d = sub.recv(timeout=10.0)
            assert d is not None, f"message {len(received)} never arrived"
            received.append(d.message.seed)
        t.join(timeout=10.0)
        assert not t.is_alive()
    finally:
        sub.close()  # unblocks the publisher if an assertion failed
        t.join(timeout=10.0)
    assert not errors
    assert received == list(range(n))
    assert sub.recv(timeout=0.0) is None
    assert bus.stats.published["episodes_raw"] == n
    assert bus.stats.received["episodes_raw"] == n


def test_closing_a_full_subscription_releases_a_blocked_publisher(bus, make_episode) -> None:
    sub = bus.subscribe(EPISODES_RAW, capacity=1)
    bus.publish(EPISODES_RAW, make_episode(T=2, seed=0), source="actor-0")
    t = threading.Thread(
        target=bus.publish,
        args=(EPISODES_RAW, make_episode(T=2, seed=1)),
        kwargs={"source": "actor-0"},
        daemon=True,
    )
    t.start()
    t.join(timeout=0.2)
    assert t.is_alive()
    sub.close()
    t.join(timeout=5.0)
    assert not t.is_alive()


# ------------------------------------------------------------------------------------------------
# bad payloads
# ------------------------------------------------------------------------------------------------


def test_bad_payloads_are_counted_reported_and_skipped(bus, make_episode) -> None:
    reports: list[tuple[str, str, ProtocolError]] = []
    bus.on_bad_message = lambda topic, key_expr, err: reports.append((topic.name, key_expr, err))
    sub = bus.subscribe(EPISODES_RAW)

    good = make_episode(T=3, seed=7)
    wire = good.to_wire()
    wire["actions"] = wire["actions"] * 0 + 2.0  # out of [-1, 1]
    out_of_range = pack({"_type": "Episode", "_v": Episode.VERSION, **wire})

    bus.publish(EPISODES_RAW, b"\xc1\xff garbage \x00", source="actor-0")  # not msgpack
    bus.publish(EPISODES_RAW, out_of_range, source="actor-0")
    bus.publish(EPISODES_RAW, heartbeat().encode(), source="actor-0")  # valid, but the wrong type
    bus.publish(EPISODES_RAW, good, source="actor-0")

    d = sub.recv(timeout=1.0)
    assert d is not None
    assert_messages_equal(d.message, good)
    assert sub.recv(timeout=0.0) is None

    assert bus.stats.bad["episodes_raw"] == 3
    assert bus.stats.received["episodes_raw"] == 1
    assert [r[0] for r in reports] == ["episodes_raw"] * 3
    assert all(r[1] == bus.key(EPISODES_RAW, source="actor-0") for r in reports)
    assert all(isinstance(r[2], ProtocolError) for r in reports)
    assert [r[2].field for r in reports] == ["<message>", "Episode.actions", "_type"]
    assert "above 1.0" in reports[1][2].problem


def test_bad_message_without_hook_is_still_counted(bus) -> None:
    sub = bus.subscribe(WEIGHTS_ANNOUNCE)
    bus.publish(WEIGHTS_ANNOUNCE, b"", source="learner-0")
    assert sub.recv(timeout=0.0) is None
    assert bus.stats.bad["weights_announce"] == 1


# ------------------------------------------------------------------------------------------------
# query/serve
# ------------------------------------------------------------------------------------------------


def test_query_serve(bus, make_weights) -> None:
    blob = make_weights(5, run_id="run-q")
    payload = blob.encode()
    seen: list[dict[str, str]] = []

    def handler(params: dict[str, str]):
        seen.append(params)
        return payload if int(params.get("min_version", "0")) <= blob.version else None

    assert bus.query(WEIGHTS_LATEST, {"min_version": "1"}) is None  # nobody serves yet
    server = bus.serve(WEIGHTS_LATEST, handler, source="learner-0")

    d = bus.query(WEIGHTS_LATEST, {"min_version": "5"})
    assert d is not None
    assert d.parts == {"source": "learner-0"}
    assert d.message.digest == blob.digest and d.message.version == 5
    assert d.size == len(payload)
    assert bus.query(WEIGHTS_LATEST, {"min_version": "6"}, source="learner-0") is None  # handler -> None
    assert bus.query(WEIGHTS_LATEST, source="learner-1") is None  # no such source
    assert seen == [{"min_version": "5"}, {"min_version": "6"}]

    server.close()
    assert bus.query(WEIGHTS_LATEST) is None
    assert bus.stats.received["weights_latest"] == 1


def test_query_takes_first_valid_reply(bus, make_weights) -> None:
    blob = make_weights(2)
    bus.serve(WEIGHTS_LATEST, lambda params: None, source="a-silent")
    bus.serve(WEIGHTS_LATEST, lambda params: b"not a blob", source="b-broken")
    bus.serve(WEIGHTS_LATEST, lambda params: blob, source="c-good")  # a Message is encoded by the bus
    d = bus.query(WEIGHTS_LATEST)
    assert d is not None and d.parts == {"source": "c-good"} and d.message.digest == blob.digest
    assert bus.stats.bad["weights_latest"] == 1


def test_a_raising_query_handler_answers_nothing_like_zenoh(bus, make_weights) -> None:
    blob = make_weights(3)

    def boom(params):
        raise RuntimeError("handler bug")

    bus.serve(WEIGHTS_LATEST, boom, source="a-raises")
    assert bus.query(WEIGHTS_LATEST) is None
    bus.serve(WEIGHTS_LATEST, lambda params: blob, source="b-good")
    d = bus.query(WEIGHTS_LATEST)
    assert d is not None and d.message.version == 3


def test_serving_one_key_twice_is_refused(bus, make_weights) -> None:
    bus.serve(WEIGHTS_LATEST, lambda params: None, source="l0")
    with pytest.raises(ValueError, match="already served"):
        bus.serve(WEIGHTS_LATEST, lambda params: None, source="l0")


def test_query_across_buses_on_one_hub(make_weights) -> None:
    hub = Hub()
    learner, actor = InProcBus(hub), InProcBus(hub)
    blob = make_weights(3)
    learner.serve(WEIGHTS_LATEST, lambda params: blob.encode(), source="learner-0")
    d = actor.query(WEIGHTS_LATEST, {"min_version": "3"})
    assert d is not None and d.message.version == 3
    learner.close()
    assert actor.query(WEIGHTS_LATEST) is None


# ------------------------------------------------------------------------------------------------
# liveliness
# ------------------------------------------------------------------------------------------------


def test_liveliness_declare_close_watch(bus) -> None:
    actors = bus.watch_alive("actor")
    everyone = bus.watch_alive()
    assert actors.alive() == set()

    a0 = bus.declare_alive("actor", "a0")
    learner = bus.declare_alive("learner", "l0")
    assert actors.alive() == {("actor", "a0")}
    assert everyone.alive() == {("actor", "a0"), ("learner", "l0")}
    assert actors.events.get_nowait() == ("actor", "a0", True)

    late = bus.watch_alive("actor")  # sees tokens declared before it
    assert late.alive() == {("actor", "a0")}

    twin = bus.declare_alive("actor", "a0")  # same key twice: alive until both are closed
    a0.close()
    assert ("actor", "a0") in actors.alive()
    twin.close()
    assert actors.wait_for(lambda alive: ("actor", "a0") not in alive, timeout=1.0)
    assert actors.events.get_nowait() == ("actor", "a0", False)
    assert actors.events.empty()
    assert late.alive() == set()
    a0.close()  # closing twice is harmless
    assert everyone.alive() == {("learner", "l0")}

    learner.close()
    assert everyone.alive() == set()


def test_wait_for_times_out(bus) -> None:
    watch = bus.watch_alive("actor")
    assert watch.wait_for(lambda alive: ("actor", "nobody") in alive, timeout=0.1) is False


def test_closed_watch_stops_updating(bus) -> None:
    watch = bus.watch_alive("actor")
    watch.close()
    bus.declare_alive("actor", "a1")
    assert watch.alive() == set()


def test_bus_close_releases_tokens_and_subscriptions(make_episode) -> None:
    hub = Hub()
    a, b = InProcBus(hub), InProcBus(hub)
    watch = b.watch_alive()
    sub = a.subscribe(EPISODES_RAW)
    a.declare_alive("actor", "a0")
    assert watch.alive() == {("actor", "a0")}
    a.close()
    assert watch.alive() == set()
    b.publish(EPISODES_RAW, make_episode(T=2), source="actor-0")
    assert sub.recv(timeout=0.0) is None
    b.close()


# ------------------------------------------------------------------------------------------------
# namespaces
# ------------------------------------------------------------------------------------------------


def test_namespaces_on_one_hub_are_isolated(make_episode, make_weights) -> None:
    hub = Hub()
    run_a, run_a2, run_b = InProcBus(hub, namespace="run-a"), InProcBus(hub, "run-a"), InProcBus(hub, "run-b")
    try:
        sub_a2, sub_b = run_a2.subscribe(EPISODES_RAW), run_b.subscribe(EPISODES_RAW)
        watch_a2, watch_b = run_a2.watch_alive(), run_b.watch_alive()
        run_a.serve(WEIGHTS_LATEST, lambda params: make_weights(1).encode(), source="learner-0")
        run_a.declare_alive("learner", "learner-0")
        run_a.publish(EPISODES_RAW, make_episode(T=2), source="actor-0")

        d = sub_a2.recv(timeout=0.0)
        assert d is not None and d.key.startswith("mea/v1/run-a/")
        assert sub_b.recv(timeout=0.0) is None
        assert run_a2.query(WEIGHTS_LATEST) is not None
        assert run_b.query(WEIGHTS_LATEST) is None
        assert watch_a2.alive() == {("learner", "learner-0")}
        assert watch_b.alive() == set()
        assert run_b.stats.received["episodes_raw"] == 0
    finally:
        for b in (run_a, run_a2, run_b):
            b.close()


# ------------------------------------------------------------------------------------------------
# type checks
# ------------------------------------------------------------------------------------------------


def test_wrong_message_type_raises(bus) -> None:
    sub = bus.subscribe(EPISODES_RAW)
    with pytest.raises(TypeError, match="episodes_raw"):
        bus.publish(EPISODES_RAW, heartbeat(), source="actor-0")
    assert sub.recv(timeout=0.0) is None
    assert bus.stats.published["episodes_raw"] == 0


def test_wrong_topic_kind_raises(bus, make_episode) -> None:
    with pytest.raises(TypeError):
        bus.publish(WEIGHTS_LATEST, make_episode(T=2), source="learner-0")
    with pytest.raises(TypeError):
        bus.subscribe(WEIGHTS_LATEST)
    with pytest.raises(TypeError):
        bus.serve(EPISODES_RAW, lambda params: None, source="actor-0")
    with pytest.raises(TypeError):
        bus.query(STATUS)
    with pytest.raises(TypeError):
        bus.publish(ALIVE, b"", service="actor", instance="a0")


def test_bad_key_parts_raise(bus, make_episode) -> None:
    ep = make_episode(T=2)
    with pytest.raises(ValueError):
        bus.publish(EPISODES_RAW, ep)  # missing `source`
    with pytest.raises(ValueError):
        bus.publish(EPISODES_RAW, ep, source="bad/slash")
    with pytest.raises(ValueError):
        bus.publish(EPISODES_RAW, ep, source="actor-0", extra="x")
    with pytest.raises(ValueError):
        InProcBus(namespace="bad namespace").publish(EPISODES_RAW, ep, source="actor-0")


def test_rejected_messages_are_all_counted_but_logged_at_most_once_per_topic_in_a_while(bus, caplog) -> None:
    from services.common.bus.base import LogLimiter

    sub = bus.subscribe(STATUS, capacity=2_000)
    with caplog.at_level("WARNING", logger="services.common.bus.base"):
        for k in range(1_000):
            bus.publish(STATUS, pack({"not": "a heartbeat", "k": k}), service="svc", instance=f"i-{k}")
        assert sub.drain() == []
    assert bus.stats.bad[STATUS.name] == 1_000
    assert len([r for r in caplog.records if r.getMessage() == "rejected message"]) == 1
    limiter = LogLimiter(seconds=5.0)
    assert [limiter.allow("t", now) for now in (0.0, 4.9, 5.0, 5.1, 10.2)] == [True, False, True, False, True]
    assert limiter.allow("other", 5.1)
