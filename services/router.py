"""`mea router`: a Zenoh router in a Python process (no zenohd needed), for multi-process or
multi-host deployments (docker-compose runs one). Services connect with `--zenoh.connect`."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

from services.common import config
from services.common.bus.zenoh_bus import DEFAULT_ROUTER, ZenohBus, ZenohConfig
from services.common.config import ServiceConfig
from services.common.runtime import ServiceContext

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class RouterConfig:
    """Zenoh router."""

    listen: tuple[str, ...] = (DEFAULT_ROUTER,)
    """Endpoints to listen on (tcp/0.0.0.0:7447 to accept other hosts)."""
    connect: tuple[str, ...] = ()
    """Other routers to mesh with (one router per host)."""
    service: ServiceConfig = ServiceConfig()
    """Identity, metrics and logs (its zenoh section is ignored: the router is configured above)."""


PRESETS = {"default": RouterConfig()}


def run(cfg: RouterConfig) -> int:
    zcfg = ZenohConfig(
        mode="router", listen=cfg.listen, connect=cfg.connect, namespace=cfg.service.zenoh.namespace
    )
    ctx = ServiceContext("router", cfg.service, bus_factory=lambda _c: ZenohBus(zcfg))
    with ctx:
        log.info("router listening", extra={"listen": ",".join(cfg.listen)})
        ctx.shutdown.wait()
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(RouterConfig, PRESETS, argv, "mea router", RouterConfig.__doc__ or ""))
