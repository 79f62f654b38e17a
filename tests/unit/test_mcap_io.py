"""MCAP recorder and readers: round trips, channels and schemas, metadata, atomic publication,
crash tolerance (truncated and killed recordings) and bad records."""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from proto.codec import Message
from proto.control import Heartbeat
from proto.episode import Augmentation, Episode
from proto.jsonschema import json_schema_text
from proto.msgpack_wire import ProtocolError
from services.common.mcap_io import (
    LIBRARY,
    MESSAGE_ENCODING,
    PROFILE,
    RECORDING_METADATA,
    SCHEMA_ENCODING,
    McapRecorder,
    ReadStats,
    read_config,
    read_messages,
    read_metadata,
    recover,
    tmp_path_for,
)
from tests.helpers import assert_messages_equal

pytestmark = [pytest.mark.unit, pytest.mark.timeout(60)]

ROOT = Path(__file__).resolve().parents[2]


def heartbeat(n: int = 0) -> Heartbeat:
    return Heartbeat(
        service="test",
        instance_id=f"hb-{n}",
        pid=1234,
        state="running",
        started_at=1_700_000_000.0,
        created_at=1_700_000_000.0 + n,
        policy_version=-1,
        counters={"episodes": float(n), "queue.depth": 0.5},
        detail="ok",
    )


def augmented(make_episode, seed: int) -> Episode:
    aug = Augmentation(
        source_episode_id=f"actor-0-{seed}-0",
        kind="mea",
        seed=seed,
        copy_index=1,
        phase_split=2,
        params={"rotation": np.array([0.25]), "delta_r": np.zeros(2, dtype=np.float32)},
    )
    return make_episode(T=6, seed=seed, augmentation=aug, episode_id=f"aug-{seed}")


def assert_same(a: Message, b: Message) -> None:
    assert type(a) is type(b)
    for f in a.fields():
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray):
            assert isinstance(vb, np.ndarray), f.name
            assert va.dtype == vb.dtype and np.array_equal(va, vb), f.name
    assert_messages_equal(a, b)


@pytest.fixture
def messages(make_episode) -> list[Message]:
    """Episodes of several lengths (one truncated, one with images, one augmented) and heartbeats."""
    eps = [
        make_episode(T=8, seed=0),
        make_episode(T=3, seed=1, truncated=True),
        make_episode(T=5, seed=2, with_images=True, image_shape=(3, 8, 8)),
        augmented(make_episode, 3),
    ]
    return [eps[0], heartbeat(0), eps[1], eps[2], heartbeat(1), eps[3]]


def record(path: Path, msgs: list[Message], **kwargs) -> None:
    with McapRecorder(path, **kwargs) as rec:
        for i, m in enumerate(msgs):
            rec.write(m, log_time_ns=1_000 + i)


# -- round trip ---------------------------------------------------------------------------------


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_round_trip_preserves_messages_and_order(tmp_path, messages, compression):
    path = tmp_path / "run.mcap"
    record(path, messages, compression=compression)
    stats = ReadStats()
    got = list(read_messages(path, stats=stats))
    assert [t for t, _ in got] == [f"/mea/{m.TYPE}" for m in messages]
    for want, (_, have) in zip(messages, got, strict=True):
        assert_same(want, have)
    assert stats.indexed and not stats.truncated
    assert (stats.messages, stats.skipped, stats.ignored) == (len(messages), 0, 0)
    ep = got[0][1]
    assert ep.segments == ["gripper", "object_0", "object_1"]
    assert ep.points.shape == (9, 3, 16, 3) and ep.points.dtype == np.float32
    assert ep.terminated[-1] and not ep.truncated.any()


def test_types_filter(tmp_path, messages):
    path = tmp_path / "run.mcap"
    record(path, messages)
    hbs = [m for _, m in read_messages(path, types={"Heartbeat"})]
    assert [m.instance_id for m in hbs] == ["hb-0", "hb-1"]
    eps = [m for _, m in read_messages(path, types={"Episode"})]
    assert [m.episode_id for m in eps] == [m.episode_id for m in messages if isinstance(m, Episode)]
    assert list(read_messages(path, types={"EvalReport"})) == []


