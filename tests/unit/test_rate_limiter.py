"""Rate limiters as math: Reverb-style sample-to-insert bounds, no deadlock, exact counts."""

from __future__ import annotations

from fractions import Fraction

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.algorithms.rate_limiter import UNLIMITED, MinSize, SampleToInsertRatio

pytestmark = pytest.mark.unit

SETTINGS = settings(max_examples=300, deadline=None, derandomize=True)

spi_values = st.one_of(
    st.sampled_from([0.01, 0.1, 0.25, 1 / 3, 0.5, 1.0, 1.0000001, 2.0, 4.0, 32.0]),
    st.floats(0.01, 50.0, allow_nan=False, allow_infinity=False),
)
limiters = st.builds(
    lambda spi, min_size, factor: SampleToInsertRatio(spi, min_size, max(1.0, spi) * factor),
    spi_values,
    st.integers(1, 300),
    st.one_of(st.just(1.0), st.floats(1.0, 4.0)),  # 1.0: the tightest buffer the limiter accepts
)


# ------------------------------------------------------------------------------ explicit examples


def test_unit_ratio_example() -> None:
    rl = SampleToInsertRatio(samples_per_insert=1.0, min_size_to_sample=100, error_buffer=50)
    assert (rl.min_diff, rl.max_diff) == (50.0, 150.0)
    assert not rl.can_sample() and rl.samples_allowed() == 0 and rl.inserts_allowed() == 150
    rl.inserted(99)
    assert not rl.can_sample()
    rl.inserted(1)
    assert rl.samples_allowed() == 50 and rl.can_sample(50) and not rl.can_sample(51)  # the burst at min size
    assert rl.inserts_allowed() == 50 and rl.can_insert(50) and not rl.can_insert(51)
    rl.sampled(50)
    assert not rl.can_sample() and rl.inserts_allowed() == 100
    for _ in range(1000):  # steady state: one update per env step
        rl.inserted(1)
        assert rl.samples_allowed() == 1
        rl.sampled()
        assert not rl.can_sample()
    assert (rl.inserts, rl.samples) == (1100, 1050)


def test_fractional_ratio_example() -> None:
    rl = SampleToInsertRatio(
        samples_per_insert=0.25, min_size_to_sample=8, error_buffer=1.0
    )  # 1 update per 4 steps
    rl.inserted(8)
    assert rl.diff == 2.0 and rl.samples_allowed() == 1
    rl.sampled()
    assert not rl.can_sample() and rl.inserts_allowed() == 8  # diff may rise from 1 to max_diff 3
    rl.inserted(3)
    assert not rl.can_sample()
    rl.inserted(1)
    assert rl.can_sample() and not rl.can_sample(2)


