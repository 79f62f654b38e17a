"""Incremental replay checkpoints: each checkpoint writes only the episodes no kept one holds, a
restored replay equals the saved one through evictions and compactions, segments go when no kept
checkpoint reads them, and a missing or damaged segment falls back to an older checkpoint."""

from __future__ import annotations

import numpy as np
import pytest

from services.learner import checkpoint, replay_segments
from services.learner.replay_segments import Segment, plan
from tests.helpers.learner import learner_episode, tiny_trainer

LINEAGE = checkpoint.Lineage(version=1, run_id="run-s", last={})


def episodes_state(lengths: list[int]) -> dict:
    """Per-episode arrays of a replay state whose rows name their episode and row."""
    obs = [(i, r) for i, n in enumerate(lengths) for r in range(n + 1)]
    trans = [(i, r) for i, n in enumerate(lengths) for r in range(n)]
    return {
        "lengths": np.array(lengths, np.int32),
        "serial": np.arange(10, 10 + len(lengths), dtype=np.int64),
        "episode_id": [f"e{i}" for i in range(len(lengths))],
        "image_codes": np.array([100 * i + r for i, r in obs], np.int64).reshape(-1, 1),
        "actions": np.array([100 * i + r for i, r in trans], np.float32).reshape(-1, 1),
    }


def test_take_and_join_pick_whole_episodes_in_the_asked_order():
    state = episodes_state([2, 3, 1])
    part = replay_segments.take(state, np.array([2, 0]))
    assert part["lengths"].tolist() == [1, 2] and part["episode_id"].tolist() == ["e2", "e0"]
    assert part["image_codes"][:, 0].tolist() == [200, 201, 0, 1, 2]
    assert part["actions"][:, 0].tolist() == [200, 0, 1]
    first, second = replay_segments.take(state, [0]), replay_segments.take(state, [1, 2])
    joined = replay_segments.join({"next_serial": 13}, [first, second], np.array([11, 12, 10]))
    assert joined["next_serial"] == 13 and joined["serial"].tolist() == [11, 12, 10]
    assert joined["image_codes"][:, 0].tolist() == [100, 101, 102, 103, 200, 201, 0, 1, 2]
    assert joined["episode_id"] == ["e1", "e2", "e0"]
    with pytest.raises(replay_segments.SegmentError, match="serial 99"):
        replay_segments.join({}, [first], np.array([10, 99]))


def test_the_plan_writes_only_new_episodes_until_evictions_leave_the_segments_half_empty():
    seg = [Segment("replay-000001.npz", (0, 1, 2, 3), 40)]
    kept, new = plan(seg, np.array([0, 1, 2, 3, 4, 5]), np.full(6, 10))
    assert kept == seg and new.tolist() == [4, 5]
    kept, new = plan(seg, np.array([2, 3, 4]), np.full(3, 10))  # half the listed transitions stored
    assert kept == seg and new.tolist() == [4]
    kept, new = plan(seg, np.array([3, 4, 5]), np.full(3, 10))  # a quarter: rewrite everything
    assert kept == [] and new.tolist() == [3, 4, 5]
    kept, new = plan(seg, np.array([7]), np.array([10]))  # none stored: the segment is not listed
    assert kept == [] and new.tolist() == [7]
    assert plan([], np.array([1, 2]), np.array([3, 4]))[1].tolist() == [1, 2]


def segment_files(directory) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.startswith("replay-"))


def fill(trainer, seeds, T: int = 10) -> None:
    for s in seeds:
        trainer.insert(learner_episode(s, T=T))


def same_replay(a, b) -> None:
    sa, sb = a.replay.state_dict(), b.replay.state_dict()
    assert sa.keys() == sb.keys()
    for key in sa:
        if isinstance(sa[key], np.ndarray):
            assert np.array_equal(sa[key], sb[key]), key
        else:
            assert sa[key] == sb[key], key


def test_each_checkpoint_writes_only_the_new_episodes_and_restores_the_whole_replay(tmp_path):
    a = tiny_trainer(min_steps=10, seed=1)
    a.insert(learner_episode(0, T=10, demo=True))
    fill(a, range(1, 4))
    _, segs = checkpoint.save_trainer(tmp_path, a, LINEAGE, {}, segments=[])
    assert [s.serials for s in segs] == [(0, 1, 2, 3)]
    fill(a, range(4, 6))
    _, segs = checkpoint.save_trainer(tmp_path, a, LINEAGE, {}, segments=segs)
    assert [s.serials for s in segs] == [(0, 1, 2, 3), (4, 5)]
    assert segment_files(tmp_path) == ["replay-000001.npz", "replay-000002.npz"]
    _, segs = checkpoint.save_trainer(tmp_path, a, LINEAGE, {}, segments=segs)  # nothing new: no file
    assert len(segs) == 2 and segment_files(tmp_path) == ["replay-000001.npz", "replay-000002.npz"]

    b = tiny_trainer(min_steps=10, seed=2)
    _, restored = checkpoint.restore_trainer(tmp_path, b)
    same_replay(a, b)
    assert restored == segs  # a resumed learner goes on writing only what is new
    fill(b, [6])
    _, segs = checkpoint.save_trainer(tmp_path, b, LINEAGE, {}, segments=restored)
    assert [s.serials for s in segs][-1] == (6,)


