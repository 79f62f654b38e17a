"""Assertions shared by the task tests: what a refused action leaves unchanged."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest


def refused_actions_change_nothing(env, ok: np.ndarray, bad: float, state: Callable[[], tuple]):
    """Steps ``ok`` twice after ``reset(11)`` for a reference observation, then resets and steps once:
    an action with ``bad`` in it and a too-short one must be refused (ValueError) leaving ``state()``
    (time, a position array, then plain values) as it was. Returns (reference, the observation of the
    next ``ok`` step), which the caller compares as its observations need."""
    env.reset(11)
    env.step(ok)
    reference = env.step(ok)[0]
    env.reset(11)
    env.step(ok)
    before = state()
    action = ok.copy()
    action[2] = bad
    with pytest.raises(ValueError, match="finite"):
        env.step(action)
    with pytest.raises(ValueError, match="shape"):
        env.step(ok[:4])
    after = state()
    assert before[0] == after[0] and np.array_equal(before[1], after[1]) and before[2:] == after[2:]
    return reference, env.step(ok)[0]
