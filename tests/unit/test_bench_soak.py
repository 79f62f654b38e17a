"""`mea bench soak`'s arithmetic: growth from the end of the warm-up, net of the replay it filled."""

from __future__ import annotations

import os

import pytest

from mea_tools.bench.soak import Series, growth_rows, rss_bytes

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


def test_a_transient_at_either_end_does_not_count_as_growth():
    """Medians over the windows: one sample caught mid-burst (an augmentation, a checkpoint) is not growth."""
    steady = [(600 + 10 * k, 330 * MB, 0) for k in range(300)]
    steady[1] = (610, 369 * MB, 0)  # a burst right after the warm-up
    steady[-1] = (steady[-1][0], 369 * MB, 0)  # and at the very end
    rows = growth_rows([Series("augmenter/augmenter-0", 1, steady)], warmup=600, limit=5.0, window=300)
    assert rows[0]["growth %"] == pytest.approx(0.0) and rows[0]["ok"] is True
    creeping = [(600 + 10 * k, (330 + k / 10) * MB, 0) for k in range(300)]  # +30 MB over 50 min
    rows = growth_rows([Series("augmenter/augmenter-0", 1, creeping)], warmup=600, limit=5.0, window=300)
    assert rows[0]["growth %"] > 5.0 and rows[0]["ok"] is False
