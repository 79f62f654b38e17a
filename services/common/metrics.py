"""Prometheus collectors, one registry and one /metrics endpoint per process.

Names follow Prometheus conventions: `mea_` prefix, base units, counters end in `_total` (added by
the client on exposition), labels only of low cardinality (topic names, phase names).
Service-specific collectors are defined here too, so every metric name lives in one file.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterable

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    PlatformCollector,
    ProcessCollector,
    start_http_server,
)
from prometheus_client.core import CounterMetricFamily
from prometheus_client.registry import Collector

from services.common.bus.base import Bus

log = logging.getLogger(__name__)

# Default /metrics ports (docs/metrics.md, "Ports"); actors use ACTOR_BASE + index.
DEFAULT_PORTS = {
    "launcher": 9100,
    "router": 9100,
    "learner": 9101,
    "augmenter": 9102,
    "evaluator": 9103,
    "inference": 9104,
    "actor": 9110,
}


class _BusCollector(Collector):
    """Reads the bus's plain counters at scrape time (no per-message Prometheus calls)."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    def collect(self) -> Iterable:
        s = self.bus.stats
        for name, counter, doc in (
            ("mea_bus_published_messages", s.published, "Messages published (or replied), by topic."),
            ("mea_bus_published_bytes", s.published_bytes, "Encoded bytes published, by topic."),
            ("mea_bus_received_messages", s.received, "Valid messages received, by topic."),
            (
                "mea_bus_received_bytes",
                s.received_bytes,
                "Encoded bytes of valid messages received, by topic.",
            ),
            (
                "mea_bus_rejected_messages",
                s.bad,
                "Messages rejected by the decoder (ProtocolError), by topic.",
            ),
            (
                "mea_bus_unauthenticated_messages",
                s.unauthenticated,
                "Of the rejected: seal missing or invalid for this run, or a sender not allowed on the topic.",
            ),
        ):
            fam = CounterMetricFamily(name, doc, labels=["topic"])
            for topic, v in sorted(counter.items()):
                fam.add_metric([topic], float(v))
            yield fam


class ServiceMetrics:
    """Collectors every service has; services add their own via the helpers below."""

    def __init__(self, service: str, instance: str, namespace: str = "default") -> None:
        self.registry = CollectorRegistry()
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)
        self.service = service
        info = Info("mea_service", "Service identity.", registry=self.registry)
        info.info({"service": service, "service_instance": instance, "pid": str(os.getpid()),
                   "namespace": namespace})  # fmt: skip
        self.started = time.time()
        Gauge("mea_start_time_seconds", "UNIX time the service started.", registry=self.registry).set(
            self.started
        )
        self.policy_version = Gauge(
            "mea_policy_version", "Weights version in use (-1: none).", registry=self.registry
        )
        self.policy_version.set(-1)
        self._server = None

    def counter(self, name: str, doc: str, labels: Iterable[str] = ()) -> Counter:
        return Counter(name, doc, list(labels), registry=self.registry)

    def gauge(self, name: str, doc: str, labels: Iterable[str] = ()) -> Gauge:
        return Gauge(name, doc, list(labels), registry=self.registry)

    def histogram(
        self, name: str, doc: str, buckets: Iterable[float], labels: Iterable[str] = ()
    ) -> Histogram:
        return Histogram(name, doc, list(labels), buckets=tuple(buckets), registry=self.registry)

    def watch_bus(self, bus: Bus) -> None:
        self.registry.register(_BusCollector(bus))

    def serve(self, addr: str, port: int) -> int:
        """Start /metrics; returns the bound port (0 = disabled)."""
        if port == 0:
            return 0
        server, _thread = start_http_server(port, addr=addr, registry=self.registry)
        self._server = server
        return server.server_address[1]

    def close(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
