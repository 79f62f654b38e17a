"""The bus interface every service is wired to, with two implementations (in-process, Zenoh).

Messages are always encoded on publish and decoded (validated) on receive, in-process too, so the
same wire rules apply in unit tests and in production. Transport threads only enqueue bytes;
decoding happens in the consumer's thread when it calls ``recv``.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from proto.codec import Message
from proto.msgpack_wire import DEFAULT_LIMITS, Limits, ProtocolError
from proto.seal import is_sealed, seal, unseal
from proto.topics import ALIVE, Kind, Topic, key, may_request, may_write, parse

log = logging.getLogger(__name__)

SLOW_READER_WARN_S = 5.0
"""A transport thread that has waited this long on a full subscription says so, once per message."""

BadMessageHook = Callable[[Topic, str, ProtocolError], None]


class Handle(Protocol):
    def close(self) -> None: ...


@dataclass(frozen=True)
class Delivery:
    """One decoded message, the key it arrived on and, when sealed, who sent it
    (``<service>/<instance>``; verified when the bus holds the run's key)."""

    key: str
    parts: dict[str, str]
    message: Message
    size: int
    sender: str = ""


@dataclass(frozen=True)
class Credentials:
    """The run's key and this service's identity: with them a bus seals everything it sends and
    accepts only messages sealed with the same key by a service allowed to write the topic."""

    key: bytes = field(repr=False)
    service: str
    instance: str


@dataclass
class BusStats:
    """Plain counters by topic name; services mirror them into Prometheus."""

    published: Counter = field(default_factory=Counter)
    published_bytes: Counter = field(default_factory=Counter)
    received: Counter = field(default_factory=Counter)
    received_bytes: Counter = field(default_factory=Counter)
    bad: Counter = field(default_factory=Counter)
    unauthenticated: Counter = field(default_factory=Counter)
    """Of ``bad``: refused because the seal or the sender was not valid for this run."""


class Subscription:
    """Between a transport thread and the consumer.

    Data topics (episodes): a bounded FIFO. When it is full the transport thread waits (it never
    drops accepted data): with BLOCK congestion control this pushes back on the publisher.
    Consumers must keep draining.

    Latest-value topics (``QoS.latest_only``: gates, weights announcements, heartbeats): only the
    newest message per key (per sender) is kept, and a push never waits, so a flood on one of them
    cannot stall the transport thread that also delivers everything else. Keys are served oldest
    first, so one busy sender does not starve the others.
    """

    def __init__(self, bus: Bus, topic: Topic, capacity: int) -> None:
        self._bus = bus
        self._topic = topic
        self._latest = topic.qos.latest_only
        self._q: queue.Queue[tuple[str, bytes]] = queue.Queue(maxsize=capacity)
        self._newest: dict[str, bytes] = {}  # latest-value topics: key -> newest payload, oldest key first
        self._cond = threading.Condition()
        self._closed = threading.Event()
        self._undeclare: Callable[[], None] | None = None
        self.replaced = 0
        """Latest-value topics: messages superseded by a newer one from the same sender before they were read."""

    # transport side -------------------------------------------------------------------------
    def push(self, key_expr: str, payload: bytes) -> None:
        if self._latest:
            # checked before it may replace the sender's newest: a forgery must not displace a real one;
            # recv checks again, for what arrived before the bus was given its credentials
            if not self._bus.admit(self._topic, key_expr, payload):
                return
            with self._cond:
                if self._newest.pop(key_expr, None) is not None:
                    self.replaced += 1
                self._newest[key_expr] = payload
                self._cond.notify()
            return
        waiting_since, warned = time.monotonic(), False
        while not self._closed.is_set():
            try:
                self._q.put((key_expr, payload), timeout=0.1)
                return
            except queue.Full:
                if not warned and time.monotonic() - waiting_since > SLOW_READER_WARN_S:
                    warned = True
                    log.warning(
                        "a subscription has been full for %.0f s: its consumer is not reading, and Zenoh "
                        "closes a transport whose reader waits past its lease (about 10 s)",
                        SLOW_READER_WARN_S, extra={"topic": self._topic.name},
                    )  # fmt: skip

    def _get(self, timeout: float | None) -> tuple[str, bytes]:
        """The next raw (key, payload); raises queue.Empty after ``timeout`` (0: do not wait)."""
        if not self._latest:
            return self._q.get(timeout=timeout) if timeout != 0.0 else self._q.get_nowait()
        with self._cond:
            if not self._newest and timeout != 0.0:
                self._cond.wait_for(lambda: bool(self._newest), timeout)
            if not self._newest:
                raise queue.Empty
            key_expr = next(iter(self._newest))
            return key_expr, self._newest.pop(key_expr)

    # consumer side --------------------------------------------------------------------------
    def qsize(self) -> int:
        if self._latest:
            with self._cond:
                return len(self._newest)
        return self._q.qsize()

    def recv(self, timeout: float | None = None) -> Delivery | None:
        """Next valid message, or None after ``timeout`` seconds. Bad messages are counted and skipped."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                key_expr, payload = self._get(remaining)
            except queue.Empty:
                return None
            delivery = self._bus.decode_delivery(self._topic, key_expr, payload)
            if delivery is not None:
                return delivery

    def drain(self, max_items: int = 1_000_000) -> list[Delivery]:
        out = []
        while len(out) < max_items:
            d = self.recv(timeout=0.0)
            if d is None:
                break
            out.append(d)
        return out

    def close(self) -> None:
        self._closed.set()
        if self._undeclare is not None:
            self._undeclare()
            self._undeclare = None


class AliveWatch:
    """Tracks which (service, instance) liveliness tokens exist; transport threads only update a set."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._alive: set[tuple[str, str]] = set()
        self._came_alive: dict[tuple[str, str], float] = {}  # who -> monotonic time its token appeared
        self.events: queue.Queue[tuple[str, str, bool]] = queue.Queue()
        self._undeclare: Callable[[], None] | None = None

    def update(self, key_expr: str, alive: bool) -> None:
        try:
            topic, _, parts = parse(key_expr)
        except ValueError:
            return
        if topic is not ALIVE:
            return
        who = (parts["service"], parts["instance"])
        with self._lock:
            (self._alive.add if alive else self._alive.discard)(who)
            if alive:
                self._came_alive[who] = time.monotonic()
        self.events.put((*who, alive))

    def came_alive(self, services: tuple[str, ...]) -> float | None:
        """``time.monotonic()`` when the newest token of one of ``services`` appeared (None: never)."""
        with self._lock:
            times = [t for (svc, _), t in self._came_alive.items() if svc in services]
        return max(times, default=None)

    def alive(self) -> set[tuple[str, str]]:
        with self._lock:
            return set(self._alive)

    def wait_for(self, predicate: Callable[[set[tuple[str, str]]], bool], timeout: float) -> bool:
        """Poll the alive set until ``predicate`` holds or ``timeout`` passes."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self.alive()):
                return True
            with contextlib.suppress(queue.Empty):
                self.events.get(timeout=0.05)
        return predicate(self.alive())

    def close(self) -> None:
        if self._undeclare is not None:
            self._undeclare()
            self._undeclare = None


QueryHandler = Callable[[dict[str, str]], "Message | bytes | None"]
RequestHandler = Callable[[Delivery], "Message | bytes | None"]
"""Answers a query that carries a request message (``Topic.request``): the decoded, checked request
in, the reply (or None: no reply) out."""


class LogLimiter:
    """At most one log line per key every ``seconds`` (a flood of bad messages must not flood the logs;
    the exact counts live in the metrics)."""

    def __init__(self, seconds: float = 5.0) -> None:
        self.seconds = seconds
        self._last: dict[str, float] = {}

    def allow(self, key: str, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        last = self._last.get(key)
        if last is not None and now - last < self.seconds:
            return False
        self._last[key] = now
        return True


class Bus(ABC):
    """Publish/subscribe, query/serve and liveliness over typed topics."""

    def __init__(self, namespace: str = "default", limits: Limits = DEFAULT_LIMITS) -> None:
        self.namespace = namespace
        self.limits = limits
        self.stats = BusStats()
        self.on_bad_message: BadMessageHook | None = None
        self._reject_log = LogLimiter()
        self.credentials: Credentials | None = None
        self.caps: dict[str, int] = {}
        """Per-topic size caps replacing ``Topic.max_bytes`` (``ServiceConfig.topic_caps``)."""

    def authenticate(self, credentials: Credentials) -> None:
        """From now on seal what this bus sends and accept only what the run's services sealed
        (messages already queued are checked when read, so nothing slips in before this call)."""
        self.credentials = credentials

    # helpers shared by implementations -------------------------------------------------------
    def key(self, topic: Topic, **parts: str) -> str:
        return key(topic, self.namespace, **parts)

    def wildcard_key(self, topic: Topic, parts: dict[str, str]) -> str:
        full = {p: parts.get(p, "*") for p in topic.placeholders}
        return key(topic, self.namespace, **full)

    def _seal(self, key_expr: str, body: bytes) -> bytes:
        c = self.credentials
        return body if c is None else seal(c.key, key_expr, c.service, c.instance, body)

    def encode_for(self, topic: Topic, msg: Message | bytes, key_expr: str) -> bytes:
        if isinstance(msg, (bytes, bytearray)):
            return self._seal(key_expr, bytes(msg))  # pre-encoded (e.g. a weights blob served many times)
        if topic.message is None or not isinstance(msg, topic.message):
            raise TypeError(f"{topic.name} carries {topic.message}, not {type(msg).__name__}")
        return self._seal(key_expr, msg.encode())

    def encode_request(self, topic: Topic, msg: Message, key_expr: str) -> bytes:
        if topic.request is None or not isinstance(msg, topic.request):
            raise TypeError(f"{topic.name} requests carry {topic.request}, not {type(msg).__name__}")
        return self._seal(key_expr, msg.encode())

    def _open(self, topic: Topic, key_expr: str, parts: dict[str, str], payload: bytes,
              request: bool = False) -> tuple[str, bytes]:  # fmt: skip
        """(sender, body): with credentials the seal must verify and the sender may write here (or,
        for a ``request``, may ask); without, a seal is only read (the sender is then unverified)."""
        c = self.credentials
        if c is None and not is_sealed(payload):
            return "", payload
        s = unseal(None if c is None else c.key, key_expr, payload)
        if c is not None:
            why = may_request(topic, s.service) if request else may_write(topic, parts, s.service, s.instance)
            if why is not None:
                raise ProtocolError("<sender>", why)
        return s.sender, s.body

    def _check_size(self, topic: Topic, payload: bytes) -> None:
        cap = self.caps.get(topic.name, topic.max_bytes)
        if len(payload) > cap:
            raise ProtocolError("<message>", f"{len(payload)} bytes over the {topic.name} cap {cap}")

    def admit(self, topic: Topic, key_expr: str, payload: bytes) -> bool:
        """Whether a payload is sealed for this run by a sender allowed here (always True without
        credentials); a refusal is counted like any bad message. Cheap for small messages."""
        if self.credentials is None:
            return True
        try:
            self._check_size(topic, payload)
            _, _, parts = parse(key_expr)
            self._open(topic, key_expr, parts, payload)
        except (ProtocolError, ValueError) as exc:
            self._reject(topic, key_expr, exc)
            return False
        return True

    def _reject(self, topic: Topic, key_expr: str, exc: Exception) -> None:
        err = exc if isinstance(exc, ProtocolError) else ProtocolError("<key>", str(exc))
        self.stats.bad[topic.name] += 1
        if err.field in ("<seal>", "<sender>"):
            self.stats.unauthenticated[topic.name] += 1
        if self._reject_log.allow(topic.name):  # counts stay exact; the log is rate-limited
            log.warning("rejected message", extra={"topic": topic.name, "key": key_expr, "error": str(err),
                                                   "rejected_total": self.stats.bad[topic.name]})  # fmt: skip
        if self.on_bad_message is not None:
            self.on_bad_message(topic, key_expr, err)

    def decode_delivery(
        self, topic: Topic, key_expr: str, payload: bytes, request: bool = False
    ) -> Delivery | None:
        """The message in ``payload`` (with ``request``: the request a query carried, whose sender must
        be one of ``topic.requesters``), checked for size, seal, sender and schema; None (counted,
        logged) when refused."""
        try:
            self._check_size(topic, payload)
            _, _, parts = parse(key_expr)
            sender, body = self._open(topic, key_expr, parts, payload, request)
            cls = topic.request if request else topic.message
            msg = cls.decode(body, self.limits)  # type: ignore[union-attr]
        except (ProtocolError, ValueError) as exc:
            self._reject(topic, key_expr, exc)
            return None
        self.stats.received[topic.name] += 1
        self.stats.received_bytes[topic.name] += len(payload)
        return Delivery(key_expr, parts, msg, len(payload), sender)

    @staticmethod
    def _expect_request(topic: Topic, carries: bool) -> None:
        if topic.kind is not Kind.QUERY:
            raise TypeError(f"{topic.name} is a {topic.kind.value} topic, not query")
        if (topic.request is not None) != carries:
            how = "answer/call" if topic.request is not None else "serve/query"
            raise TypeError(f"{topic.name}: use {how}")

    def _count_published(self, topic: Topic, n: int) -> None:
        self.stats.published[topic.name] += 1
        self.stats.published_bytes[topic.name] += n

    @staticmethod
    def _expect(topic: Topic, kind: Kind) -> None:
        if topic.kind is not kind:
            raise TypeError(f"{topic.name} is a {topic.kind.value} topic, not {kind.value}")

    # the interface ---------------------------------------------------------------------------
    @abstractmethod
    def publish(self, topic: Topic, msg: Message | bytes, **parts: str) -> int:
        """Publish on the concrete key given by ``parts``; returns the encoded size."""

    @abstractmethod
    def subscribe(self, topic: Topic, capacity: int = 64, **parts: str) -> Subscription:
        """Subscribe to a topic; omitted placeholders match any value."""

    @abstractmethod
    def serve(self, topic: Topic, handler: QueryHandler, **parts: str) -> Handle:
        """Answer queries on a QUERY topic. ``handler(params)`` runs on a bus worker thread."""

    @abstractmethod
    def query(
        self, topic: Topic, params: dict[str, str] | None = None, timeout: float = 10.0, **parts: str
    ) -> Delivery | None:
        """Ask a QUERY topic; the first valid reply, or None if none came before ``timeout``."""

    @abstractmethod
    def answer(self, topic: Topic, handler: RequestHandler, **parts: str) -> Handle:
        """Answer queries that carry a request (``topic.request``) on the concrete key of ``parts``;
        ``handler(request)`` runs on a bus worker thread, one query at a time."""

    @abstractmethod
    def call(self, topic: Topic, request: Message, timeout: float = 10.0, **parts: str) -> Delivery | None:
        """Send ``request`` to the server at the concrete key of ``parts``; its valid reply, or None
        if none came before ``timeout``."""

    @abstractmethod
    def declare_alive(self, service: str, instance: str) -> Handle:
        """Hold a liveliness token until closed (or until the process dies)."""

    @abstractmethod
    def watch_alive(self, service: str = "*") -> AliveWatch:
        """Track liveliness tokens of one service kind (or all)."""

    @abstractmethod
    def close(self) -> None:
        """Release every declared entity and the session."""

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
