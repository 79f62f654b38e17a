"""The discrete action space on the wire (proto/discrete_actions.py)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from proto.actions import JAW, THETA
from proto.discrete_actions import NAMES, TOGGLE, TRIVIAL, index_of, rotate_c4, to_vector

pytestmark = pytest.mark.contract


@pytest.mark.parametrize(("index", "jaw_open"), list(itertools.product(range(9), (True, False))))
def test_every_action_round_trips(index: int, jaw_open: bool):
    a = to_vector(index, jaw_open)
    assert a.shape == (5,) and np.all(np.abs(a) <= 1.0)
    assert index_of(a, jaw_open) == index
    assert (a[JAW] > 0) == (jaw_open != (index == TOGGLE))  # the command after the step
    assert np.count_nonzero(np.delete(a, JAW)) == (0 if index == TOGGLE else 1)


def test_the_layout_is_the_papers():
    assert to_vector(NAMES.index("+x"), True).tolist() == [1, 1, 0, 0, 0]
    assert to_vector(NAMES.index("-y"), False).tolist() == [-1, 0, -1, 0, 0]
    assert to_vector(NAMES.index("+yaw"), True)[THETA] == 1.0
    assert to_vector(TOGGLE, True).tolist() == [-1, 0, 0, 0, 0]  # open -> closes


def test_continuous_actions_are_not_discrete():
    assert index_of(np.array([1, 0.4, -0.2, 0, 0]), True) is None
    assert index_of(np.array([1, 1, 1, 0, 0]), True) is None
    assert index_of(np.array([-1, 1, 0, 0, 0]), True) is None  # a toggle cannot also move


def test_c4_turns_xy_counter_clockwise_and_keeps_the_trivial_set():
    names = {n: i for i, n in enumerate(NAMES)}
    assert [NAMES[rotate_c4(names["+x"], k)] for k in range(4)] == ["+x", "+y", "-x", "-y"]
    for i in TRIVIAL:
        assert all(rotate_c4(i, k) == i for k in range(4))
    for i in set(range(9)) - TRIVIAL:
        v = to_vector(i, True)[1:3]
        w = to_vector(rotate_c4(i, 1), True)[1:3]
        assert np.allclose(w, [-v[1], v[0]])  # the same as rotating (dx, dy) by +90 degrees
        assert rotate_c4(i, 4) == i and rotate_c4(rotate_c4(i, 1), 3) == i
