"""Damaged files are named, never silently empty: a cut recording reads back every message written
whole before the cut and warns where it ends; `mea recording check` reports it; a damaged checkpoint,
eval-history line or weights file is named with why (issue 29, item 4)."""

from __future__ import annotations

import io
import logging
import random
from pathlib import Path

import numpy as np
import pytest
import torch
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk

from proto.seal import seal
from proto.weights import WeightsBlob
from services import recording_check
from services.common import weights_file
from services.common.mcap_io import McapRecorder, ReadStats, read_recording, recover
from services.common.retention import segment_name
from services.evaluator.history import append_history, read_history
from services.learner import checkpoint
from tests.helpers import assert_messages_equal

pytestmark = [pytest.mark.unit, pytest.mark.timeout(120)]

CUT_SEED = 29
CUTS = 10


def _record(path: Path, make_episode, compression: str = "zstd") -> list:
    """24 episodes of several lengths in chunks of a few episodes each."""
    episodes = [make_episode(T=3 + i % 5, seed=i, episode_id=f"ep-{i}") for i in range(24)]
    with McapRecorder(path, compression=compression, chunk_size=6000, flush_interval_s=None) as rec:
        for i, ep in enumerate(episodes):
            rec.write(ep, log_time_ns=1_000_000_000 * (i + 1))
    return episodes


