"""Config plumbing: frozen dataclasses with presets, parsed by tyro, saved with each run.

Every command takes ``--preset NAME`` first (e.g. ``paper``, ``cpu-small``); any other flag then
overrides a field of that preset. Field docstrings are the ``--help`` text.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import tyro

from proto.msgpack_wire import DEFAULT_LIMITS, Limits
from proto.topics import TopicKeyError, by_name
from services.common.bus.zenoh_bus import ZenohConfig

C = TypeVar("C")


@dataclasses.dataclass(frozen=True)
class ServiceConfig:
    """What every service process shares: identity, transport, metrics and logs."""

    instance_id: str = ""
    """Instance id (unique per service kind); empty picks `<service>-<pid>`."""
    zenoh: ZenohConfig = ZenohConfig()
    """How to join the Zenoh network."""
    metrics_port: int = -1
    """Prometheus /metrics port; -1 uses the service's default (README), 0 disables."""
    metrics_addr: str = "127.0.0.1"
    """Address /metrics binds to (0.0.0.0 inside containers)."""
    log_format: str = "json"
    """`json` (one object per line) or `text`."""
    log_level: str = "INFO"
    """Python logging level."""
    heartbeat_seconds: float = 1.0
    """Period of the status heartbeat."""
    limits: Limits = DEFAULT_LIMITS
    """Caps applied while decoding any received message (sizes, nesting, strings)."""
    topic_caps: tuple[str, ...] = ()
    """Per-topic size caps replacing the defaults (proto/README.md, Topics table), each
    `TOPIC=BYTES`, e.g. `episodes_raw=134217728`; larger messages are refused and counted."""
    run_key_file: str = ""
    """The run's key (hex, owner-only file; `mea run` creates RUN_DIR/run.key): every message is sealed
    with it and only messages sealed with it by a service allowed on the topic are accepted. Empty:
    the bus is not authenticated (anyone on the Zenoh network can write to it)."""

    def __post_init__(self) -> None:
        if self.log_format not in ("json", "text"):
            raise ValueError(f"log_format must be json or text, not {self.log_format!r}")
        if self.heartbeat_seconds <= 0:
            raise ValueError("heartbeat_seconds must be positive")
        self.caps()  # refuse a malformed --service.topic-caps at start-up

    def caps(self) -> dict[str, int]:
        """``topic_caps`` as {topic name: bytes}; ValueError naming a bad entry."""
        out = {}
        for entry in self.topic_caps:
            name, _, value = entry.partition("=")
            try:
                by_name(name)
                out[name] = int(value)
            except (TopicKeyError, ValueError):
                raise ValueError(
                    f"topic_caps entry {entry!r}: expected TOPIC=BYTES with a known topic"
                ) from None
            if out[name] <= 0:
                raise ValueError(f"topic_caps entry {entry!r}: the cap must be positive")
        return out


def parse(cls: type[C], presets: Mapping[str, C], argv: Sequence[str], prog: str, description: str) -> C:
    """Parse ``[--preset NAME] [field flags...]`` into a frozen config."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", choices=sorted(presets), default=next(iter(presets)))
    known, rest = pre.parse_known_args(list(argv))
    desc = f"{description}\n\nPresets (--preset, applied before other flags): {', '.join(presets)}; default {next(iter(presets))}."
    # a ValueError from a config's own checks (__post_init__) ends in tyro's error box, exit 2
    return tyro.cli(cls, prog=prog, description=desc, args=rest, default=presets[known.preset])


def to_jsonable(cfg: Any) -> Any:
    if dataclasses.is_dataclass(cfg):
        return {f.name: to_jsonable(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_jsonable(v) for v in cfg]
    if isinstance(cfg, Path):
        return str(cfg)
    return cfg


def save(cfg: Any, path: Path) -> None:
    """Write the resolved config as JSON (atomically)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(to_jsonable(cfg), indent=2, sort_keys=True) + "\n")
    tmp.replace(path)