def test_channels_schemas_and_sequences(tmp_path, messages):
    path = tmp_path / "run.mcap"
    record(path, messages)
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        raw = list(reader.iter_messages(log_time_order=False))
    assert (header.profile, header.library) == (PROFILE, LIBRARY)
    by_topic = {ch.topic: ch for ch in summary.channels.values()}
    assert set(by_topic) == {"/mea/Episode", "/mea/Heartbeat"}
    for topic, cls in (("/mea/Episode", Episode), ("/mea/Heartbeat", Heartbeat)):
        ch = by_topic[topic]
        assert ch.message_encoding == MESSAGE_ENCODING == "msgpack"
        schema = summary.schemas[ch.schema_id]
        assert schema.name == cls.TYPE
        assert schema.encoding == SCHEMA_ENCODING == "jsonschema"
        assert schema.data.decode() == json_schema_text(cls)
        doc = json.loads(schema.data)
        required = [f.name for f in cls.fields() if f.default is dataclasses.MISSING]
        assert doc["required"] == ["_type", "_v", *required]
        assert doc["properties"]["_type"]["const"] == cls.TYPE
        assert doc["properties"]["_v"]["const"] == cls.VERSION
    assert len(summary.schemas) == 2
    # payloads are exactly msg.encode(); sequence numbers count per channel
    assert [m.data for _, _, m in raw] == [m.encode() for m in messages]
    seqs: dict[str, list[int]] = {}
    for _, ch, m in raw:
        seqs.setdefault(ch.topic, []).append(m.sequence)
    assert seqs == {"/mea/Episode": [0, 1, 2, 3], "/mea/Heartbeat": [0, 1]}
    assert [m.log_time for _, _, m in raw] == [1_000 + i for i in range(len(messages))]


def test_custom_topic(tmp_path, make_episode):
    path = tmp_path / "run.mcap"
    with McapRecorder(path) as rec:
        rec.write(make_episode(seed=0), topic="/mea/episodes/raw")
        rec.write(make_episode(seed=1))
        with pytest.raises(ValueError, match="already records Episode"):
            rec.write(heartbeat(), topic="/mea/episodes/raw")
    assert [t for t, _ in read_messages(path)] == ["/mea/episodes/raw", "/mea/Episode"]
    with open(path, "rb") as f:
        assert len(make_reader(f).get_summary().schemas) == 1  # one schema per type, shared


# -- metadata -----------------------------------------------------------------------------------


def test_metadata_and_config_round_trip(tmp_path, messages):
    path = tmp_path / "run.mcap"
    cfg = json.dumps({"algorithm": "equi_rsac", "lr": 3e-4, "seeds": [1, 2, 3]})
    with McapRecorder(path, metadata={"task": "block_pull", "seed": "7"}) as rec:
        rec.write(messages[0])
        rec.add_metadata("seeds", {"eval": "100,101", "train": "0"})
        rec.write_config("learner", cfg)
        with pytest.raises(ValueError, match="already written"):
            rec.add_metadata("seeds", {"x": "y"})
        with pytest.raises(ValueError, match="reserved"):
            rec.add_metadata(RECORDING_METADATA, {"x": "y"})
        with pytest.raises(TypeError):
            rec.add_metadata("bad", {"n": 1})  # type: ignore[dict-item]
        with pytest.raises(ValueError):
            rec.write_config("broken", "{not json")
    meta = read_metadata(path)
    assert meta["run"] == {"task": "block_pull", "seed": "7"}
    assert meta["seeds"] == {"eval": "100,101", "train": "0"}
    assert meta["config/learner"] == {"json": cfg}
    assert read_config(path, "learner") == cfg
    assert read_config(path, "missing") is None
    assert meta[RECORDING_METADATA]["status"] == "complete"
    assert meta[RECORDING_METADATA]["messages"] == "1"
    assert set(meta) == {"run", "seeds", "config/learner", RECORDING_METADATA}


# -- atomic publication -------------------------------------------------------------------------


