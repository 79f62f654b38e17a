"""Zenoh implementation of the bus (eclipse-zenoh 1.10).

Open it only inside the process that uses it (spawned, never forked with a live session).
Callbacks only enqueue; queries are answered on a worker thread.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro
import zenoh

from proto.codec import Message
from proto.msgpack_wire import DEFAULT_LIMITS, Limits
from proto.topics import ALIVE, Congestion, Kind, Topic
from services.common.bus.base import AliveWatch, Bus, Delivery, QueryHandler, RequestHandler, Subscription

log = logging.getLogger(__name__)
_LOG_ONCE = threading.Lock()
_log_started = False

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
BLOCK_WAIT_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"
BLOCK_WAIT_US = 600_000_000
"""How long (us) a session waits on a peer that does not read before closing its transport: 10 min.
Episodes are sent with BLOCK congestion control and a full subscriber queue waits (nothing accepted is
dropped), so a consumer's pause (a learner writing a checkpoint of a multi-GB replay) must not outlast
it; Zenoh's own 5 s closed the transport for good and lost what it held (docs/results.md)."""


_PROJECT_KEYS = (
    "mode",
    "listen/endpoints",
    "connect/endpoints",
    "connect/timeout_ms",
    "scouting/multicast/enabled",
    BLOCK_WAIT_KEY,
)
"""The Zenoh keys ZenohConfig's own fields write; a config file that sets one of them wins."""


def _zenoh_message(exc: Exception) -> str:
    """A ZError's text without the Rust source location zenoh appends."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?\s*$", "", str(exc)).strip()


def load_zenoh_file(path: str) -> zenoh.Config:
    """Zenoh's own config file (JSON5, JSON or YAML, by extension); ValueError naming the file on any problem."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"Zenoh config file {path}: no such file")
    if not p.is_file():
        raise ValueError(f"Zenoh config file {path}: not a regular file")
    try:
        with p.open("rb"):
            pass
    except OSError as exc:
        raise ValueError(f"Zenoh config file {path}: cannot read it ({exc.strerror})") from None
    try:
        return zenoh.Config.from_file(str(p))
    except zenoh.ZError as exc:
        raise ValueError(
            f"Zenoh config file {path} is not a valid Zenoh config: {_zenoh_message(exc)}"
        ) from None


@dataclass(frozen=True)
class ZenohConfig:
    """How a process joins the Zenoh network."""

    mode: Literal["peer", "client", "router"] = "peer"
    """Zenoh session mode."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to; empty: the mode's."""
    listen: tuple[str, ...] = ()
    """Endpoints to listen on; empty: the mode's."""
    multicast_scouting: bool = False
    """Multicast discovery (off: endpoints only)."""
    namespace: str = "default"
    """Namespace separating runs on one network."""
    config_file: Annotated[str, tyro.conf.arg(aliases=("--zenoh-config",))] = ""
    """Zenoh's own config file (JSON5); empty: none."""

    def __post_init__(self) -> None:
        if self.config_file:
            self._file_config()  # missing, unreadable, invalid or contradicted: fail while parsing flags

    def _file_config(self) -> tuple[zenoh.Config, set[str]]:
        """The file's config and which of `_PROJECT_KEYS` it sets (differs from Zenoh's default)."""
        conf = load_zenoh_file(self.config_file)
        default = zenoh.Config()
        file_sets = {k for k in _PROJECT_KEYS if conf.get_json(k) != default.get_json(k)}
        given = {  # field values other than the default count as explicit
            "mode": ("mode", self.mode != "peer", self.mode),
            "listen/endpoints": ("listen", bool(self.listen), list(self.listen)),
            "connect/endpoints": ("connect", bool(self.connect), list(self.connect)),
            "scouting/multicast/enabled": ("multicast_scouting", self.multicast_scouting, True),
        }
        for key, (field, explicit, value) in given.items():
            if explicit and key in file_sets and json.loads(conf.get_json(key)) != value:
                raise ValueError(
                    f"zenoh {field} {json.dumps(value)} contradicts {key} = {conf.get_json(key)} in the Zenoh "
                    f"config file {self.config_file} (the file wins for every key it sets): drop one of them"
                )
        return conf, file_sets

    def to_zenoh(self) -> zenoh.Config:
        """The session config: the config file if any, then this config's fields for every key it leaves unset."""
        if self.config_file:
            conf, file_sets = self._file_config()
        else:
            conf, file_sets = zenoh.Config(), set()

        def put(key: str, value) -> None:
            if key not in file_sets:
                conf.insert_json5(key, json.dumps(value))

        put("mode", self.mode)
        mode = json.loads(conf.get_json("mode"))  # the file's mode, where it sets one
        put("scouting/multicast/enabled", self.multicast_scouting)
        put(BLOCK_WAIT_KEY, BLOCK_WAIT_US)
        listen = list(self.listen)
        if not listen:
            listen = [DEFAULT_ROUTER] if mode == "router" else ["tcp/127.0.0.1:0"] if mode == "peer" else []
        put("listen/endpoints", listen)
        if "listen/endpoints" in file_sets:
            listen = json.loads(conf.get_json("listen/endpoints"))
            listen = listen if isinstance(listen, list) else listen.get(mode) or []
        connect = list(self.connect) or ([] if mode == "router" else [DEFAULT_ROUTER])
        put("connect/endpoints", [e for e in connect if e not in listen])
        if mode == "client":
            # wait for the router instead of failing at once (compose/launcher start order)
            put("connect/timeout_ms", {"client": -1})
        return conf


