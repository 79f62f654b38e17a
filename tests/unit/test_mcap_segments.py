"""Segmented recordings: rolling by size and age, complete files with their metadata, the byte
budget, and reading every segment back in order (old single-file recordings included)."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.common.mcap_io import (
    RECORDING_METADATA,
    RUN_METADATA,
    SEGMENT_METADATA,
    McapRecorder,
    ReadStats,
    SegmentedRecorder,
    read_messages,
    read_metadata,
    read_recording,
    recording_segments,
)
from services.common.retention import segment_name

pytestmark = [pytest.mark.unit, pytest.mark.timeout(60)]


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def ids(directory: Path, **kw) -> list[str]:
    return [m.episode_id for _, m in read_recording(directory, **kw)]


def names(directory: Path, **kw) -> list[str]:
    return [p.name for p in recording_segments(directory, **kw)]


def test_size_rolls_segments_each_a_complete_file_with_the_run_metadata(tmp_path, make_episode):
    eps = [make_episode(T=4, seed=i, episode_id=f"ep-{i}") for i in range(12)]
    with SegmentedRecorder(tmp_path, 0, metadata={"task": "block_pull"}, segment_bytes=1) as rec:
        assert rec.path == tmp_path / segment_name(0, 0)  # the first segment opens at once
        for ep in eps:
            rec.write(ep)
        assert rec.path is None  # the next segment waits for its first message: no empty file
    assert rec.message_count == 12
    assert names(tmp_path) == [segment_name(0, i) for i in range(12)]  # one message each, 10 after 9
    for i, path in enumerate(recording_segments(tmp_path)):
        meta = read_metadata(path)
        assert meta[RUN_METADATA] == {"task": "block_pull"}
        assert meta[SEGMENT_METADATA] == {"run": "0", "index": str(i)}
        assert (
            meta[RECORDING_METADATA]["status"] == "complete" and meta[RECORDING_METADATA]["messages"] == "1"
        )
        stats = ReadStats()
        assert len(list(read_messages(path, stats=stats))) == 1 and stats.indexed and not stats.truncated
    assert ids(tmp_path) == [ep.episode_id for ep in eps]


def test_no_limits_keep_one_segment(tmp_path, make_episode):
    with SegmentedRecorder(tmp_path, 3) as rec:
        for i in range(5):
            rec.write(make_episode(T=3, seed=i))
    assert names(tmp_path) == ["raw-3-0000.mcap"]


def test_the_size_estimate_counts_the_open_chunk(tmp_path, make_episode):
    rec = McapRecorder(tmp_path / "a.mcap", chunk_size=1 << 20, flush_interval_s=None)
    start = rec.size_bytes
    ep = make_episode(T=8, seed=1)
    rec.write(ep)
    assert rec.size_bytes >= start + len(ep.encode())  # still in the open chunk, counted all the same
    assert (tmp_path / "a.mcap.tmp").stat().st_size == start
    rec.close()
    assert rec.size_bytes == (tmp_path / "a.mcap").stat().st_size


def test_age_rolls_a_segment_even_while_idle_but_never_an_empty_one(tmp_path, make_episode):
    clock = Clock()
    rec = SegmentedRecorder(tmp_path, 1, segment_seconds=60.0, clock=clock)
    clock.t += 120
    rec.tick()  # nothing written: the segment stays open
    assert rec.path == tmp_path / segment_name(1, 0) and names(tmp_path, unfinished=False) == []
    rec.write(make_episode(T=3, seed=0, episode_id="a"))  # written, then rolled at once (open 120 s)
    assert rec.path is None and names(tmp_path) == [segment_name(1, 0)]
    rec.write(make_episode(T=3, seed=1, episode_id="b"))
    clock.t += 59
    rec.tick()
    assert rec.path == tmp_path / segment_name(1, 1)
    clock.t += 1
    rec.tick()  # 60 s: rolled without another message
    assert rec.path is None and names(tmp_path, unfinished=False) == [segment_name(1, 0), segment_name(1, 1)]
    rec.close()
    assert ids(tmp_path) == ["a", "b"]
    with pytest.raises(RuntimeError, match="closed"):
        rec.write(make_episode(T=3, seed=2))


def test_the_budget_deletes_the_oldest_finished_segments_of_every_run(tmp_path, make_episode):
    with McapRecorder(tmp_path / "raw-0.mcap") as old:  # a recording from before segments
        old.write(make_episode(T=4, seed=100, episode_id="legacy"))
    (tmp_path / "notes.txt").write_text("not a segment")
    size = (tmp_path / "raw-0.mcap").stat().st_size
    eps = [make_episode(T=4, seed=i, episode_id=f"ep-{i}") for i in range(6)]
    with SegmentedRecorder(tmp_path, 1, segment_bytes=1, max_bytes=int(3.5 * size)) as rec:
        assert names(tmp_path, unfinished=False) == ["raw-0.mcap"]  # within budget: kept
        for ep in eps:
            rec.write(ep)
    kept = names(tmp_path)
    assert kept == [segment_name(1, i) for i in range(6 - len(kept), 6)] and 2 <= len(kept) <= 4
    assert sum((tmp_path / n).stat().st_size for n in kept) <= 3.5 * size
    assert ids(tmp_path) == [ep.episode_id for ep in eps[6 - len(kept) :]]  # the newest, in order
    assert (tmp_path / "notes.txt").exists()
    # a budget smaller than one segment keeps the newest finished one
    with SegmentedRecorder(tmp_path, 2, segment_bytes=1, max_bytes=1) as rec:
        rec.write(make_episode(T=4, seed=50, episode_id="last"))
    assert names(tmp_path) == [segment_name(2, 0)] and ids(tmp_path) == ["last"]


def test_the_open_segment_is_never_deleted(tmp_path, make_episode):
    with SegmentedRecorder(tmp_path, 0, segment_bytes=1) as rec:
        for i in range(3):
            rec.write(make_episode(T=4, seed=i))
    open_one = SegmentedRecorder(tmp_path, 1, max_bytes=1)  # prunes at start, then opens its segment
    assert names(tmp_path) == [segment_name(0, 2), segment_name(1, 0) + ".tmp"]
    open_one.write(make_episode(T=4, seed=9))
    open_one.prune()
    assert names(tmp_path) == [segment_name(0, 2), segment_name(1, 0) + ".tmp"]
    open_one.close()
    assert names(tmp_path) == [segment_name(1, 0)]


def test_indexes_continue_after_the_segments_already_there(tmp_path, make_episode):
    with SegmentedRecorder(tmp_path, 0, segment_bytes=1) as rec:
        rec.write(make_episode(T=3, seed=0, episode_id="a"))
    stale = McapRecorder(tmp_path / segment_name(0, 1))  # a killed launcher's unfinished segment
    stale.write(make_episode(T=3, seed=1, episode_id="b"))
    stale.flush()
    with SegmentedRecorder(tmp_path, 0) as rec:  # the same run started again: nothing overwritten
        assert rec.path == tmp_path / segment_name(0, 2)
        rec.write(make_episode(T=3, seed=2, episode_id="c"))
    assert names(tmp_path) == [segment_name(0, 0), segment_name(0, 1) + ".tmp", segment_name(0, 2)]
    assert names(tmp_path, unfinished=False) == [segment_name(0, 0), segment_name(0, 2)]
    stats = ReadStats()
    assert ids(tmp_path, stats=stats) == ["a", "b", "c"]  # the unfinished one up to its last chunk
    assert stats.truncated and stats.messages == 3
    assert ids(tmp_path, unfinished=False) == ["a", "c"]


def test_a_run_dir_from_before_segments_reads_as_before(tmp_path, make_episode):
    for run, seed in ((0, 0), (1, 1), (10, 2), (2, 3)):
        with McapRecorder(tmp_path / f"raw-{run}.mcap") as rec:
            rec.write(make_episode(T=3, seed=seed, episode_id=f"run-{run}"))
    with SegmentedRecorder(tmp_path, 11, segment_bytes=1) as rec:  # resumed with segments
        rec.write(make_episode(T=3, seed=5, episode_id="run-11"))
    assert ids(tmp_path) == ["run-0", "run-1", "run-2", "run-10", "run-11"]
    assert list(read_recording(tmp_path / "missing")) == [] and recording_segments(tmp_path / "missing") == []


def test_negative_limits_are_refused(tmp_path):
    for kw in ({"segment_bytes": -1}, {"segment_seconds": -1.0}, {"max_bytes": -1}):
        with pytest.raises(ValueError):
            SegmentedRecorder(tmp_path, 0, **kw)
