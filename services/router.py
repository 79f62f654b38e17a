"""`mea router`: a Zenoh router in a Python process (no zenohd needed), for multi-process or
multi-host deployments (docker-compose runs one). Services connect with `--service.zenoh.connect`.

TLS, user/password authentication and access control come from Zenoh's own config file
(`--zenoh-config FILE`, also `--service.zenoh.config-file`); see docs/security.md."""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
from collections.abc import Sequence

import zenoh

from services.common import config
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from services.common.config import ServiceConfig
from services.common.runtime import ServiceContext

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class RouterConfig:
    """Zenoh router."""

    listen: tuple[str, ...] = ()
    """Endpoints to listen on (tcp/0.0.0.0:7447 accepts other hosts)."""
    connect: tuple[str, ...] = ()
    """Other routers to mesh with (one router per host)."""
    service: ServiceConfig = ServiceConfig()
    """Identity, metrics and logs (of zenoh: namespace and config file only)."""


PRESETS = {"default": RouterConfig()}


def run(cfg: RouterConfig) -> int:
    try:  # a missing, invalid or contradicted --zenoh-config file: one line, no traceback
        zcfg = ZenohConfig(
            mode="router",
            listen=cfg.listen,
            connect=cfg.connect,
            namespace=cfg.service.zenoh.namespace,
            config_file=cfg.service.zenoh.config_file,
        )
        listen = json.loads(zcfg.to_zenoh().get_json("listen/endpoints"))
    except ValueError as exc:
        print(f"mea router: {exc}", file=sys.stderr)
        return 2
    listen = ",".join(listen if isinstance(listen, list) else listen.get("router") or [])

    def open_bus(_c: ServiceConfig) -> ZenohBus:
        try:
            return ZenohBus(zcfg)
        except zenoh.ZError as exc:  # e.g. a port in use, a certificate file that cannot be read
            raise SystemExit(f"mea router: cannot start the Zenoh router on {listen}: {exc}") from None

    with ServiceContext("router", cfg.service, bus_factory=open_bus) as ctx:
        log.info("router listening", extra={"listen": listen})
        ctx.shutdown.wait()
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(RouterConfig, PRESETS, argv, "mea router", RouterConfig.__doc__ or ""))
