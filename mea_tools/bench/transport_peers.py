"""The transport benchmark's spawned children (module-level: they are started with the spawn method):
an episode subscriber and a weights server, each a Zenoh client of the benchmark's router."""

from __future__ import annotations

import dataclasses
import time

from mea_tools.bench.harness import run_with_bus
from mea_tools.bench.transport_data import SOURCE, make_blob
from proto.topics import EPISODES_RAW, WEIGHTS_ANNOUNCE, WEIGHTS_LATEST
from proto.weights import WeightsBlob

SUB_SERVICE = "bench-transport-sub"
SERVER_SERVICE = "bench-transport-weights"
INSTANCE = "0"


def subscriber_main(endpoint: str, expected: int, capacity: int, idle_timeout: float, results) -> None:
    """Receive (decode and validate) ``expected`` episodes, then report count, bytes and times."""
    run_with_bus(
        endpoint, results, lambda bus: _receive_episodes(bus, expected, capacity, idle_timeout, results)
    )


def _receive_episodes(bus, expected: int, capacity: int, idle_timeout: float, results) -> None:
    sub = bus.subscribe(EPISODES_RAW, capacity=capacity)
    bus.declare_alive(SUB_SERVICE, INSTANCE)  # after the subscription: the parent's go signal
    count = nbytes = 0
    t_first = t_last = None
    ids: set[str] = set()
    while count < expected:
        d = sub.recv(timeout=idle_timeout)
        if d is None:
            break
        t_last = time.monotonic()
        if t_first is None:
            t_first = t_last
        count += 1
        nbytes += d.size
        ids.add(d.message.episode_id)
    results.put(
        (
            "done",
            {
                "received": count,
                "bytes": nbytes,
                "t_first": t_first,
                "t_last": t_last,
                "distinct_ids": len(ids),
                "bad": int(sum(bus.stats.bad.values())),
            },
        )
    )


def weights_server_main(endpoint: str, commands, results) -> None:
    """Serve WEIGHTS_LATEST from pre-encoded bytes; on command load a blob or announce a new version."""
    run_with_bus(endpoint, results, lambda bus: _serve_weights(bus, commands, results))


def _serve_weights(bus, commands, results) -> None:
    current: list[tuple[int, bytes]] = [(-1, b"")]

    def handler(params: dict[str, str]) -> bytes | None:
        version, payload = current[0]
        try:
            wanted = int(params.get("min_version", "0"))
        except ValueError:
            return None
        return payload if version >= 0 and version >= wanted else None

    bus.serve(WEIGHTS_LATEST, handler, source=SOURCE)
    bus.declare_alive(SERVER_SERVICE, INSTANCE)
    blob: WeightsBlob | None = None
    version = 0
    while True:
        cmd = commands.get()
        if cmd[0] == "stop":
            break
        version += 1
        if cmd[0] == "load":
            _, size_mb, seed = cmd
            blob = make_blob(size_mb, seed, version)
            payload = blob.encode()
            current[0] = (version, payload)
            results.put(("loaded", version, len(payload)))
        elif cmd[0] == "announce" and blob is not None:
            # same tensors, new version: the digest stays valid; encode before timing starts
            blob = dataclasses.replace(blob, version=version, created_at=time.time())
            payload = blob.encode()
            current[0] = (version, payload)
            ann = blob.announcement(len(payload))
            t0 = time.monotonic()
            bus.publish(WEIGHTS_ANNOUNCE, ann, source=SOURCE)
            results.put(("announced", version, t0))
        else:
            results.put(("error", f"bad command {cmd!r}"))
