"""`mea serve`: the real-robot inference service, a shell around ``core.sessions.InferenceCore``.

Design notes: docs/architecture-notes.md, services/inference/main.py."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from proto.inference import ActRequest, ResetRequest
from proto.topics import ESTOP, SERVE_ACT, SERVE_RESET, WEIGHTS_ANNOUNCE, WEIGHTS_LATEST
from services.common import config, run_key, weights_file
from services.common.bus.base import Bus, Delivery
from services.common.config import ServiceConfig
from services.common.metrics import ServiceMetrics
from services.common.runtime import ServiceContext, subscribing_bus_factory, torch_threads
from services.common.weights import WeightsClient
from services.inference.config import PRESETS, ServeConfig
from services.inference.core.envelope import CLAMP_REASONS, HOLD_REASONS
from services.inference.core.sessions import (
    REFUSAL_REASONS,
    SESSION_HOLDS,
    InferenceCore,
    SwapRefusedError,
    refused_reset,
    sessionless_hold,
)

log = logging.getLogger(__name__)
WEIGHTS_POLL_SECONDS = 0.01
"""How often the main loop looks for announced weights and e-stops."""
_LATENCY = (0.0005, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.01, 0.02, 0.05, 0.1, 0.25)


def serve_metrics(m: ServiceMetrics) -> dict:
    mx = {
        "act_seconds": m.histogram("mea_inference_act_seconds", "Server time of one act() (s).", _LATENCY),
        "requests": m.counter("mea_inference_requests", "Requests answered, by kind.", ["kind"]),
        "holds": m.counter("mea_inference_holds", "Actions answered with a hold, by reason.", ["reason"]),
        "clamps": m.counter("mea_inference_clamps", "Actions clamped by the envelope, by limit.", ["reason"]),
        "sessions": m.gauge("mea_inference_sessions", "Robot sessions open."),
        "version": m.gauge("mea_inference_policy_version", "Newest weights version loaded (-1: none)."),
        "served_version": m.gauge(
            "mea_inference_served_version", "Weights version of the last action served."
        ),
        "swaps": m.counter("mea_inference_swaps", "Weights versions made current."),
        "refused": m.counter(
            "mea_inference_weights_refused", "Weights refused (old ones kept), by reason.", ["reason"]
        ),  # fmt: skip
        "first_action": m.histogram(
            "mea_inference_swap_to_first_action_seconds",
            "From a version's announcement (its created_at) to the first action it served (s).",
            (0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0),
        ),
        "estop": m.gauge("mea_inference_estop_engaged", "1 while an operator's e-stop is engaged."),
    }
    for r in (*HOLD_REASONS, *SESSION_HOLDS):
        mx["holds"].labels(r)
    for r in CLAMP_REASONS:
        mx["clamps"].labels(r)
    for r in (*REFUSAL_REASONS, "invalid"):
        mx["refused"].labels(r)
    mx["version"].set(-1)
    mx["served_version"].set(-1)
    return mx


def _starting(d: Delivery, kind: str):
    """The answer while the server is still loading its policy."""
    if kind == "reset":
        return refused_reset(d.message.session, "server starting")
    return sessionless_hold(d.message, "no_policy", d.message.episode)


class Server:
    """The query handlers and the weights/e-stop loop around one ``InferenceCore``."""

    def __init__(self, cfg: ServeConfig, ctx: ServiceContext, weights: WeightsClient | None, estop) -> None:
        self.cfg, self.ctx, self.weights, self.estop_sub = cfg, ctx, weights, estop
        self.core = InferenceCore(cfg.settings(), cfg.limits_for())
        self.mx = serve_metrics(ctx.metrics)
        self.counts = {"acts": 0, "resets": 0, "holds": 0, "swaps": 0, "refused": 0}
        self._created_at: dict[int, float] = {}  # version -> when it was made, for swap_to_first_action
        self._served = -1
        self._estops: dict[str, bool] = {}  # operator -> its latest e-stop state (latched per operator)

    # weights ---------------------------------------------------------------------------------
    def offer(self, blob) -> bool:
        try:
            loaded = self.core.offer(blob)
        except SwapRefusedError as exc:
            self.counts["refused"] += 1
            self.mx["refused"].labels(exc.reason).inc()
            log.warning("weights refused, still serving the old ones",
                        extra={"version": blob.version, "reason": exc.reason, "error": str(exc)})  # fmt: skip
            return False
        self._created_at = {loaded.version: blob.created_at}
        self.counts["swaps"] += 1
        self.mx["swaps"].inc()
        self.mx["version"].set(loaded.version)
        self.ctx.policy_version = loaded.version
        log.info("serving weights", extra={"version": loaded.version, "run_id": loaded.run_id,
                                           "algorithm": loaded.algorithm})  # fmt: skip
        return True

    def load_pinned(self) -> None:
        key = run_key.load(self.cfg.service.run_key_file) if self.cfg.service.run_key_file else None
        path = weights_file.resolve(
            Path(self.cfg.weights), None if self.cfg.version < 0 else self.cfg.version
        )
        blob = weights_file.read(path, key, self.ctx.bus.limits)  # type: ignore[union-attr]
        if not self.offer(blob):
            raise SystemExit(f"serve: {path}: the weights do not load (see the log)")

    def on_bad_message(self, topic, key_expr, err) -> None:
        if topic in (WEIGHTS_LATEST, WEIGHTS_ANNOUNCE):  # unsealed, forged, corrupt or malformed
            self.counts["refused"] += 1
            self.mx["refused"].labels("invalid").inc()

    # queries ---------------------------------------------------------------------------------
    def on_reset(self, d: Delivery):
        req: ResetRequest = d.message  # type: ignore[assignment]
        try:
            reply = self.core.reset(req, time.monotonic(), d.sender)
        except Exception as exc:  # noqa: BLE001 - the robot gets a refusal, never silence
            log.exception("reset failed", extra={"session": req.session})
            reply = refused_reset(req.session, f"server error: {exc}")
        self.counts["resets"] += 1
        self.mx["requests"].labels("reset").inc()
        self.mx["sessions"].set(len(self.core.sessions))
        if not reply.accepted:
            log.info("reset refused", extra={"session": req.session, "reason": reply.reason})
        return reply

    def on_act(self, d: Delivery):
        req: ActRequest = d.message  # type: ignore[assignment]
        try:
            reply = self.core.act(req, time.monotonic(), time.time(), d.sender)
        except Exception:  # noqa: BLE001 - the robot gets a hold with the reason, never silence
            log.exception("act failed", extra={"session": req.session, "step": req.step})
            reply = sessionless_hold(req, "server_error", req.episode)
        self.counts["acts"] += 1
        self.mx["requests"].labels("act").inc()
        self.mx["act_seconds"].observe(reply.compute_seconds)
        if reply.held:
            self.counts["holds"] += 1
        for r in reply.reasons:
            (self.mx["holds"] if reply.held else self.mx["clamps"]).labels(r).inc()
        v = reply.policy_version
        if v != self._served and v >= 0:
            self._served = v
            self.mx["served_version"].set(v)
            made = self._created_at.get(v)
            if made is not None:
                self.mx["first_action"].observe(max(0.0, time.time() - made))
        return reply

    # loop ------------------------------------------------------------------------------------
    def step(self) -> None:
        for d in self.estop_sub.drain():
            op, engaged = d.message.operator_id, bool(d.message.engaged)
            if self._estops.get(op) != engaged:
                log.warning("e-stop " + ("engaged" if engaged else "released"),
                            extra={"operator": op, "reason": d.message.reason})  # fmt: skip
            self._estops[op] = engaged
        self.core.estop = any(self._estops.values())
        self.mx["estop"].set(int(self.core.estop))
        if self.weights is not None:
            blob = self.weights.poll()
            if blob is not None:
                self.offer(blob)
        self.mx["sessions"].set(len(self.core.sessions))

    def heartbeat_counters(self) -> dict[str, float]:
        return {**self.counts, "sessions": len(self.core.sessions), "estop": int(self.core.estop)}


def run(cfg: ServeConfig, bus_factory: Callable[[ServiceConfig], Bus] | None = None,
        ready: Callable[[Server], None] | None = None) -> int:  # fmt: skip
    """Serve until stopped; ``ready(server)`` is called once it answers queries (tests)."""
    with torch_threads(cfg.torch_threads):
        return _run(cfg, bus_factory, ready)


def _run(cfg: ServeConfig, bus_factory: Callable[[ServiceConfig], Bus] | None,
         ready: Callable[[Server], None] | None) -> int:  # fmt: skip
    holder: dict[str, object] = {}

    def answer(kind: str):
        def handler(d: Delivery):
            server = holder.get("server")
            if not isinstance(server, Server):  # queries answered before the policy is loaded
                return _starting(d, kind)
            return server.on_reset(d) if kind == "reset" else server.on_act(d)

        return handler

    def declare(bus: Bus) -> None:
        # before the liveliness token: a robot that sees the server can be answered at once
        holder["estop"] = bus.subscribe(ESTOP, capacity=16)
        holder["weights"] = None if cfg.weights else WeightsClient(bus)
        holder["handles"] = [bus.answer(SERVE_RESET, answer("reset"), source=ctx.instance),
                             bus.answer(SERVE_ACT, answer("act"), source=ctx.instance)]  # fmt: skip

    def counters() -> dict[str, float]:
        s = holder.get("server")
        return s.heartbeat_counters() if isinstance(s, Server) else {}

    make_bus = subscribing_bus_factory(bus_factory, declare)
    ctx = ServiceContext("inference", cfg.service, bus_factory=make_bus, counters=counters)
    with ctx:
        server = Server(cfg, ctx, holder["weights"], holder["estop"])  # type: ignore[arg-type]
        bus = ctx.bus
        assert bus is not None
        previous = bus.on_bad_message

        def on_bad(topic, key_expr, err) -> None:
            server.on_bad_message(topic, key_expr, err)
            if previous is not None:
                previous(topic, key_expr, err)

        bus.on_bad_message = on_bad
        if cfg.weights:
            try:
                server.load_pinned()
            except weights_file.WeightsFileError as exc:
                raise SystemExit(f"serve: {exc}") from None
        holder["server"] = server
        ctx.detail = f"serving {cfg.weights or 'the learner broadcast'}"
        log.info("serving", extra={"instance": ctx.instance, "weights": cfg.weights or "follow"})
        if ready is not None:
            ready(server)
        try:
            while not ctx.shutdown.is_set():
                server.step()
                ctx.shutdown.wait(WEIGHTS_POLL_SECONDS)
        finally:
            for h in holder["handles"]:  # type: ignore[attr-defined]
                h.close()
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(ServeConfig, PRESETS, argv, "mea serve", ServeConfig.__doc__ or ""))


__all__ = ["Server", "main", "run"]