def _priority(topic: Topic) -> zenoh.Priority:
    return getattr(zenoh.Priority, topic.qos.priority.name)


def _congestion(topic: Topic) -> zenoh.CongestionControl:
    return (
        zenoh.CongestionControl.BLOCK
        if topic.qos.congestion is Congestion.BLOCK
        else zenoh.CongestionControl.DROP
    )


def _reliability(topic: Topic) -> zenoh.Reliability:
    return zenoh.Reliability.RELIABLE if topic.qos.reliable else zenoh.Reliability.BEST_EFFORT


class _Undeclare:
    def __init__(self, entity) -> None:
        self._entity = entity

    def close(self) -> None:
        if self._entity is not None:
            with contextlib.suppress(zenoh.ZError):
                self._entity.undeclare()
            self._entity = None


class ZenohBus(Bus):
    def __init__(self, cfg: ZenohConfig | None = None, limits: Limits = DEFAULT_LIMITS) -> None:
        cfg = cfg or ZenohConfig()
        super().__init__(cfg.namespace, limits)
        global _log_started
        with _LOG_ONCE:
            if not _log_started:
                zenoh.init_log_from_env_or(os.environ.get("MEA_ZENOH_LOG", "error"))
                _log_started = True
        self.cfg = cfg
        self.session = zenoh.open(cfg.to_zenoh())
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._pub_lock = threading.Lock()
        self._handles: list = []
        self._queries: queue.Queue = queue.Queue()
        self._servers: dict[
            str, tuple[QueryHandler | RequestHandler, bool]
        ] = {}  # key -> (handler, takes a request)
        self._worker: threading.Thread | None = None
        self._closed = False

    # pub/sub ---------------------------------------------------------------------------------
    def publish(self, topic: Topic, msg: Message | bytes, **parts: str) -> int:
        self._expect(topic, Kind.PUBSUB)
        key_expr = self.key(topic, **parts)
        payload = self.encode_for(topic, msg, key_expr)
        with self._pub_lock:
            pub = self._publishers.get(key_expr)
            if pub is None:
                pub = self.session.declare_publisher(
                    key_expr,
                    congestion_control=_congestion(topic),
                    priority=_priority(topic),
                    express=topic.qos.express,
                    reliability=_reliability(topic),
                )
                self._publishers[key_expr] = pub
        pub.put(payload)
        self._count_published(topic, len(payload))
        return len(payload)

    def subscribe(self, topic: Topic, capacity: int = 64, **parts: str) -> Subscription:
        self._expect(topic, Kind.PUBSUB)
        sub = Subscription(self, topic, capacity)

        def on_sample(sample: zenoh.Sample) -> None:
            sub.push(str(sample.key_expr), sample.payload.to_bytes())

        entity = self.session.declare_subscriber(self.wildcard_key(topic, parts), on_sample)
        sub._undeclare = _Undeclare(entity).close
        self._handles.append(sub)
        return sub

    # query/serve -----------------------------------------------------------------------------
    def serve(self, topic: Topic, handler: QueryHandler, **parts: str):
        self._expect_request(topic, False)
        return self._declare_server(topic, handler, False, parts)

    def answer(self, topic: Topic, handler: RequestHandler, **parts: str):
        self._expect_request(topic, True)
        return self._declare_server(topic, handler, True, parts)

    def _declare_server(self, topic: Topic, handler, takes_request: bool, parts: dict[str, str]):
        key_expr = self.key(topic, **parts)
        if key_expr in self._servers:
            raise ValueError(f"{key_expr} is already served by this bus")
        self._servers[key_expr] = (handler, takes_request)
        self._ensure_worker()

        def on_query(q: zenoh.Query) -> None:
            self._queries.put((topic, key_expr, q))

        entity = _Undeclare(self.session.declare_queryable(key_expr, on_query, complete=True))

        class _Served:
            def close(inner) -> None:  # noqa: N805 - closure over the bus
                entity.close()
                self._servers.pop(key_expr, None)

        h = _Served()
        self._handles.append(h)
        return h

    def _ensure_worker(self) -> None:
        if self._worker is None:
            self._worker = threading.Thread(target=self._answer_queries, name="zenoh-queries", daemon=True)
            self._worker.start()

    def _answer_queries(self) -> None:
        while True:
            item = self._queries.get()
            if item is None:
                return
            topic, key_expr, q = item
            try:
                entry = self._servers.get(key_expr)
                reply = None
                if entry is not None and entry[1]:  # the query carries a request message
                    raw = q.payload.to_bytes() if q.payload is not None else b""
                    request = self.decode_delivery(topic, key_expr, raw, request=True)
                    reply = entry[0](request) if request is not None else None
                elif entry is not None:
                    reply = entry[0]({k: v for k, v in q.parameters})
                if reply is not None:
                    payload = self.encode_for(topic, reply, key_expr)
                    q.reply(key_expr, payload)  # replies travel with the query's QoS
                    self._count_published(topic, len(payload))
            except Exception:  # noqa: BLE001 - a bad query must not kill the server thread
                log.exception("query handler failed", extra={"topic": topic.name})
            finally:
                q.drop()

    def query(
        self, topic: Topic, params: dict[str, str] | None = None, timeout: float = 10.0, **parts: str
    ) -> Delivery | None:
        self._expect_request(topic, False)
        selector = self.wildcard_key(topic, parts)
        if params:
            selector += "?" + ";".join(f"{k}={v}" for k, v in params.items())
        replies = self.session.get(
            selector, timeout=timeout, congestion_control=_congestion(topic), priority=_priority(topic)
        )
        return self._first_reply(topic, replies)

    def call(self, topic: Topic, request: Message, timeout: float = 10.0, **parts: str) -> Delivery | None:
        self._expect_request(topic, True)
        key_expr = self.key(topic, **parts)
        payload = self.encode_request(topic, request, key_expr)
        replies = self.session.get(key_expr, payload=payload, timeout=timeout, express=topic.qos.express,
                                   congestion_control=_congestion(topic), priority=_priority(topic))  # fmt: skip
        self._count_published(topic, len(payload))
        return self._first_reply(topic, replies)

    def _first_reply(self, topic: Topic, replies) -> Delivery | None:
        result = None
        for reply in replies:
            if result is None and reply.ok is not None:
                sample = reply.ok
                result = self.decode_delivery(topic, str(sample.key_expr), sample.payload.to_bytes())
        return result

    # liveliness ------------------------------------------------------------------------------
    def declare_alive(self, service: str, instance: str):
        token = self.session.liveliness().declare_token(self.key(ALIVE, service=service, instance=instance))
        h = _Undeclare(token)
        self._handles.append(h)
        return h

    def watch_alive(self, service: str = "*") -> AliveWatch:
        watch = AliveWatch()

        def on_sample(sample: zenoh.Sample) -> None:
            watch.update(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        entity = self.session.liveliness().declare_subscriber(
            self.key(ALIVE, service=service, instance="*"), on_sample, history=True
        )
        watch._undeclare = _Undeclare(entity).close
        self._handles.append(watch)
        return watch

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for h in reversed(self._handles):
            h.close()
        with self._pub_lock:
            for pub in self._publishers.values():
                with contextlib.suppress(zenoh.ZError):
                    pub.undeclare()
            self._publishers.clear()
        if self._worker is not None:
            self._queries.put(None)
            self._worker.join(timeout=2.0)
        self.session.close()
