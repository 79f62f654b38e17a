"""In-process bus: the same topics and encoding as Zenoh, routed inside one process (tests, debug)."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field

from proto.codec import Message
from proto.msgpack_wire import DEFAULT_LIMITS, Limits
from proto.topics import ALIVE, Kind, Topic
from services.common.bus.base import AliveWatch, Bus, Delivery, QueryHandler, RequestHandler, Subscription

log = logging.getLogger(__name__)


def key_matches(pattern: str, key_expr: str) -> bool:
    """Zenoh-style match for the wildcards this project uses: ``*`` is one chunk, ``**`` any."""
    p, k = pattern.split("/"), key_expr.split("/")

    def rec(i: int, j: int) -> bool:
        if i == len(p):
            return j == len(k)
        if p[i] == "**":
            return any(rec(i + 1, jj) for jj in range(j, len(k) + 1))
        return j < len(k) and (p[i] == "*" or p[i] == k[j]) and rec(i + 1, j + 1)

    return rec(0, 0)


@dataclass
class Hub:
    """Shared routing table; give several InProcBus instances one Hub to connect them."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    subs: list[tuple[str, Subscription]] = field(default_factory=list)
    queryables: list[tuple[str, QueryHandler | RequestHandler, InProcBus]] = field(default_factory=list)
    tokens: dict[str, int] = field(default_factory=dict)
    watches: list[tuple[str, AliveWatch]] = field(default_factory=list)


class _Closer:
    def __init__(self, fn) -> None:
        self._fn = fn

    def close(self) -> None:
        if self._fn is not None:
            self._fn()
            self._fn = None


class InProcBus(Bus):
    def __init__(self, hub: Hub | None = None, namespace: str = "default", limits: Limits = DEFAULT_LIMITS):
        super().__init__(namespace, limits)
        self.hub = hub or Hub()
        self._handles: list = []
        self._answering = threading.Lock()

    def publish(self, topic: Topic, msg: Message | bytes, **parts: str) -> int:
        self._expect(topic, Kind.PUBSUB)
        key_expr = self.key(topic, **parts)
        payload = self.encode_for(topic, msg, key_expr)
        with self.hub.lock:
            targets = [s for pat, s in self.hub.subs if key_matches(pat, key_expr)]
        for s in targets:
            s.push(key_expr, payload)
        self._count_published(topic, len(payload))
        return len(payload)

    def subscribe(self, topic: Topic, capacity: int = 64, **parts: str) -> Subscription:
        self._expect(topic, Kind.PUBSUB)
        sub = Subscription(self, topic, capacity)
        entry = (self.wildcard_key(topic, parts), sub)
        with self.hub.lock:
            self.hub.subs.append(entry)

        def undeclare() -> None:
            with self.hub.lock:
                if entry in self.hub.subs:
                    self.hub.subs.remove(entry)

        sub._undeclare = undeclare
        self._handles.append(sub)
        return sub

    def serve(self, topic: Topic, handler: QueryHandler, **parts: str):
        self._expect_request(topic, False)
        return self._declare_server(topic, handler, parts)

    def answer(self, topic: Topic, handler: RequestHandler, **parts: str):
        self._expect_request(topic, True)
        return self._declare_server(topic, handler, parts)

    def _declare_server(self, topic: Topic, handler, parts: dict[str, str]):
        entry = (self.key(topic, **parts), handler, self)
        with self.hub.lock:
            if any(k == entry[0] for k, _, _ in self.hub.queryables):
                raise ValueError(f"{entry[0]} is already served")
            self.hub.queryables.append(entry)

        def undeclare() -> None:
            with self.hub.lock:
                if entry in self.hub.queryables:
                    self.hub.queryables.remove(entry)

        h = _Closer(undeclare)
        self._handles.append(h)
        return h

    def query(
        self, topic: Topic, params: dict[str, str] | None = None, timeout: float = 10.0, **parts: str
    ) -> Delivery | None:
        self._expect_request(topic, False)
        pattern = self.wildcard_key(topic, parts)
        with self.hub.lock:
            targets = [(k, h, b) for k, h, b in self.hub.queryables if key_matches(pattern, k)]
        for key_expr, handler, server in targets:
            try:
                reply = handler(dict(params or {}))
            except Exception:  # noqa: BLE001 - same as Zenoh: a failing server answers nothing
                log.exception("query handler failed", extra={"topic": topic.name})
                continue
            if reply is None:
                continue
            payload = server.encode_for(topic, reply, key_expr)  # sealed by the server, as over Zenoh
            delivery = self.decode_delivery(topic, key_expr, payload)
            if delivery is not None:
                return delivery
        return None

    def call(self, topic: Topic, request: Message, timeout: float = 10.0, **parts: str) -> Delivery | None:
        self._expect_request(topic, True)
        key_expr = self.key(topic, **parts)
        payload = self.encode_request(topic, request, key_expr)
        self._count_published(topic, len(payload))
        with self.hub.lock:
            targets = [(h, b) for k, h, b in self.hub.queryables if k == key_expr]
        for handler, server in targets:
            decoded = server.decode_delivery(
                topic, key_expr, payload, request=True
            )  # checked by the server, as over Zenoh
            if decoded is None:
                continue
            with server._answering:  # one request at a time per server, as Zenoh's query thread does
                try:
                    reply = handler(decoded)
                except Exception:  # noqa: BLE001 - same as Zenoh: a failing server answers nothing
                    log.exception("query handler failed", extra={"topic": topic.name})
                    continue
            if reply is not None:
                answer = server.encode_for(topic, reply, key_expr)
                server._count_published(topic, len(answer))
                return self.decode_delivery(topic, key_expr, answer)
        return None

    def declare_alive(self, service: str, instance: str):
        key_expr = self.key(ALIVE, service=service, instance=instance)
        self._token_change(key_expr, +1)
        h = _Closer(lambda: self._token_change(key_expr, -1))
        self._handles.append(h)
        return h

    def _token_change(self, key_expr: str, delta: int) -> None:
        with self.hub.lock:
            before = self.hub.tokens.get(key_expr, 0)
            after = before + delta
            self.hub.tokens[key_expr] = after
            watches = [w for pat, w in self.hub.watches if key_matches(pat, key_expr)]
        if (before == 0) != (after == 0):
            for w in watches:
                w.update(key_expr, after > 0)

    def watch_alive(self, service: str = "*") -> AliveWatch:
        watch = AliveWatch()
        pattern = self.key(ALIVE, service=service, instance="*")
        with self.hub.lock:
            self.hub.watches.append((pattern, watch))
            present = [k for k, n in self.hub.tokens.items() if n > 0 and key_matches(pattern, k)]
        for k in present:
            watch.update(k, True)

        def undeclare() -> None:
            with self.hub.lock:
                self.hub.watches[:] = [(p, w) for p, w in self.hub.watches if w is not watch]

        watch._undeclare = undeclare
        self._handles.append(watch)
        return watch

    def close(self) -> None:
        for h in reversed(self._handles):
            h.close()
        self._handles.clear()
