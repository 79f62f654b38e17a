"""The retention policy: segment names and their order, when a segment rolls, which files go."""

from __future__ import annotations

import random

import pytest

from services.common.retention import (
    LEGACY_INDEX,
    ordered_segments,
    segment_key,
    segment_name,
    should_roll,
    to_delete,
)

pytestmark = pytest.mark.unit


def test_segment_names_round_trip_and_other_files_are_not_segments():
    assert segment_name(0, 0) == "raw-0-0000.mcap"
    assert segment_name(12, 10_000) == "raw-12-10000.mcap"  # past the padding, still one name
    assert segment_name(3, 7, prefix="x", suffix=".bin") == "x-3-0007.bin"
    for run, index in [(0, 0), (2, 13), (10, 9999), (1, 123456)]:
        assert segment_key(segment_name(run, index)) == (run, index)
    assert segment_key("raw-4.mcap") == (4, LEGACY_INDEX)  # a recording from before segments
    for other in ("raw-0-0001.mcap.tmp", "raw-.mcap", "raw-a-1.mcap", "demos.mcap", "raw-1-2-3.mcap",
                  "xraw-1-2.mcap", "raw-1-2.mcapx", "summary.json"):  # fmt: skip
        assert segment_key(other) is None, other
    with pytest.raises(ValueError):
        segment_name(-1, 0)


def test_segments_are_ordered_numerically_by_run_then_index():
    expected = (
        ["raw-0.mcap"]  # a single-file recording of run 0 comes before any segment of run 0
        + [segment_name(0, i) for i in range(12)]
        + [segment_name(2, 0), segment_name(2, 9), "raw-2-10.mcap", segment_name(2, 11)]  # unpadded too
        + [segment_name(9, 0), "raw-10.mcap", segment_name(10, 0), segment_name(10, 1)]
    )
    shuffled = [*expected, "raw-3-0001.mcap.tmp", "notes.txt"]
    random.Random(0).shuffle(shuffled)
    assert ordered_segments(shuffled) == expected
    assert sorted(expected) != expected  # lexicographic order would be wrong here
    assert ordered_segments([]) == []


@pytest.mark.parametrize(
    ("size", "age", "max_bytes", "max_seconds", "roll"),
    [
        (99, 10.0, 100, 60.0, False),
        (100, 10.0, 100, 60.0, True),  # the size reached
        (0, 60.0, 100, 60.0, True),  # the age reached
        (10**12, 10**9, 0, 0.0, False),  # no limits: one segment for ever
        (10**12, 0.0, 0, 60.0, False),
        (100, 10**9, 100, 0.0, True),
    ],
)
def test_a_segment_rolls_at_its_size_or_its_age(size, age, max_bytes, max_seconds, roll):
    assert should_roll(size, age, max_bytes, max_seconds) is roll


def files(*sizes: int) -> list[tuple[str, int]]:
    return [(f"f{i}", s) for i, s in enumerate(sizes)]


def test_keep_counts_the_newest_and_deletes_the_rest_oldest_first():
    assert to_delete(files(5, 5, 5, 5), keep=2) == ["f0", "f1"]
    assert to_delete(files(5, 5), keep=2) == []
    assert to_delete(files(5, 5, 5), keep=1) == ["f0", "f1"]
    assert to_delete(files(5, 5, 5)) == []  # no count limit and no budget: everything stays
    assert to_delete([], keep=1, max_bytes=1) == []


def test_the_budget_is_respected_but_the_newest_always_stays():
    assert to_delete(files(4, 4, 4, 4), max_bytes=12) == ["f0"]
    assert to_delete(files(4, 4, 4, 4), max_bytes=11) == ["f0", "f1"]
    assert to_delete(files(4, 4, 4, 4), max_bytes=11, keep=1) == ["f0", "f1", "f2"]
    assert to_delete(files(1, 1, 100), max_bytes=10) == ["f0", "f1"]  # newest over budget: kept alone
    assert to_delete(files(100), max_bytes=10) == []
    # what stays has no holes: a small old file does not survive past a big one that went
    assert to_delete(files(1, 50, 5, 5), max_bytes=20) == ["f0", "f1"]


def test_any_inputs_keep_the_newest_and_stay_within_the_limits():
    rng = random.Random(1)
    for _ in range(500):
        fs = files(*(rng.randint(0, 50) for _ in range(rng.randint(1, 12))))
        keep, budget = rng.randint(0, 5), rng.choice([0, rng.randint(1, 200)])
        doomed = to_delete(fs, keep=keep, max_bytes=budget)
        kept = fs[len(doomed) :]
        assert doomed == [n for n, _ in fs[: len(doomed)]]  # the oldest, in order
        assert kept and kept[-1] == fs[-1]
        within = (not keep or len(kept) <= keep) and (not budget or sum(s for _, s in kept) <= budget)
        assert within or len(kept) == 1
        if doomed:  # and no more: the next older file would not have fitted
            more = fs[len(doomed) - 1 :]
            assert (keep and len(more) > keep) or (budget and sum(s for _, s in more) > budget)


def test_negative_limits_are_refused():
    with pytest.raises(ValueError):
        to_delete(files(1), keep=-1)
    with pytest.raises(ValueError):
        to_delete(files(1), max_bytes=-1)