def test_evictions_are_restored_and_compaction_bounds_the_segments(tmp_path):
    a = tiny_trainer(min_steps=10, seed=1, replay_capacity=60)  # six episodes of 10
    a.insert(learner_episode(0, T=10, demo=True))  # a demo is never evicted
    segs: list[Segment] = []
    written = []
    for round_ in range(6):
        fill(a, range(10 * round_ + 1, 10 * round_ + 4))
        path, segs = checkpoint.save_trainer(tmp_path, a, LINEAGE, {}, keep=2, segments=segs)
        written.append(sum(s.transitions for s in segs))
        b = tiny_trainer(min_steps=10, seed=2, replay_capacity=60)
        checkpoint.restore_trainer(tmp_path, b)
        same_replay(a, b)
    assert a.replay.stats()["evicted_episodes"] > 0
    # what the newest checkpoint lists stays within twice the replay (the compaction's bound)
    assert max(written) <= 2 * 60
    listed = {s.name for p in checkpoint.checkpoints(tmp_path) for s in checkpoint.listed_segments(p)}
    assert set(segment_files(tmp_path)) == listed  # nothing unlisted left behind


def test_pruned_checkpoints_take_their_segments_and_the_byte_budget_counts_them(tmp_path):
    a = tiny_trainer(min_steps=10, seed=1, replay_capacity=60)
    segs: list[Segment] = []
    for round_ in range(4):
        fill(a, range(10 * round_, 10 * round_ + 6))  # each round evicts all of the last one
        _, segs = checkpoint.save_trainer(tmp_path, a, LINEAGE, {}, keep=1, segments=segs)
    assert [p.name for p in checkpoint.checkpoints(tmp_path)] == ["learner-000004.pt"]
    assert segment_files(tmp_path) == ["replay-000004.npz"]

    budget = tmp_path / "budget"
    for round_ in range(3):
        fill(a, range(100 + 10 * round_, 100 + 10 * round_ + 6))
        _, segs = checkpoint.save_trainer(budget, a, LINEAGE, {}, keep=3, segments=segs)
    newest = checkpoint.checkpoints(budget)[0]
    alone = newest.stat().st_size + sum((budget / s.name).stat().st_size for s in segs)
    checkpoint.prune(budget, keep=3, max_bytes=alone)  # room for the newest and its segment only
    assert [p.name for p in checkpoint.checkpoints(budget)] == [newest.name]
    assert segment_files(budget) == [s.name for s in segs]


@pytest.mark.parametrize("damage", ["delete", "truncate"])
def test_a_missing_or_damaged_segment_falls_back_to_an_older_checkpoint(tmp_path, caplog, damage):
    a = tiny_trainer(min_steps=10, seed=1)
    fill(a, range(3))
    _, segs = checkpoint.save_trainer(tmp_path, a, LINEAGE, {}, segments=[])
    fill(a, range(3, 5))
    _, segs = checkpoint.save_trainer(tmp_path, a, LINEAGE, {}, segments=segs)
    newest_segment = tmp_path / segs[-1].name
    if damage == "delete":
        newest_segment.unlink()
    else:
        newest_segment.write_bytes(newest_segment.read_bytes()[:100])
    b = tiny_trainer(min_steps=10, seed=2)
    _, restored = checkpoint.restore_trainer(tmp_path, b)
    assert b.replay.num_episodes == 3 and "its replay is unreadable" in caplog.text
    assert "replay-000002.npz" in caplog.text and [s.name for s in restored] == ["replay-000001.npz"]
    # the resumed learner lists only what it read; a listed segment that has gone is written again
    fill(b, [7])
    stale = restored if damage == "truncate" else segs
    _, segs = checkpoint.save_trainer(tmp_path, b, LINEAGE, {}, segments=stale)
    assert len(segs) == (2 if damage == "truncate" else 1)
    c = tiny_trainer(min_steps=10, seed=3)
    checkpoint.restore_trainer(tmp_path, c)
    same_replay(b, c)


def test_a_checkpoint_holding_its_replay_whole_still_loads(tmp_path):
    a = tiny_trainer(min_steps=10, seed=1)
    fill(a, range(3))
    learner = {"sac": checkpoint.on_cpu(a.agent.state_dict()), "rng": checkpoint.rng_state(a.rng)}
    meta = {"version": 4, "run_id": "old", "env_steps": a.env_steps, "limiter": a.limiter.state_dict()}
    checkpoint.save(tmp_path, learner=learner, replay=a.replay.state_dict(), meta=meta)
    b = tiny_trainer(min_steps=10, seed=2)
    lineage, segs = checkpoint.restore_trainer(tmp_path, b)
    assert lineage.version == 4 and segs == []
    same_replay(a, b)
    fill(b, [9])
    checkpoint.save_trainer(tmp_path, b, LINEAGE, {}, segments=segs)
    assert segment_files(tmp_path) == ["replay-000002.npz"]
    c = tiny_trainer(min_steps=10, seed=3)
    checkpoint.restore_trainer(tmp_path, c)
    same_replay(b, c)
