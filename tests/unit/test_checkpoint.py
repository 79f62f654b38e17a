"""Checkpoint files: atomic writes, the newest few kept (by count and bytes), fallback to an older one,
nothing unpickled beyond tensors and plain data."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
import torch

from services.learner import checkpoint
from tests.helpers.learner import learner_episode, tiny_trainer


def payload(k: int) -> tuple[dict, dict, dict]:
    learner = {
        "w": torch.full((3,), float(k)),
        "opt": {"state": {}, "param_groups": [{"lr": 0.1, "betas": (0.9, 0.99)}]},
    }
    replay = {"codes": np.arange(12, dtype=np.uint8).reshape(3, 4) + k, "count": k, "ids": ["a", "b"]}
    meta = {"version": k, "run_id": "run-1"}
    return learner, replay, meta


def save(directory, k: int, **kw):
    return checkpoint.save(
        directory, **dict(zip(("learner", "replay", "meta"), payload(k), strict=True)), **kw
    )


def test_round_trip_and_previous_copy(tmp_path):
    save(tmp_path, 1)
    save(tmp_path, 2)
    learner, replay, meta = checkpoint.load(tmp_path)
    assert meta == {"version": 2, "run_id": "run-1"}
    assert torch.equal(learner["w"], torch.full((3,), 2.0))
    assert learner["opt"]["param_groups"][0]["betas"] == (0.9, 0.99)
    assert replay["codes"].dtype == np.uint8 and (replay["codes"] == np.arange(12).reshape(3, 4) + 2).all()
    assert replay["count"] == 2 and replay["ids"] == ["a", "b"]
    assert [p.name for p in checkpoint.checkpoints(tmp_path)] == ["learner-000002.pt", "learner-000001.pt"]
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_a_corrupt_newest_file_falls_back_to_the_previous_one(tmp_path, caplog):
    for k in (1, 2, 3):
        save(tmp_path, k)
    newest, older, _ = checkpoint.checkpoints(tmp_path)
    newest.write_bytes(b"\x00garbage")
    _, _, meta = checkpoint.load(tmp_path)
    assert meta["version"] == 2 and "resuming an older one" in caplog.text
    older.write_bytes(b"")  # and further back, as far as there are checkpoints
    assert checkpoint.load(tmp_path)[2]["version"] == 1


class Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned > /dev/null",))


def test_arbitrary_pickles_are_refused(tmp_path):
    with open(tmp_path / checkpoint.file_name(1), "wb") as f:
        torch.save(
            {"format": checkpoint.FORMAT, "learner": Evil(), "replay": {}, "meta": "{}"},
            f,
            pickle_module=pickle,
        )
    with pytest.raises(checkpoint.CheckpointError, match="learner-000001.pt"):
        checkpoint.load(tmp_path)


def test_missing_checkpoint_is_a_clear_error(tmp_path):
    assert not checkpoint.exists(tmp_path)
    with pytest.raises(checkpoint.CheckpointError, match="no checkpoint"):
        checkpoint.load(tmp_path)


def test_rng_state_round_trip():
    rng = np.random.default_rng(5)
    torch.manual_seed(3)
    state = checkpoint.rng_state(rng)
    a, b = rng.random(3), torch.rand(3)
    rng2 = np.random.default_rng(999)
    checkpoint.restore_rng(state, rng2)
    assert (rng2.random(3) == a).all() and torch.equal(torch.rand(3), b)


@pytest.mark.parametrize(
    ("since", "updates", "minutes", "every", "due"),
    [
        (599.9, 3, 10.0, 0, False),
        (600.0, 3, 10.0, 0, True),
        (1e9, 3, 0.0, 0, False),  # both schedules off
        (0.0, 10, 0.0, 5, True),
        (0.0, 12, 0.0, 5, False),
        (0.0, 0, 0.0, 5, False),  # no checkpoint before the first update
        (0.0, 15, 10.0, 5, True),
    ],
)
def test_checkpoint_schedule(since, updates, minutes, every, due):
    assert checkpoint.due(since, updates, minutes, every) is due


def test_a_trainer_round_trips_with_its_lineage(tmp_path):
    a = tiny_trainer(min_steps=10, seed=1)
    raw = learner_episode(0, T=10, demo=True)
    a.insert(raw)
    a.insert(learner_episode(50, copy_of=raw.episode_id))
    a.insert(learner_episode(1, T=8))
    for _ in range(2):
        assert a.step() is not None
    lineage = checkpoint.Lineage(version=3, run_id="run-x", last={"critic_loss": 0.5})
    checkpoint.save_trainer(tmp_path, a, lineage, {"batch_size": 4})
    _, _, meta = checkpoint.load(tmp_path)
    assert list(meta) == ["version", "run_id", "env_steps", "limiter", "last", "config", "saved_at"]
    assert (meta["env_steps"], meta["config"], meta["limiter"]["samples"]) == (18, {"batch_size": 4}, 2)

    b = tiny_trainer(min_steps=10, seed=2)
    assert checkpoint.restore_trainer(tmp_path, b)[0] == lineage
    assert (b.updates, b.env_steps, b.limiter.samples) == (2, 18, 2)
    assert (len(b.replay), b.replay.episode_ids()) == (len(a.replay), a.replay.episode_ids())
    for name, tensor in a.agent.state_dict()["actor"].items():
        assert torch.equal(tensor, b.agent.state_dict()["actor"][name]), name
    assert (b.rng.random(4) == a.rng.random(4)).all()


def test_a_resumed_lineage_never_reuses_an_announced_version(tmp_path):
    from services.learner.checkpoint import (
        CheckpointError,
        Lineage,
        continued_lineage,
        last_published,
        record_published,
    )

    assert last_published(tmp_path) is None
    for v in range(7):
        record_published(tmp_path, "run-a", v)
    assert last_published(tmp_path) == ("run-a", 6)
    at_ckpt = Lineage(3, "run-a", {"critic_loss": 0.5})
    # killed after announcing v4..v6 past the checkpoint at v3: go on from v6
    assert continued_lineage(at_ckpt, ("run-a", 6), "fresh") == Lineage(6, "run-a", {"critic_loss": 0.5})
    # nothing announced past the checkpoint, or another run's record: the checkpoint's lineage
    assert continued_lineage(at_ckpt, ("run-a", 3), "fresh") == at_ckpt
    assert continued_lineage(at_ckpt, ("run-b", 99), "fresh") == at_ckpt
    # killed before the first checkpoint: keep the run id and count on; nothing at all: a new lineage
    assert continued_lineage(None, ("run-a", 6), "fresh") == Lineage(6, "run-a", {})
    assert continued_lineage(None, None, "fresh") == Lineage(-1, "fresh", {})
    (tmp_path / "published.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="published.json"):
        last_published(tmp_path)


def test_every_learner_preset_checkpoints():
    from services.learner.config import PRESETS

    for name, cfg in PRESETS.items():
        assert cfg.checkpoint_minutes > 0 or cfg.checkpoint_every > 0, name


# ------------------------------------------------------------------------------------------------
# Retention
# ------------------------------------------------------------------------------------------------


def names(directory) -> list[str]:
    return [p.name for p in checkpoint.checkpoints(directory)]


def test_only_the_newest_keep_checkpoints_remain_numbered_past_nine(tmp_path):
    for k in range(1, 13):
        save(tmp_path, k, keep=3)
        assert len(names(tmp_path)) == min(k, 3)
    assert names(tmp_path) == ["learner-000012.pt", "learner-000011.pt", "learner-000010.pt"]
    assert checkpoint.load(tmp_path)[2]["version"] == 12
    save(tmp_path, 13, keep=1)  # keep 1: the new one alone
    assert names(tmp_path) == ["learner-000013.pt"]
    with pytest.raises(ValueError, match="keep"):
        save(tmp_path, 14, keep=0)
    assert names(tmp_path) == ["learner-000013.pt"]  # refused before anything was written


def test_a_byte_budget_deletes_the_oldest_but_never_the_newest(tmp_path):
    save(tmp_path, 1)
    size = (tmp_path / checkpoint.file_name(1)).stat().st_size
    for k in (2, 3, 4):
        save(tmp_path, k, keep=10, max_bytes=2 * size + size // 2)
    assert names(tmp_path) == ["learner-000004.pt", "learner-000003.pt"]  # two fit, three do not
    save(tmp_path, 5, keep=10, max_bytes=1)  # a budget below one checkpoint still keeps the newest
    assert names(tmp_path) == ["learner-000005.pt"]
    assert checkpoint.load(tmp_path)[2]["version"] == 5


def test_a_file_being_written_and_the_published_lineage_are_never_rotated(tmp_path):
    save(tmp_path, 1)
    checkpoint.record_published(tmp_path, "run-1", 7)
    (tmp_path / checkpoint.TMP).write_bytes(b"half a checkpoint")  # a write in progress (or crashed)
    assert names(tmp_path) == ["learner-000001.pt"]
    for k in (2, 3, 4):
        save(tmp_path, k, keep=1)
    assert sorted(os.listdir(tmp_path)) == ["learner-000004.pt", "published.json"]  # the tmp was reused
    assert checkpoint.last_published(tmp_path) == ("run-1", 7)


def test_checkpoints_from_before_numbering_are_resumed_then_rotated(tmp_path):
    # the layout of earlier versions: learner.pt (newest) and learner.prev.pt
    save(tmp_path, 1)
    save(tmp_path, 2)
    os.replace(tmp_path / checkpoint.file_name(1), tmp_path / "learner.prev.pt")
    os.replace(tmp_path / checkpoint.file_name(2), tmp_path / "learner.pt")
    assert checkpoint.exists(tmp_path) and checkpoint.load(tmp_path)[2]["version"] == 2
    (tmp_path / "learner.pt").write_bytes(b"\x00garbage")
    assert checkpoint.load(tmp_path)[2]["version"] == 1  # the old fallback still works
    save(tmp_path, 3, keep=3)  # numbering starts after them, and they count as the oldest
    assert names(tmp_path) == ["learner-000001.pt", "learner.pt", "learner.prev.pt"]
    assert checkpoint.load(tmp_path)[2]["version"] == 3
    save(tmp_path, 4, keep=2)
    assert names(tmp_path) == ["learner-000002.pt", "learner-000001.pt"]


def test_a_learner_saving_more_than_keep_resumes_from_the_newest(tmp_path):
    from services.learner.config import LearnerConfig

    assert LearnerConfig().keep_checkpoints == checkpoint.KEEP == 3
    with pytest.raises(ValueError, match="keep_checkpoints"):
        LearnerConfig(keep_checkpoints=0)
    with pytest.raises(ValueError, match="checkpoint_max_bytes"):
        LearnerConfig(checkpoint_max_bytes=-1)
    a = tiny_trainer(min_steps=10, seed=1)
    a.insert(learner_episode(0, T=10, demo=True))
    lineages = []
    for v in range(5):
        assert a.step() is not None
        lineages.append(checkpoint.Lineage(version=v, run_id="run-k", last={"critic_loss": float(v)}))
        checkpoint.save_trainer(tmp_path, a, lineages[-1], {"v": v}, keep=2)
    assert names(tmp_path) == ["learner-000005.pt", "learner-000004.pt"]
    b = tiny_trainer(min_steps=10, seed=2)
    assert checkpoint.restore_trainer(tmp_path, b)[0] == lineages[-1]
    assert b.updates == a.updates == 5