def test_file_appears_only_after_close(tmp_path, messages):
    path = tmp_path / "sub" / "run.mcap"
    tmp = tmp_path_for(path)
    assert tmp.name == "run.mcap.tmp"
    rec = McapRecorder(path)
    rec.write(messages[0])
    assert tmp.exists() and not path.exists()
    rec.close()
    assert path.exists() and not tmp.exists()
    rec.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        rec.write(messages[0])
    with pytest.raises(FileExistsError):
        McapRecorder(path)
    with McapRecorder(path, overwrite=True) as rec:
        rec.write(heartbeat())
    assert [m.TYPE for _, m in read_messages(path)] == ["Heartbeat"]


def test_stale_tmp_is_not_clobbered(tmp_path):
    path = tmp_path / "run.mcap"
    tmp_path_for(path).write_bytes(b"crashed recording")
    with pytest.raises(FileExistsError, match="recover"):
        McapRecorder(path)
    assert tmp_path_for(path).read_bytes() == b"crashed recording"


def test_exception_in_block_still_publishes_a_finished_file(tmp_path, messages, caplog):
    path = tmp_path / "run.mcap"
    with pytest.raises(KeyError), McapRecorder(path) as rec:
        rec.write(messages[0])
        rec.write(messages[1])
        raise KeyError("boom")
    assert path.exists() and not tmp_path_for(path).exists()
    stats = ReadStats()
    assert len(list(read_messages(path, stats=stats))) == 2
    assert stats.indexed
    status = read_metadata(path)[RECORDING_METADATA]
    assert status["status"] == "aborted" and "KeyError" in status["error"]
    assert any("after an error" in r.getMessage() for r in caplog.records)


def test_refuses_nested_only_and_bad_times(tmp_path, messages):
    with McapRecorder(tmp_path / "run.mcap") as rec:
        with pytest.raises(TypeError):
            rec.write(messages[-1].augmentation)  # type: ignore[arg-type]
        with pytest.raises(ValueError):
            rec.write(messages[0], log_time_ns=-1)
        assert rec.message_count == 0


def test_concurrent_writers(tmp_path):
    path = tmp_path / "run.mcap"
    with McapRecorder(path, chunk_size=4096) as rec:

        def work(k: int) -> None:
            for i in range(50):
                rec.write(heartbeat(k * 100 + i))

        threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    with open(path, "rb") as f:
        raw = list(make_reader(f).iter_messages(log_time_order=False))
    assert sorted(m.sequence for _, _, m in raw) == list(range(200))
    assert len(list(read_messages(path))) == 200


# -- crash tolerance ----------------------------------------------------------------------------


def chunk_ends(path: Path) -> list[int]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    return sorted(ci.chunk_start_offset + ci.chunk_length for ci in summary.chunk_indexes)


def test_truncated_file_readable_up_to_the_cut(tmp_path, make_episode):
    eps = [make_episode(T=4 + i, seed=i) for i in range(6)]
    path = tmp_path / "run.mcap"
    record(path, eps, chunk_size=1, metadata={"task": "block_pull"})  # one chunk per message
    ends = chunk_ends(path)
    assert len(ends) == len(eps)
    data = path.read_bytes()
    cuts = sorted({e + d for e in ends for d in (-1, 0, 1)} | {len(data) - 1, 40})
    for cut in cuts:
        cut_path = tmp_path / f"cut-{cut}.mcap.tmp"
        cut_path.write_bytes(data[:cut])
        expected = sum(1 for e in ends if e <= cut)
        stats = ReadStats()
        got = [m for _, m in read_messages(cut_path, stats=stats)]
        assert len(got) == expected, cut
        for want, have in zip(eps, got, strict=False):
            assert_same(want, have)
        assert not stats.indexed
        assert recover(cut_path) == expected
        if cut < ends[-1]:
            assert stats.truncated and stats.errors
    # a file missing only its last bytes (end magic, footer) has all its messages but is not whole
    for missing in (1, 10):
        cut_path = tmp_path / f"tail-{missing}.mcap"
        cut_path.write_bytes(data[:-missing])
        stats = ReadStats()
        assert len(list(read_messages(cut_path, stats=stats))) == len(eps)
        assert stats.truncated and not stats.indexed and "footer" in stats.errors[-1], stats.errors
    # metadata written before the cut survives it
    assert read_metadata(tmp_path / f"cut-{ends[0]}.mcap.tmp")["run"] == {"task": "block_pull"}
    assert recover(path) == len(eps)


