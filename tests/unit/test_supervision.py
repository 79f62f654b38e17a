"""Restart arithmetic of `mea run`'s supervision: backoff, the window, giving up."""

from __future__ import annotations

import pytest

from services.supervision import RestartPolicy, RestartSettings


def test_backoff_doubles_up_to_the_cap_and_the_limit_within_the_window_is_final():
    p = RestartPolicy(RestartSettings(limit=3, window_seconds=100.0, first_delay=1.0, max_delay=3.0))
    assert [p.on_exit("actor-0", t) for t in (0.0, 10.0, 20.0)] == [1.0, 2.0, 3.0]  # 4.0 capped at 3.0
    assert p.on_exit("actor-0", 30.0) is None  # a 4th exit within 100 s: give up
    assert p.restarts["actor-0"] == 3
    # other instances have their own count
    assert p.on_exit("learner-0", 30.0) == 1.0


def test_exits_older_than_the_window_no_longer_count():
    p = RestartPolicy(RestartSettings(limit=2, window_seconds=60.0, first_delay=2.0, max_delay=30.0))
    assert p.on_exit("a", 0.0) == 2.0
    assert p.on_exit("a", 50.0) == 4.0
    assert p.on_exit("a", 100.0) == 4.0  # the exit at 0 left the window; 50 and 100 remain
    assert p.on_exit("a", 105.0) is None  # 50, 100, 105: three within 60 s
    assert p.restarts["a"] == 3


def test_limit_zero_never_restarts_and_bad_settings_are_refused():
    assert RestartPolicy(RestartSettings(limit=0)).on_exit("a", 0.0) is None
    with pytest.raises(ValueError):
        RestartSettings(limit=-1)
    with pytest.raises(ValueError):
        RestartSettings(first_delay=5.0, max_delay=1.0)
