"""The actor's delivery: unacknowledged episodes are kept while a learner is expected, even one cut off."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

from services.actor.config import ActorConfig
from services.actor.main import EpisodeSender, _metrics
from services.common.bus.inproc import Hub, InProcBus
from services.common.metrics import ServiceMetrics
from services.common.runtime import Shutdown
from tests.helpers import build_episode


def _delivery(hub: Hub, limit: int = 3) -> tuple[EpisodeSender, SimpleNamespace]:
    ctx = SimpleNamespace(bus=InProcBus(hub), instance="actor-0", shutdown=Shutdown())
    mx = _metrics(SimpleNamespace(metrics=ServiceMetrics("actor", "actor-0")))
    return EpisodeSender(ctx, ActorConfig(unacked_limit=limit), mx), ctx


def test_without_a_learner_ever_the_oldest_go_and_are_counted():
    d, _ = _delivery(Hub())
    for k in range(5):
        d.wait_for_room()  # never waits: nobody acknowledges
        d.publish(build_episode(T=2, seed=k, actor_id="actor-0"))
    assert len(d.outbox) == 3 and d.outbox.evicted == 2
    assert d.mx["evicted"]._value.get() == 2


def test_a_learner_that_went_away_is_waited_for_and_nothing_is_let_go():
    hub = Hub()
    token = InProcBus(hub).declare_alive("learner", "learner-0")
    d, ctx = _delivery(hub)
    for k in range(3):
        d.publish(build_episode(T=2, seed=k, actor_id="actor-0"))
    token.close()  # the learner is cut off (or crashed) with 3 episodes unacknowledged
    assert not d.learner_alive() and d.learner_expected()
    threading.Timer(0.5, ctx.shutdown.set).start()
    t0 = time.monotonic()
    d.wait_for_room()  # waits for its return (here: until the actor is stopped)
    assert time.monotonic() - t0 >= 0.4
    assert len(d.outbox) == 3 and d.outbox.evicted == 0
