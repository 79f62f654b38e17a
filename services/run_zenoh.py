"""`mea run --zenoh-config FILE`: the embedded router reads FILE, every service joins it with the
client config derived from FILE (``services.common.bus.zenoh_derive``), written to
``RUN_DIR/zenoh-client.json5`` (owner-only: it may hold a password) when the run starts."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from services.common.bus.zenoh_bus import ZenohConfig
from services.common.bus.zenoh_derive import listen_endpoints, run_router, write_client_config
from services.plan import ChildSpec
from services.run_config import RunConfig

CLIENT_FILE = "zenoh-client.json5"


def router_config(cfg: RunConfig) -> ZenohConfig:
    """The embedded router's Zenoh config (``--listen``, ``--connect``, ``--zenoh-config``)."""
    return run_router(cfg.zenoh_config, cfg.listen, cfg.connect, cfg.namespace)


def _joined(spec: ChildSpec, client: str) -> ChildSpec:
    if spec.config is not None:
        service = spec.config.service
        zenoh = ZenohConfig(namespace=service.zenoh.namespace, config_file=client)
        config = dataclasses.replace(spec.config, service=dataclasses.replace(service, zenoh=zenoh))
        return dataclasses.replace(spec, config=config)
    argv = list(spec.argv)
    for i, arg in enumerate(argv[:-1]):  # a plugin's flags: the router's endpoint becomes the file
        if arg == "--service.zenoh.connect":
            argv[i : i + 2] = ["--service.zenoh.config-file", client]
    return dataclasses.replace(spec, argv=tuple(argv))


def secure(specs: list[ChildSpec], cfg: RunConfig, run_dir: Path) -> list[ChildSpec]:
    """With ``--zenoh-config``: write the run's client config and return ``specs`` joining through it
    (``specs`` as they are otherwise)."""
    if not cfg.zenoh_config:
        return specs
    endpoints = listen_endpoints(router_config(cfg).to_zenoh())
    client = str(write_client_config(cfg.zenoh_config, endpoints, run_dir / CLIENT_FILE))
    return [_joined(s, client) for s in specs]
