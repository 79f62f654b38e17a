"""One actor service run in this process over the in-process bus, with weights already announced."""

from __future__ import annotations

from proto.topics import EPISODES_RAW
from proto.weights import WeightsBlob
from services.actor.config import ActorConfig
from services.actor.main import run
from services.common.bus import Hub, InProcBus
from services.common.weights import WeightsServer


def published_episodes(cfg: ActorConfig, blob: WeightsBlob) -> list:
    """What one actor publishes with ``blob`` as its weights (no learner: no gate)."""
    hub = Hub()
    observer = InProcBus(hub)
    sub = observer.subscribe(EPISODES_RAW, capacity=256)
    server = WeightsServer(observer, "learner-0")
    server.publish(blob)
    try:
        assert run(cfg, bus_factory=lambda _c: InProcBus(hub)) == 0
        return [d.message for d in sub.drain()]
    finally:
        server.close()
