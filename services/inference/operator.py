"""`mea operator`: the operator's presence and e-stop on the bus.

While it runs it holds an ``operator`` liveliness token and publishes its ``EStop`` state about once a
second (``--engage`` starts engaged). Robots started with ``--require-operator`` hold when the token
disappears (the operator's process or machine went away); every robot and server holds while any
operator's e-stop is engaged. ``SIGUSR1`` engages, ``SIGUSR2`` releases (a foot pedal or a console
maps onto these); stopping the process removes the token.
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import time
from collections.abc import Callable, Sequence

from proto.inference import EStop
from proto.topics import ESTOP
from services.common import config
from services.common.bus.base import Bus
from services.common.config import ServiceConfig
from services.common.runtime import ServiceContext

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class OperatorConfig:
    """Hold the operator's liveliness token and e-stop state while running."""

    engage: bool = False
    """Start with the e-stop engaged."""
    every: float = 1.0
    """Publish the state this often (s) besides on every change."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""


def run(cfg: OperatorConfig, bus_factory: Callable[[ServiceConfig], Bus] | None = None) -> int:
    kwargs = {} if bus_factory is None else {"bus_factory": bus_factory}
    with ServiceContext("operator", cfg.service, **kwargs) as ctx:
        state = {"engaged": cfg.engage, "changed": True}

        def set_engaged(value: bool) -> Callable[[int, object], None]:
            def handler(_signum: int, _frame: object) -> None:
                state["engaged"], state["changed"] = value, True

            return handler

        signal.signal(signal.SIGUSR1, set_engaged(True))
        signal.signal(signal.SIGUSR2, set_engaged(False))
        next_at = 0.0
        while not ctx.shutdown.is_set():
            now = time.monotonic()
            if state["changed"] or now >= next_at:
                if state["changed"]:
                    log.warning("e-stop " + ("engaged" if state["engaged"] else "released"))
                state["changed"], next_at = False, now + cfg.every
                assert ctx.bus is not None
                ctx.bus.publish(ESTOP, EStop(operator_id=ctx.instance, engaged=bool(state["engaged"]),
                                             created_at=time.time(), reason="operator"), source=ctx.instance)  # fmt: skip
            ctx.shutdown.wait(0.05)
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(OperatorConfig, {"default": OperatorConfig()}, argv, "mea operator",
                            OperatorConfig.__doc__ or ""))  # fmt: skip
