"""The launcher's raw-episode recording over the in-process bus: with a tiny segment size it rolls
over many segment files, each complete, and reading the run's recording gives back every episode
once, in the order published; a resumed run goes on in segments of its own; a stalled disk never holds the router."""

from __future__ import annotations

import threading
import time

import pytest

from proto.topics import EPISODES_RAW
from services.common.bus import Hub, InProcBus
from services.common.mcap_io import (
    RECORDING_METADATA,
    SEGMENT_METADATA,
    read_metadata,
    read_recording,
    recording_segments,
)
from services.launcher import EpisodeRecorder
from tests.helpers import poll_until
from tests.helpers.synthetic import synthetic_episode

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


def record(run_dir, run: int, seeds: range, **limits) -> EpisodeRecorder:
    hub = Hub()
    router, actor = InProcBus(hub), InProcBus(hub)
    meta = {"task": "block_pick", "resumes": str(run)}
    recorder = EpisodeRecorder(router, run_dir / "episodes", run, meta, **limits)
    try:
        for seed in seeds:
            ep, _ = synthetic_episode(seed, T=10)
            actor.publish(EPISODES_RAW, ep, source=f"actor-{seed % 2}")
            if seed % 3 == 0:
                time.sleep(0.01)  # let the recorder thread catch up now and then
        # half written by the thread, the rest maybe drained by close()
        poll_until(lambda: recorder.written >= len(seeds) // 2, 30.0, every=0.01)
    finally:
        recorder.close()
        actor.close()
        router.close()
    return recorder


def test_a_tiny_segment_size_rolls_many_segments_and_nothing_is_lost_or_repeated(tmp_path):
    one, _ = synthetic_episode(0, T=10)
    size = len(one.encode())
    first = record(tmp_path, 0, range(40), segment_bytes=3 * size, segment_seconds=3600.0)
    assert first.written == 40
    segments = recording_segments(tmp_path / "episodes")
    assert len(segments) >= 12  # about 3 episodes each: past segment 9, so order is numeric
    for i, path in enumerate(segments):
        assert path.name == f"raw-0-{i:04d}.mcap"
        meta = read_metadata(path)
        assert meta["run"] == {"task": "block_pick", "resumes": "0"}
        assert meta[SEGMENT_METADATA] == {"run": "0", "index": str(i)}
        assert meta[RECORDING_METADATA]["status"] == "complete"
        assert 1 <= int(meta[RECORDING_METADATA]["messages"]) <= 4
    recorded = list(read_recording(tmp_path / "episodes"))
    assert [m.episode_id for _, m in recorded] == [f"syn-{s}" for s in range(40)]
    assert {t.rsplit("/", 1)[-1] for t, _ in recorded} == {"actor-0", "actor-1"}  # the bus keys

    # the run resumed: its segments follow the first run's, and a budget deletes the oldest
    budget = sum(p.stat().st_size for p in segments) // 2
    second = record(tmp_path, 1, range(40, 50), segment_bytes=3 * size, max_bytes=budget)
    assert second.written == 10
    after = recording_segments(tmp_path / "episodes")
    assert after[-1].name.startswith("raw-1-") and sum(p.stat().st_size for p in after) <= budget
    ids = [m.episode_id for _, m in read_recording(tmp_path / "episodes")]
    oldest_kept = int(ids[0].split("-")[1])
    assert ids == [f"syn-{s}" for s in range(oldest_kept, 50)] and oldest_kept > 0


def test_a_stalled_disk_does_not_hold_the_routers_reader(tmp_path):
    """While a write hangs, the recorder keeps reading the router's subscription (capacity 256) into
    its inbox, so publishers through the router never wait on the disk; once the write returns,
    every episode is recorded once, in order."""
    hub = Hub()
    router, actor = InProcBus(hub), InProcBus(hub)
    recorder = EpisodeRecorder(router, tmp_path / "episodes", 0, {"task": "block_pull"})
    release, real_write = threading.Event(), recorder.recorder.write

    def stalled_write(message, topic):
        release.wait(30)
        real_write(message, topic=topic)

    recorder.recorder.write = stalled_write
    episodes = [synthetic_episode(seed, T=10)[0] for seed in range(300)]
    published = threading.Event()

    def publish_all():
        for ep in episodes:
            actor.publish(EPISODES_RAW, ep, source="actor-0")
        published.set()

    threading.Thread(target=publish_all, daemon=True).start()
    try:
        assert published.wait(20), "the publisher waited on the recorder's disk"
        # the reader drains the subscription a moment after the last publish returns
        assert poll_until(lambda: len(recorder.inbox) >= 300 - 256 - 1, 10.0), len(recorder.inbox)
        assert recorder.written == 0
        release.set()
        poll_until(lambda: recorder.written >= 300, 30.0)
    finally:
        release.set()
        recorder.close()
        actor.close()
        router.close()
    assert recorder.written == 300
    recorded = [m.episode_id for _, m in read_recording(tmp_path / "episodes")]
    assert recorded == [ep.episode_id for ep in episodes]
