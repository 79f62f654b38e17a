"""A minimal service for launcher tests: the real ServiceContext around a counting loop."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from services.common import config
from services.common.config import ServiceConfig
from services.common.runtime import ServiceContext


@dataclasses.dataclass(frozen=True)
class DummyConfig:
    """Counts ticks until stopped."""

    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics, logs."""
    fail_after_ticks: int = 0
    """Exit with code 3 after this many ticks (0: never)."""


def main(argv: Sequence[str]) -> int:
    cfg = config.parse(DummyConfig, {"default": DummyConfig()}, argv, "dummy", DummyConfig.__doc__ or "")
    ticks = 0
    with ServiceContext("test", cfg.service, counters=lambda: {"ticks": ticks}) as ctx:
        while not ctx.shutdown.wait(0.05):
            ticks += 1
            if cfg.fail_after_ticks and ticks >= cfg.fail_after_ticks:
                return 3
    return 0
