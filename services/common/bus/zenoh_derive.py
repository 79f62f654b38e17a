"""One Zenoh config file for a router and the clients on its own host (`mea run --zenoh-config`).

The file holds both sides of each link (TLS, credentials): the router reads it as it is, and
:func:`client_config` derives the config of a client on the same host from it.

Design notes: docs/architecture-notes.md, services/common/bus/zenoh_derive.py."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import zenoh

from services.common.bus.zenoh_bus import DEFAULT_ROUTER, ZenohConfig, load_zenoh_file

CLIENT_KEYS = ("transport", "scouting", "namespace", "timestamping")
"""Top-level sections of the router's file that a derived client keeps."""

_UNSPECIFIED = re.compile(r"^(?P<proto>[a-z0-9]+)/(?P<host>0\.0\.0\.0|\[::\])(?P<rest>:.*)$")


def _changed(value: Any, default: Any) -> Any:
    """The parts of ``value`` that differ from Zenoh's ``default`` (None: nothing differs)."""
    if isinstance(value, dict) and isinstance(default, dict):
        out = {k: d for k, v in value.items() if (d := _changed(v, default.get(k))) is not None}
        return out or None
    return None if value == default else value


def set_keys(conf: zenoh.Config) -> dict:
    """What ``conf`` sets, as a nested dict: every key whose value differs from Zenoh's default."""
    return _changed(json.loads(str(conf)), json.loads(str(zenoh.Config()))) or {}


def listen_endpoints(conf: zenoh.Config) -> list[str]:
    """The endpoints a router built from ``conf`` listens on."""
    listen = json.loads(conf.get_json("listen/endpoints"))
    return listen if isinstance(listen, list) else list(listen.get("router") or [])


def loopback(endpoint: str) -> str:
    """The endpoint a client on the router's host connects to: 0.0.0.0 and [::] become loopback."""
    m = _UNSPECIFIED.match(endpoint)
    if m is None:
        return endpoint
    host = "127.0.0.1" if m["host"] == "0.0.0.0" else "[::1]"
    return f"{m['proto']}/{host}{m['rest']}"


def client_config(router_file: str, endpoints: list[str]) -> dict:
    """The config (a JSON-able dict) of a client on the router's host joining the router of
    ``router_file`` that listens on ``endpoints``; ValueError naming the file and the missing key
    where the router would refuse that client."""
    conf = load_zenoh_file(router_file)
    keys = set_keys(conf)
    where = f"Zenoh config file {router_file}"
    connect = [loopback(e) for e in endpoints]
    if not connect or any(re.search(r":0(\D|$)", e.split("/", 1)[-1]) for e in connect):
        raise ValueError(
            f"{where}: the router needs a fixed listen port for the run's services, not {endpoints}"
        )
    tls = keys.get("transport", {}).get("link", {}).get("tls", {})
    usrpwd = keys.get("transport", {}).get("auth", {}).get("usrpwd", {})
    if tls.get("enable_mtls") and not (tls.get("connect_certificate") and tls.get("connect_private_key")):
        raise ValueError(
            f"{where}: the router asks clients for certificates (transport/link/tls/enable_mtls) but the file "
            "has no transport/link/tls/connect_certificate and connect_private_key for the run's own services"
        )
    if usrpwd.get("dictionary_file") and not (usrpwd.get("user") and usrpwd.get("password")):
        raise ValueError(
            f"{where}: the router checks user and password (transport/auth/usrpwd/dictionary_file) but the "
            "file sets no transport/auth/usrpwd/user and password for the run's own services"
        )
    client = {k: keys[k] for k in CLIENT_KEYS if k in keys}
    transport = client.get("transport", {})
    for name in [k for k in tls if k.startswith("listen_")]:
        del transport["link"]["tls"][name]
    if usrpwd:
        transport["auth"]["usrpwd"] = (
            {k: v for k, v in usrpwd.items() if k in ("user", "password")}
            if usrpwd.get("dictionary_file")
            else {}
        )  # credentials go only to a router that checks them (one that does not refuses them)
    return {"mode": "client", "connect": {"endpoints": connect}, **client}


def write_client_config(router_file: str, endpoints: list[str], out: Path) -> Path:
    """Write :func:`client_config` to ``out`` (JSON, which Zenoh reads as JSON5), readable by its
    owner only (it may hold a password); returns ``out``."""
    text = json.dumps(client_config(router_file, endpoints), indent=2) + "\n"
    tmp = out.with_name(f".{out.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, out)
    return out


def run_router(config_file: str, listen: str, connect: tuple[str, ...], namespace: str) -> ZenohConfig:
    """The config of `mea run`'s embedded router: ``listen`` (``--listen``) unless ``config_file`` is
    given and ``listen`` is the default, where the file's listen endpoints (else the default) apply."""
    explicit = () if config_file and listen == DEFAULT_ROUTER else (listen,)
    return ZenohConfig(
        mode="router", listen=explicit, connect=connect, namespace=namespace, config_file=config_file
    )


def check_run_file(
    config_file: str, listen: str, connect: tuple[str, ...], namespace: str, in_process: bool = False
) -> None:
    """ValueError, one line naming ``--zenoh-config``, unless ``config_file`` (none: nothing to check)
    configures both the embedded router and the run's own services (:func:`client_config`)."""
    if not config_file:
        return
    if in_process:
        raise ValueError("--zenoh-config configures the Zenoh router; --in-process runs without Zenoh")
    try:
        router = run_router(config_file, listen, connect, namespace)
        client_config(config_file, listen_endpoints(router.to_zenoh()))
    except ValueError as exc:
        raise ValueError(f"--zenoh-config: {exc}") from None