def test_producers_wait_when_ahead_and_learner_waits_when_ahead() -> None:
    rl = SampleToInsertRatio(samples_per_insert=2.0, min_size_to_sample=10, error_buffer=4.0)
    rl.inserted(10)
    assert rl.inserts_allowed() == 2  # diff 20 <= 24
    rl.inserted(50)  # an in-flight episode overshoots; it is recorded anyway
    assert not rl.can_insert() and rl.inserts_allowed() == 0
    assert rl.samples_allowed() == 120 - 16
    rl.sampled(rl.samples_allowed())
    assert not rl.can_sample() and rl.can_insert()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((0.0, 10, 5.0), "samples_per_insert"),
        ((-1.0, 10, 5.0), "samples_per_insert"),
        ((float("inf"), 10, 5.0), "samples_per_insert"),
        ((1.0, 0, 5.0), "min_size_to_sample"),
        ((1.0, 2.5, 5.0), "min_size_to_sample"),
        ((1.0, 10, 0.5), "error_buffer"),
        ((4.0, 10, 3.9), "error_buffer"),
        ((0.1, 10, 0.99), "error_buffer"),
    ],
)
def test_invalid_parameters_raise(args: tuple, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        SampleToInsertRatio(*args)


def test_negative_counts_raise() -> None:
    rl = SampleToInsertRatio(1.0, 1, 1.0)
    with pytest.raises(ValueError, match="non-negative"):
        rl.inserted(-1)
    with pytest.raises(ValueError, match="non-negative"):
        rl.can_sample(-2)


def test_state_dict_round_trip() -> None:
    rl = SampleToInsertRatio(0.5, 20, 3.0)
    rl.inserted(37)
    rl.sampled(9)
    other = SampleToInsertRatio(0.5, 20, 3.0)
    other.load_state_dict(rl.state_dict())
    assert (other.inserts, other.samples) == (37, 9)
    assert other.samples_allowed() == rl.samples_allowed() and other.inserts_allowed() == rl.inserts_allowed()
    assert all(isinstance(v, int | float) for v in rl.state_dict().values())


def test_min_size_limiter() -> None:
    rl = MinSize(5)
    assert not rl.can_sample() and rl.samples_allowed() == 0 and rl.can_insert(10**9)
    rl.inserted(5)
    assert rl.can_sample(10**6) and rl.samples_allowed() == UNLIMITED and rl.inserts_allowed() == UNLIMITED
    rl.sampled(1000)
    assert rl.can_sample()
    restored = MinSize(5)
    restored.load_state_dict(rl.state_dict())
    assert (restored.inserts, restored.samples) == (5, 1000)


# ------------------------------------------------------------------------------ properties


def exact_bounds(rl: SampleToInsertRatio) -> tuple[Fraction, Fraction]:
    """(min_diff, max_diff) computed exactly from the float parameters, as the limiter does."""
    offset = Fraction(rl.samples_per_insert) * rl.min_size_to_sample
    return offset - Fraction(rl.error_buffer), offset + Fraction(rl.error_buffer)


def _check_consistency(rl: SampleToInsertRatio) -> None:
    """``can_*(n)`` agrees with ``*_allowed()`` at and around the boundary."""
    s, i = rl.samples_allowed(), rl.inserts_allowed()
    for n in {1, 2, max(1, s), s + 1}:
        assert rl.can_sample(n) == (n <= s), (n, s)
    for n in {1, 2, max(1, i), i + 1}:
        assert rl.can_insert(n) == (n <= i), (n, i)


@SETTINGS
@given(
    rl=limiters,
    ops=st.lists(
        st.tuples(st.sampled_from(["insert", "forced_insert", "sample"]), st.integers(1, 60)), max_size=200
    ),
)
def test_never_blocks_both_sides_under_random_interleavings(rl: SampleToInsertRatio, ops: list) -> None:
    spi = Fraction(rl.samples_per_insert)
    for op, n in ops:
        if op == "insert" and rl.can_insert(1):  # an actor starts an episode only when allowed ...
            rl.inserted(n)  # ... and its whole episode is inserted
        elif op == "forced_insert":  # an episode already in flight when the limit was reached
            rl.inserted(n)
        elif op == "sample":
            for _ in range(n):
                if not rl.can_sample():
                    break
                rl.sampled()
        if rl.inserts >= rl.min_size_to_sample:
            assert rl.can_sample() or rl.can_insert(), (rl.inserts, rl.samples)
        if rl.samples:  # gated updates never run ahead of the ratio by more than the buffer
            assert spi * rl.inserts - rl.samples >= exact_bounds(rl)[0]
        _check_consistency(rl)


@SETTINGS
@given(rl=limiters, inserts=st.integers(0, 10**6), samples=st.integers(0, 10**7))
def test_at_least_one_side_is_open_in_every_state(
    rl: SampleToInsertRatio, inserts: int, samples: int
) -> None:
    rl.load_state_dict({"inserts": max(inserts, rl.min_size_to_sample), "samples": samples})
    assert rl.can_sample() or rl.can_insert()
    _check_consistency(rl)


@SETTINGS
@given(rl=limiters, steps=st.integers(1, 600))
def test_alternating_producer_and_learner_track_the_ratio(rl: SampleToInsertRatio, steps: int) -> None:
    """Insert while allowed, then sample while allowed: the realised ratio stays within the buffer."""
    spi = Fraction(rl.samples_per_insert)
    for _ in range(steps):
        if rl.can_insert():
            rl.inserted(1)
        rl.sampled(rl.samples_allowed())
        if rl.inserts >= rl.min_size_to_sample:
            diff = spi * rl.inserts - rl.samples
            lo, hi = exact_bounds(rl)
            assert lo <= diff <= hi
            assert diff - lo < 1  # the learner has caught up
