"""The actor's outbox (services/actor/outbox.py): kept until acked, resent on a consumer restart or
a late ack, bounded."""

from __future__ import annotations

import pytest

from services.actor.outbox import Outbox

pytestmark = pytest.mark.unit


def test_acked_episodes_are_forgotten_and_others_kept():
    box: Outbox[str] = Outbox(capacity=8, resend_after=60.0)
    for i in range(4):
        box.sent(f"e{i}", f"episode {i}", now=float(i))
    assert box.ack(["e1", "e3", "unknown"]) == 2
    assert len(box) == 2 and "e0" in box and "e2" in box and "e1" not in box
    assert box.acked == 2


def test_nothing_is_due_before_the_timeout_or_a_restart():
    box: Outbox[str] = Outbox(capacity=8, resend_after=60.0)
    box.sent("a", "A", now=0.0)
    assert box.due(now=59.0) == []
    assert box.due(now=60.0) == [("a", "A")]
    assert box.due(now=61.0) == []  # sent again at 60: the clock starts over
    assert box.due(now=120.0) == [("a", "A")]
    assert box.resent == 2


def test_a_consumer_restart_resends_only_what_was_sent_before_it():
    box: Outbox[str] = Outbox(capacity=8, resend_after=600.0)
    box.sent("old", "O", now=10.0)
    box.sent("new", "N", now=30.0)
    assert box.due(now=31.0, consumer_restarted_at=20.0) == [("old", "O")]
    # the same restart does not trigger again: "old" was sent at 31 > 20
    assert box.due(now=32.0, consumer_restarted_at=20.0) == []


def test_full_outbox_lets_the_oldest_go_and_counts_it():
    box: Outbox[int] = Outbox(capacity=3, resend_after=60.0)
    for i in range(5):
        box.sent(str(i), i, now=float(i))
    assert len(box) == 3 and box.full and box.evicted == 2
    assert [eid for eid, _ in box.due(now=1000.0)] == ["2", "3", "4"]  # oldest first


def test_sending_the_same_id_again_does_not_duplicate():
    box: Outbox[str] = Outbox(capacity=3, resend_after=60.0)
    box.sent("a", "A", now=0.0)
    box.sent("a", "A", now=50.0)
    assert len(box) == 1 and box.due(now=100.0) == [] and box.due(now=110.0) == [("a", "A")]


@pytest.mark.parametrize(("capacity", "resend_after"), [(0, 1.0), (1, 0.0)])
def test_bad_settings_are_refused(capacity: int, resend_after: float):
    with pytest.raises(ValueError):
        Outbox(capacity, resend_after)