def _chunks(path: Path) -> list[tuple[int, int, int]]:
    """(start offset, end offset, messages) of each chunk in file order, from the intact file's summary and chunks
    (mcap's own readers), the oracle of what a cut must keep."""
    with open(path, "rb") as f:
        indexes = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = path.read_bytes()
    chunks = [r for r in StreamReader(io.BytesIO(data), emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) == len(indexes)
    counts = [sum(isinstance(r, McapMessage) for r in breakup_chunk(c)) for c in chunks]
    return [
        (ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length, n)
        for ci, n in zip(indexes, counts, strict=True)
    ]


def test_a_recording_cut_at_random_offsets_reads_every_message_written_before_the_cut(
    tmp_path, make_episode, caplog
):
    full = tmp_path / "full" / segment_name(0, 0)
    episodes = _record(full, make_episode)
    chunks = _chunks(full)
    assert len(chunks) >= 6 and max(n for _, _, n in chunks) >= 2  # chunks of several messages
    assert sum(n for _, _, n in chunks) == len(episodes)
    stats = ReadStats()
    with caplog.at_level(logging.WARNING, logger="services.common.mcap_io"):
        assert len(list(read_recording(full.parent, stats=stats))) == len(episodes)
        assert recover(full) == len(episodes)  # scans the whole file: no false alarm either
    assert stats.indexed and not stats.damage and not caplog.records
    data = full.read_bytes()
    rng = random.Random(CUT_SEED)
    cuts = sorted(rng.sample(range(9, chunks[-1][1] + 1), CUTS))
    for cut in cuts:
        run = tmp_path / f"cut-{cut}"
        path = run / segment_name(0, 0)
        run.mkdir()
        path.write_bytes(data[:cut])
        whole = [(end, n) for _, end, n in chunks if end <= cut]
        expected = sum(n for _, n in whole)
        caplog.clear()
        for source in (run, path):  # the run's directory of segments, and the file itself
            stats = ReadStats()
            with caplog.at_level(logging.WARNING, logger="services.common.mcap_io"):
                got = [m for _, m in read_recording(source, stats=stats)]
            assert len(got) == expected, (cut, source)
            for want, have in zip(episodes, got, strict=False):
                assert_messages_equal(want, have)
            assert stats.truncated and len(stats.damage) == 1, cut
            damage = stats.damage[0]
            last_whole_end = whole[-1][0] if whole else 0
            assert damage.path == str(path) and damage.size == cut and damage.recovered == expected
            assert last_whole_end <= damage.offset <= cut, (cut, damage)
            warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
            assert any(
                str(path) in w and f"{expected} messages recovered before byte {damage.offset}" in w
                for w in warned
            ), warned
        report = recording_check.describe(recording_check.check_recording(path))
        assert (
            f"damaged at byte {damage.offset} of {cut}" in report[0] and f"{expected} messages" in report[0]
        )


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_a_damaged_chunk_inside_a_finished_recording_ends_the_read_there_with_a_warning(
    tmp_path, make_episode, compression, caplog
):
    path = tmp_path / "run.mcap"
    episodes = _record(path, make_episode, compression)
    chunks = _chunks(path)
    start, end, _ = chunks[3]
    data = bytearray(path.read_bytes())
    data[(start + end) // 2] ^= 0x20  # one bit in the middle of the fourth chunk
    path.write_bytes(bytes(data))
    before = sum(n for _, _, n in chunks[:3])
    for types in (None, {"Episode"}):
        stats = ReadStats()
        with caplog.at_level(logging.WARNING, logger="services.common.mcap_io"):
            got = [m for _, m in read_recording(path, types=types, stats=stats)]
        assert len(got) == before, types  # nothing altered passes, nothing before it is lost or repeated
        for want, have in zip(episodes[:before], got, strict=True):
            assert_messages_equal(want, have)
        assert [(d.offset, d.recovered) for d in stats.damage] == [(start, before)]
        assert not stats.indexed and "corrupt record" in stats.damage[0].problem
    assert any(f"{before} messages recovered before byte {start}" in r.getMessage() for r in caplog.records)


def test_recording_check_reports_whole_damaged_and_bad_input(tmp_path, make_episode, capsys):
    path = tmp_path / "demos.mcap"
    episodes = _record(path, make_episode)
    assert recording_check.main(["check", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"{path}: whole, {len(episodes)} messages on 1 channel" in out and "/mea/Episode: 24" in out
    assert "1970-01-01T00:00:01.000Z to 1970-01-01T00:00:24.000Z (23.000 s)" in out
    cut = tmp_path / "cut.mcap"
    start = _chunks(path)[3][0]
    cut.write_bytes(path.read_bytes()[: start + 100])  # three whole chunks and part of the fourth
    recovered = sum(n for _, _, n in _chunks(path)[:3])
    assert recording_check.main(["check", str(path), str(cut)]) == 1
    out = capsys.readouterr().out.splitlines()
    damaged = next(line for line in out if line.startswith(f"{cut}:"))
    assert f"DAMAGED, damaged at byte {start} of {start + 100}" in damaged
    assert f"recovered before it: {recovered} messages" in damaged and "never closed" in damaged
    # a directory stands for its segments
    run = tmp_path / "run"
    run.mkdir()
    (run / segment_name(0, 0)).write_bytes(path.read_bytes())
    assert recording_check.main(["check", str(run)]) == 0
    assert capsys.readouterr().out.startswith(f"{run / segment_name(0, 0)}: whole")
    # bad input: one line each, exit 2
    (tmp_path / "notes.txt").write_text("not a recording at all")
    for argv, says in (
        (["check", str(tmp_path / "missing.mcap")], "no such file or directory"),
        (["check", str(tmp_path / "notes.txt")], "not an MCAP file"),
        (["check", str(tmp_path / "empty-dir-1")], "no such file"),
    ):
        assert recording_check.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0] and "Traceback" not in err[0], err
    (tmp_path / "empty").mkdir()
    assert recording_check.main(["check", str(tmp_path / "empty")]) == 2
    assert "without recording segments" in capsys.readouterr().err
    for argv in ([], ["check"], ["inspect", str(path)]):
        with pytest.raises(SystemExit) as exit_:
            recording_check.main(argv)
        assert exit_.value.code == 2


def test_a_missing_recording_directory_is_named_in_a_warning(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="services.common.mcap_io"):
        assert list(read_recording(tmp_path / "nowhere")) == []
    assert any(str(tmp_path / "nowhere") in r.getMessage() for r in caplog.records)


# -- checkpoints --------------------------------------------------------------------------------


def _save(directory: Path, k: int) -> Path:
    return checkpoint.save(
        directory, learner={"w": torch.full((256,), float(k))}, replay={"n": k}, meta={"version": k}, keep=5
    )


class _Evil:
    def __reduce__(self):
        return (print, ("unpickled",))


def test_each_unreadable_checkpoint_is_named_with_why_and_an_older_one_resumes(tmp_path, caplog):
    paths = [_save(tmp_path, k) for k in range(1, 6)]
    oldest, foreign, listed, garbage, cut = paths
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    garbage.write_bytes(b"\x00" * 64)
    torch.save([1, 2, 3], listed)
    torch.save({"format": checkpoint.FORMAT, "learner": _Evil()}, foreign)
    with caplog.at_level(logging.WARNING, logger="services.learner.checkpoint"):
        learner, replay, meta = checkpoint.load(tmp_path)
    assert meta == {"version": 1} and replay["n"] == 1 and torch.equal(learner["w"], torch.full((256,), 1.0))
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    why = {
        cut: "not a whole torch archive",
        garbage: "not a whole torch archive",
        listed: "not a learner checkpoint (holds a list)",
        foreign: "holds objects other than tensors",
    }
    for path, reason in why.items():
        assert sum(str(path) in w and reason in w for w in warned) == 1, (path, warned)
    assert any("resuming an older one" in w and str(oldest) in w for w in warned)
    oldest.write_bytes(b"")
    with pytest.raises(checkpoint.CheckpointError) as err:
        checkpoint.load(tmp_path)
    assert all(str(p) in str(err.value) for p in paths) and "Traceback" not in str(err.value)


# -- eval history -------------------------------------------------------------------------------


def test_bad_eval_history_lines_are_named_by_number_and_the_rest_read(tmp_path, caplog):
    path = tmp_path / "history.jsonl"
    good = [{"version": v, "env_steps": 100 * v, "success_rate": v / 10} for v in range(1, 5)]
    append_history(path, good[0])
    append_history(path, good[1])
    with open(path, "a") as f:
        f.write('{"version": 9, "env_st\n')  # line 3: cut in the middle, then written over
        f.write("[1, 2]\n")  # line 4: JSON, not an object
    append_history(path, good[2])
    append_history(path, good[3])
    with open(path, "a") as f:
        f.write('{"version": 5, "succ')  # line 7: a crash mid-write
    problems: list[str] = []
    with caplog.at_level(logging.WARNING, logger="services.evaluator.history"):
        assert read_history(path, problems) == good
    assert [p.split(": ")[1] for p in problems] == ["line 3 skipped", "line 4 skipped", "line 7 skipped"]
    assert all(p.startswith(f"{path}: ") for p in problems) and "truncated" in problems[-1]
    warned = [r.getMessage() for r in caplog.records]
    assert all(any(p in w for w in warned) for p in problems), warned


# -- weights files ------------------------------------------------------------------------------

KEY = bytes(range(32))


def _blob(version: int) -> WeightsBlob:
    tensors = {"w": np.arange(512, dtype=np.float32).reshape(16, 32) * version}
    return WeightsBlob.create(version, "equi_rsac", "run-a", tensors, "{}")


@pytest.mark.parametrize(
    ("case", "key", "says"),
    [
        ("cut", None, "not a valid weights file"),
        ("empty", None, "the file is empty"),
        ("tensor_flipped", None, "digest does not match"),
        ("version_flipped", None, "holds version 3, not the 1 of its name"),
        ("sealed_cut", KEY, "seal does not verify"),
        ("sealed_flipped", KEY, "seal does not verify"),
    ],
)
def test_a_damaged_weights_file_is_named_with_the_check_it_failed(tmp_path, case, key, says):
    blob = _blob(1)
    body = blob.encode()
    sealed = seal(KEY, weights_file.FILE_KEY, "learner", "learner-0", body)
    if case == "tensor_flipped":
        data = bytearray(body)
        data[body.index(np.float32(7.0).tobytes())] ^= 0x01  # one bit of one weight
    elif case == "version_flipped":
        at = body.index(b"\xa7version") + len(b"\xa7version")
        data = bytearray(body)
        assert data[at] == 1
        data[at] = 3
    else:
        data = {
            "cut": body[: len(body) // 2],
            "empty": b"",
            "sealed_cut": sealed[:-100],
            "sealed_flipped": sealed[:200] + bytes([sealed[200] ^ 0x10]) + sealed[201:],
        }[case]
    path = weights_file.write(tmp_path, blob, key)  # weights-00000001.blob, then damaged
    assert weights_file.read(path, key).digest == blob.digest
    path.write_bytes(bytes(data))
    with pytest.raises(weights_file.WeightsFileError) as err:
        weights_file.read(path, key)
    text = str(err.value)
    assert text.startswith(f"{path}: refused") and says in text and "\n" not in text, text