def test_recover_rewrites_a_complete_file(tmp_path, make_episode):
    eps = [make_episode(seed=i) for i in range(4)]
    path = tmp_path / "run.mcap"
    record(path, [*eps, heartbeat()], chunk_size=1, metadata={"task": "block_pull"})
    data = path.read_bytes()
    cut_path = tmp_path / "run.mcap.tmp"
    cut_path.write_bytes(data[: chunk_ends(path)[2] + 5])
    out = tmp_path / "recovered.mcap"
    assert recover(cut_path, out=out) == 3
    stats = ReadStats()
    got = [m for _, m in read_messages(out, stats=stats)]
    assert stats.indexed and len(got) == 3
    for want, have in zip(eps, got, strict=False):
        assert_same(want, have)
    meta = read_metadata(out)
    assert meta["run"] == {"task": "block_pull"}
    assert meta[RECORDING_METADATA]["status"] == "recovered"
    with pytest.raises(ValueError):
        recover(out, out=out)


def test_open_recording_is_readable_after_flush(tmp_path, make_episode):
    path = tmp_path / "run.mcap"
    with McapRecorder(path, flush_interval_s=None) as rec:
        rec.write(make_episode(seed=0))
        rec.write(make_episode(seed=1))
        rec.flush()
        rec.write(make_episode(seed=2))  # still in the open chunk
        got = [m.episode_id for _, m in read_messages(rec.tmp_path)]
        assert got == ["actor-0-0-0", "actor-0-1-0"]
        assert recover(rec.tmp_path) == 2
    assert len(list(read_messages(path))) == 3


KILLED_WRITER = """
import sys, time
sys.path.insert(0, sys.argv[2])
from services.common.mcap_io import McapRecorder
from tests.helpers import build_episode
rec = McapRecorder(sys.argv[1], chunk_size=1, metadata={"task": "block_pull"})
i = 0
while True:
    rec.write(build_episode(T=5, seed=i))
    i += 1
    print(i, flush=True)
    if i >= 200:
        time.sleep(60)
"""


def test_killed_writer_leaves_a_readable_tmp(tmp_path):
    path = tmp_path / "run.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED_WRITER, str(path), str(ROOT)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        for _ in range(5):
            assert proc.stdout.readline(), "writer exited early"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stdout.close()
    assert not path.exists()
    tmp = tmp_path_for(path)
    stats = ReadStats()
    got = [m for _, m in read_messages(tmp, stats=stats)]
    assert len(got) >= 5 and stats.truncated and not stats.indexed
    assert [m.seed for m in got] == list(range(len(got)))
    assert recover(tmp) == len(got)
    assert RECORDING_METADATA not in read_metadata(tmp)


# -- bad records --------------------------------------------------------------------------------


def corrupt_second_episode(tmp_path: Path, make_episode) -> tuple[Path, list[Episode]]:
    eps = [make_episode(seed=i) for i in range(3)]
    path = tmp_path / "run.mcap"
    record(path, eps, compression="none", chunk_size=1)  # one chunk per message
    data = path.read_bytes()
    assert data.count(b"actor-0-1-0") == 1
    path.write_bytes(data.replace(b"actor-0-1-0", b"actor-0-1!0"))  # same length, bad pattern
    return path, eps


