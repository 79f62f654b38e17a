"""Queries that carry a request message (``Bus.answer`` / ``Bus.call``: SERVE_RESET, SERVE_ACT), on the
in-process bus and over Zenoh: the request reaches the server's handler decoded and checked, its reply
comes back decoded and checked; with the run's key only a `robot` may ask and only an `inference` server
answering on its own key is believed, and every refusal is counted.

The Zenoh buses are peers of this process: the server listens on a free 127.0.0.1 port, every other
bus connects to it; multicast scouting is off and nothing else is connected, so the tests stay off any
other Zenoh network on the host. A caller waits for the server's liveliness token, declared after its
queryable, before it asks (as in ``tests.helpers.zenoh_peer``).
"""

from __future__ import annotations

import dataclasses
import threading
import uuid
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from proto.inference import ActReply, ActRequest, ResetReply, ResetRequest
from proto.topics import ESTOP, SERVE_ACT, SERVE_RESET, WEIGHTS_LATEST, Topic, key
from services.common.bus.base import Bus, Credentials, Delivery
from services.common.bus.inproc import Hub, InProcBus
from tests.helpers import find_free_port
from tests.helpers.wire_asserts import assert_same

pytestmark = [pytest.mark.unit, pytest.mark.timeout(60)]

KEY = bytes(range(32))
OTHER = bytes(range(1, 33))
SERVER = "inference-0"
WAIT = 5.0
"""Bound of every wait for the other side (seconds)."""
CALL_TIMEOUT = 3.0


# ------------------------------------------------------------------------------------------------
# networks of buses
# ------------------------------------------------------------------------------------------------


