"""`mea bench soak`'s arithmetic: growth from the end of the warm-up, net of the replay it filled."""

from __future__ import annotations

import os

import pytest

from services.bench.soak import Series, growth_rows, rss_bytes

pytestmark = pytest.mark.unit
MB = 1_000_000


def test_growth_is_measured_from_the_warm_up_and_net_of_the_replay():
    learner = Series(
        "learner/learner-0", 10, [(0, 100 * MB, 0), (600, 500 * MB, 300 * MB), (3600, 540 * MB, 330 * MB)]
    )
    actor = Series("actor/actor-0", 11, [(0, 200 * MB, 0), (610, 300 * MB, 0), (3600, 318 * MB, 0)])
    rows = {r["instance"]: r for r in growth_rows([learner, actor], warmup=600, limit=5.0)}
    lr = rows["learner/learner-0"]
    assert lr["growth %"] == pytest.approx(8.0) and lr["growth net of replay %"] == pytest.approx(2.0)
    assert lr["ok"] is True and lr["minutes measured"] == pytest.approx(50.0)
    ar = rows["actor/actor-0"]
    assert ar["growth %"] == pytest.approx(6.0) and ar["ok"] is False  # over 5% with no replay to explain it


def test_a_process_that_ended_during_warm_up_has_no_growth():
    rows = growth_rows(
        [Series("augmenter/augmenter-0", 12, [(0, MB, 0), (100, MB, 0)])], warmup=600, limit=5.0
    )
    assert rows[0]["growth %"] is None and rows[0]["ok"] is None


def test_rss_of_this_process_and_of_no_process():
    assert rss_bytes(os.getpid()) > 10 * MB
    assert rss_bytes(2**22 + 12345) is None