def bad_second_episode(tmp_path: Path, make_episode) -> tuple[Path, list[Episode]]:
    """A whole file (chunk CRCs match) whose second message does not decode: an invalid episode id
    written by another program (a damaged file is caught by its CRC before decoding)."""
    eps = [make_episode(seed=i) for i in range(3)]
    path = tmp_path / "run.mcap"
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=1)
        w.start(profile=PROFILE, library="other")
        sid = w.register_schema("Episode", SCHEMA_ENCODING, json_schema_text(Episode).encode())
        cid = w.register_channel("/mea/Episode", MESSAGE_ENCODING, sid)
        for i, ep in enumerate(eps):
            data = ep.encode().replace(b"actor-0-1-0", b"actor-0-1!0")  # same length, bad pattern
            w.add_message(cid, i, data, i, sequence=i)
        w.finish()
    return path, eps


def test_corrupted_record_raises_protocol_error(tmp_path, make_episode):
    path, _ = bad_second_episode(tmp_path, make_episode)
    it = read_messages(path)
    assert next(it)[1].episode_id == "actor-0-0-0"
    with pytest.raises(ProtocolError) as err:
        next(it)
    assert err.value.field == "Episode.episode_id"
    assert "/mea/Episode #1" in str(err.value)


def test_corrupted_record_skipped_and_counted(tmp_path, make_episode, caplog):
    path, eps = bad_second_episode(tmp_path, make_episode)
    stats = ReadStats()
    got = [m for _, m in read_messages(path, on_error="skip", stats=stats)]
    assert [m.episode_id for m in got] == ["actor-0-0-0", "actor-0-2-0"]
    assert (stats.messages, stats.skipped) == (2, 1)
    assert "Episode.episode_id" in stats.errors[0]
    assert any("skipping bad record" in r.getMessage() for r in caplog.records)
    with pytest.raises(ValueError):
        list(read_messages(path, on_error="ignore"))  # type: ignore[arg-type]


def test_corrupted_chunk_ends_the_scan_of_an_unfinished_file(tmp_path, make_episode):
    path, _ = corrupt_second_episode(tmp_path, make_episode)
    data = path.read_bytes()
    tmp = tmp_path / "run.mcap.tmp"
    tmp.write_bytes(data[: len(data) - 10])  # no footer: scanned, chunk CRCs checked
    stats = ReadStats()
    got = [m for _, m in read_messages(tmp, stats=stats)]
    assert [m.episode_id for m in got] == ["actor-0-0-0"]
    assert stats.truncated and "crc validation failed" in stats.errors[-1]


def test_type_must_match_channel_schema_and_foreign_channels_are_ignored(tmp_path, make_episode):
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="mea", library="other")
        sid = w.register_schema("Heartbeat", "jsonschema", json_schema_text(Heartbeat).encode())
        lying = w.register_channel("/mea/Heartbeat", "msgpack", sid)
        js = w.register_channel("/json", "json", 0)
        bare = w.register_channel("/bare", "msgpack", 0)  # no schema: the payload's _type decides
        w.add_message(lying, 1, make_episode(seed=0).encode(), 1)
        w.add_message(js, 2, b'{"a": 1}', 2)
        w.add_message(bare, 3, heartbeat(3).encode(), 3)
        w.finish()
    with pytest.raises(ProtocolError) as err:
        list(read_messages(path))
    assert err.value.field == "_type"
    stats = ReadStats()
    got = list(read_messages(path, on_error="skip", stats=stats))
    assert [(t, m.TYPE) for t, m in got] == [("/bare", "Heartbeat")]
    assert (stats.skipped, stats.ignored) == (1, 1)


def test_reading_never_unpickles(tmp_path, messages, monkeypatch):
    path = tmp_path / "run.mcap"
    record(path, messages)

    def refuse(*args, **kwargs):
        raise AssertionError("unpickling attempted")

    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "Unpickler", refuse)
    assert len(list(read_messages(path))) == len(messages)
    truncated = tmp_path / "cut.mcap"
    truncated.write_bytes(path.read_bytes()[:-200])
    list(read_messages(truncated))
    read_metadata(path)


def test_flush_interval_closes_chunks_on_write(tmp_path):
    path = tmp_path / "run.mcap"
    with McapRecorder(path, flush_interval_s=0.0) as rec:
        for i in range(3):
            rec.write(heartbeat(i))
            time.sleep(0.001)
        assert recover(rec.tmp_path) == 3