class Net:
    """Buses that reach each other: in process (one Hub), or Zenoh peers of which the first listens
    on a free 127.0.0.1 port and the others connect to it."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.hub = Hub()
        self.namespace = f"req-{uuid.uuid4().hex[:12]}"
        self.endpoint = ""
        self.buses: list[Bus] = []

    def bus(self, service: str | None = None, instance: str = "", key: bytes | None = KEY) -> Bus:
        """A new member, authenticated as ``service/instance`` with ``key`` when ``service`` is given."""
        bus = InProcBus(self.hub, namespace=self.namespace) if self.kind == "inproc" else self._zenoh()
        self.buses.append(bus)
        if service is not None and key is not None:
            bus.authenticate(Credentials(key, service, instance))
        return bus

    def _zenoh(self) -> Bus:
        import zenoh

        from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig

        if self.endpoint:
            return ZenohBus(ZenohConfig(mode="peer", connect=(self.endpoint,), namespace=self.namespace))
        last: Exception | None = None
        for _ in range(5):  # the port was free a moment ago; another process may have taken it since
            endpoint = f"tcp/127.0.0.1:{find_free_port()}"
            try:
                # connect == listen: ZenohConfig drops a connect endpoint it listens on, so this peer
                # connects nowhere (not to the default router either)
                bus = ZenohBus(ZenohConfig(mode="peer", listen=(endpoint,), connect=(endpoint,),
                                           namespace=self.namespace))  # fmt: skip
            except zenoh.ZError as exc:
                last = exc
                continue
            self.endpoint = endpoint
            return bus
        raise RuntimeError(f"no Zenoh peer could listen on 127.0.0.1: {last}")

    def close(self) -> None:
        for bus in reversed(self.buses):
            bus.close()


@pytest.fixture(params=["inproc", "zenoh"])
def net(request) -> Iterator[Net]:
    n = Net(request.param)
    try:
        yield n
    finally:
        n.close()


# ------------------------------------------------------------------------------------------------
# messages and servers
# ------------------------------------------------------------------------------------------------


def act_request(step: int = 0, session: str = "robot-0", **obs: object) -> ActRequest:
    if not obs:
        obs = {"points": np.arange(2 * 4 * 3, dtype=np.float32).reshape(2, 4, 3) / 100,
               "point_counts": np.array([4, 17], np.int32)}  # fmt: skip
    return ActRequest(
        session=session,
        episode=1,
        step=step,
        stamp=1_700_000_000.5,
        state=np.array([0.5, 0.0, 0.12, 0.3, 1.0], np.float32),
        executed=None if step == 0 else np.array([1.0, 0.2, 0.0, 0.0, -0.5], np.float32),
        **obs,
    )


def act_reply(req: ActRequest) -> ActReply:
    action = np.array([1.0, 0.1 * (req.step % 10), -0.25, 0.0, 0.5], np.float32)
    return ActReply(session=req.session, episode=req.episode, step=req.step, action=action, policy_version=3,
                    held=False, reasons=["workspace_z"], compute_seconds=0.001)  # fmt: skip


RESET = ResetRequest(session="robot-0", task="block_pull", created_at=1_700_000_000.0)


def reset_reply(req: ResetRequest) -> ResetReply:
    return ResetReply(session=req.session, accepted=True, reason="", episode=1, policy_version=3,
                      run_id="run-0", observation="voxel")  # fmt: skip


class Handler:
    """Records every request it is given and answers with ``reply(request)``."""

    def __init__(self, reply: Callable[[object], object] = act_reply) -> None:
        self.reply = reply
        self.seen: list[Delivery] = []
        self._lock = threading.Lock()

    def __call__(self, d: Delivery):
        with self._lock:
            self.seen.append(d)
        return self.reply(d.message)


def answer(server: Bus, handler: Handler, topic: Topic = SERVE_ACT, instance: str = SERVER):
    """Answer ``topic`` at ``instance``'s key, then hold that instance's liveliness token (last)."""
    handle = server.answer(topic, handler, source=instance)
    server.declare_alive("inference", instance)
    return handle


def wait_for_server(caller: Bus, instance: str = SERVER) -> None:
    watch = caller.watch_alive("inference")
    assert watch.wait_for(lambda alive: ("inference", instance) in alive, WAIT), "the server never appeared"


def call(caller: Bus, request, topic: Topic = SERVE_ACT, timeout: float = CALL_TIMEOUT) -> Delivery | None:
    return caller.call(topic, request, timeout=timeout, source=SERVER)


# ------------------------------------------------------------------------------------------------
# requests and replies
# ------------------------------------------------------------------------------------------------


def test_a_request_reaches_the_handler_and_the_reply_comes_back(net: Net) -> None:
    server, robot = net.bus(), net.bus()
    handler = Handler()
    answer(server, handler)
    wait_for_server(robot)
    requests = [act_request(0), act_request(1, image=np.full((2, 84, 84), 7, np.uint8))]
    for req in requests:
        got = call(robot, req)
        assert got is not None, "no reply"
        assert isinstance(got.message, ActReply)
        assert_same(got.message, act_reply(req))
        assert got.key == key(SERVE_ACT, net.namespace, source=SERVER) and got.parts == {"source": SERVER}
        assert got.sender == ""  # nothing sealed without the run's key
    assert len(handler.seen) == 2
    for d, req in zip(handler.seen, requests, strict=True):
        assert isinstance(d.message, ActRequest)
        assert_same(d.message, req)  # decoded, arrays and all
        assert d.parts == {"source": SERVER} and d.sender == ""
    assert robot.stats.published["serve_act"] == 2 and robot.stats.received["serve_act"] == 2
    assert server.stats.received["serve_act"] == 2
    assert server.stats.bad["serve_act"] == 0 and robot.stats.bad["serve_act"] == 0


def test_a_request_with_any_float_state_arrives_bit_for_bit(net: Net) -> None:
    server, robot = net.bus(), net.bus()
    handler = Handler()
    answer(server, handler)
    wait_for_server(robot)
    bits = np.array([0x7FC0BEEF, 0xFF800000, 0x7F800000, 0x80000000, 0x3F800000], np.uint32)
    req = act_request(2, image=np.zeros((3, 64, 64), np.uint8))
    req = dataclasses.replace(req, state=bits.view(np.float32))  # NaN with a payload, -inf, inf, -0.0, 1.0
    assert call(robot, req) is not None
    assert np.array_equal(np.asarray(handler.seen[0].message.state).view(np.uint32), bits)


def test_reset_and_act_are_served_side_by_side(net: Net) -> None:
    server, robot = net.bus("inference", SERVER), net.bus("robot", "robot-0")
    resets, acts = Handler(reset_reply), Handler()
    server.answer(SERVE_RESET, resets, source=SERVER)
    answer(server, acts)
    wait_for_server(robot)
    got = call(robot, RESET, SERVE_RESET)
    assert got is not None and got.message == reset_reply(RESET) and got.sender == f"inference/{SERVER}"
    assert resets.seen[0].message == RESET and resets.seen[0].sender == "robot/robot-0"
    got = call(robot, act_request(0))
    assert got is not None and isinstance(got.message, ActReply)
    assert len(resets.seen) == 1 and len(acts.seen) == 1  # each request reached its own handler only


def test_the_runs_robot_is_answered_and_both_sides_see_who(net: Net) -> None:
    server, robot = net.bus("inference", SERVER), net.bus("robot", "robot-0")
    handler = Handler()
    answer(server, handler)
    wait_for_server(robot)
    got = call(robot, act_request(0))
    assert got is not None and got.sender == f"inference/{SERVER}"
    assert handler.seen[0].sender == "robot/robot-0"
    assert server.stats.unauthenticated["serve_act"] == 0 and robot.stats.unauthenticated["serve_act"] == 0


@pytest.mark.parametrize(
    ("service", "instance", "run_key"),
    [
        ("actor", "actor-0", KEY),  # of the run, but not a requester
        ("inference", "inference-1", KEY),  # a server does not ask another server
        ("operator", "operator-0", KEY),
        ("robot", "robot-0", OTHER),  # another run's key
        (None, "", None),  # not sealed at all
    ],
    ids=["actor", "other-server", "operator", "other-key", "unsealed"],
)
def test_a_request_from_outside_the_runs_robots_is_refused_and_counted(
    net: Net, service: str | None, instance: str, run_key: bytes | None
) -> None:
    server, robot = net.bus("inference", SERVER), net.bus("robot", "robot-0")
    rogue = net.bus(service, instance, run_key)
    handler = Handler()
    answer(server, handler)
    wait_for_server(rogue)
    wait_for_server(robot)
    assert call(rogue, act_request(0, session="robot-0")) is None
    assert handler.seen == [], "a refused request reached the handler"
    assert server.stats.unauthenticated["serve_act"] == 1 and server.stats.bad["serve_act"] == 1
    assert server.stats.received["serve_act"] == 0
    # the server keeps answering the run's robot
    assert call(robot, act_request(1)) is not None
    assert len(handler.seen) == 1 and handler.seen[0].sender == "robot/robot-0"
    assert server.stats.unauthenticated["serve_act"] == 1


@pytest.mark.parametrize(
    ("service", "instance", "run_key"),
    [
        ("actor", SERVER, KEY),  # of the run, but not an inference server
        ("inference", "inference-1", KEY),  # an inference server answering on another server's key
        (None, "", None),  # a server without the run's key: its reply is not sealed
    ],
    ids=["actor", "other-server", "unsealed"],
)
def test_a_reply_not_sealed_by_the_inference_server_is_refused_by_the_caller(
    net: Net, service: str | None, instance: str, run_key: bytes | None
) -> None:
    server, robot = net.bus(service, instance, run_key), net.bus("robot", "robot-0")
    handler = Handler()
    answer(server, handler)
    wait_for_server(robot)
    assert call(robot, act_request(0)) is None
    assert len(handler.seen) == 1  # the request itself was fine
    assert robot.stats.unauthenticated["serve_act"] == 1 and robot.stats.bad["serve_act"] == 1
    assert robot.stats.received["serve_act"] == 0


def test_a_request_the_decoder_refuses_is_counted_but_not_as_unauthenticated(net: Net) -> None:
    server, robot = net.bus("inference", SERVER), net.bus("robot", "robot-0")
    handler = Handler()
    answer(server, handler)
    wait_for_server(robot)
    both = act_request(0, points=np.zeros((1, 2, 3), np.float32), point_counts=np.zeros(1, np.int32),
                       image=np.zeros((2, 4, 4), np.uint8))  # fmt: skip
    assert call(robot, both) is None  # sent as is: a message is checked when decoded, not when encoded
    assert handler.seen == []
    assert server.stats.bad["serve_act"] == 1 and server.stats.unauthenticated["serve_act"] == 0


def test_no_reply_when_the_handler_declines_or_fails_and_the_server_keeps_answering(net: Net) -> None:
    def reply(req: ActRequest):
        if req.step == 1:
            return None
        if req.step == 2:
            raise RuntimeError("handler bug (expected in this test)")
        return act_reply(req)

    server, robot = net.bus(), net.bus()
    handler = Handler(reply)
    answer(server, handler)
    wait_for_server(robot)
    assert call(robot, act_request(1)) is None
    assert call(robot, act_request(2)) is None
    got = call(robot, act_request(3))
    assert got is not None and got.message.step == 3
    assert [d.message.step for d in handler.seen] == [1, 2, 3]


def test_no_server_no_reply(net: Net) -> None:
    robot = net.bus()
    assert call(robot, act_request(0), timeout=0.5) is None
    assert robot.stats.received["serve_act"] == 0


def test_a_closed_server_no_longer_answers(net: Net) -> None:
    server, robot = net.bus(), net.bus()
    handler = Handler()
    handle = answer(server, handler)
    wait_for_server(robot)
    assert call(robot, act_request(0)) is not None
    handle.close()
    assert call(robot, act_request(1), timeout=1.0) is None
    assert len(handler.seen) == 1


def test_a_key_is_answered_once_per_bus(net: Net) -> None:
    server = net.bus()
    server.answer(SERVE_ACT, Handler(), source=SERVER)
    with pytest.raises(ValueError):
        server.answer(SERVE_ACT, Handler(), source=SERVER)
    server.answer(SERVE_RESET, Handler(reset_reply), source=SERVER)  # another topic, same instance: fine


# ------------------------------------------------------------------------------------------------
# wrong use
# ------------------------------------------------------------------------------------------------


def test_request_topics_and_plain_topics_are_not_interchangeable(net: Net) -> None:
    bus = net.bus("robot", "robot-0")
    req = act_request(0)
    with pytest.raises(TypeError):
        bus.call(WEIGHTS_LATEST, req, source="learner-0")  # a plain query: no request
    with pytest.raises(TypeError):
        bus.call(ESTOP, req, source="operator-0")  # not a query
    with pytest.raises(TypeError):
        bus.query(SERVE_ACT, source=SERVER)  # SERVE_ACT needs a request: call
    with pytest.raises(TypeError):
        bus.query(SERVE_RESET, timeout=0.1)
    with pytest.raises(TypeError):
        bus.serve(SERVE_ACT, lambda params: None, source=SERVER)  # answer, not serve
    with pytest.raises(TypeError):
        bus.answer(WEIGHTS_LATEST, Handler(), source="learner-0")
    with pytest.raises(TypeError):
        bus.answer(ESTOP, Handler(), source="operator-0")
    with pytest.raises(TypeError):
        bus.publish(SERVE_ACT, act_reply(req), source=SERVER)
    assert sum(bus.stats.published.values()) == 0, "nothing is sent after a TypeError"


def test_a_call_carries_only_its_topics_request_type(net: Net) -> None:
    bus = net.bus()
    with pytest.raises(TypeError):
        bus.call(SERVE_ACT, RESET, source=SERVER)
    with pytest.raises(TypeError):
        bus.call(SERVE_RESET, act_request(0), source=SERVER)
    with pytest.raises(TypeError):
        bus.call(SERVE_ACT, act_reply(act_request(0)), source=SERVER)  # a reply is not a request
    assert sum(bus.stats.published.values()) == 0
