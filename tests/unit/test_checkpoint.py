"""Checkpoint files: atomic replace, previous copy kept, nothing unpickled beyond tensors and plain data."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
import torch

from services.learner import checkpoint


def payload(k: int) -> tuple[dict, dict, dict]:
    learner = {
        "w": torch.full((3,), float(k)),
        "opt": {"state": {}, "param_groups": [{"lr": 0.1, "betas": (0.9, 0.99)}]},
    }
    replay = {"codes": np.arange(12, dtype=np.uint8).reshape(3, 4) + k, "count": k, "ids": ["a", "b"]}
    meta = {"version": k, "run_id": "run-1"}
    return learner, replay, meta


def test_round_trip_and_previous_copy(tmp_path):
    checkpoint.save(tmp_path, **dict(zip(("learner", "replay", "meta"), payload(1), strict=True)))
    checkpoint.save(tmp_path, **dict(zip(("learner", "replay", "meta"), payload(2), strict=True)))
    learner, replay, meta = checkpoint.load(tmp_path)
    assert meta == {"version": 2, "run_id": "run-1"}
    assert torch.equal(learner["w"], torch.full((3,), 2.0))
    assert learner["opt"]["param_groups"][0]["betas"] == (0.9, 0.99)
    assert replay["codes"].dtype == np.uint8 and (replay["codes"] == np.arange(12).reshape(3, 4) + 2).all()
    assert replay["count"] == 2 and replay["ids"] == ["a", "b"]
    assert (tmp_path / checkpoint.PREVIOUS).exists()
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_a_corrupt_newest_file_falls_back_to_the_previous_one(tmp_path):
    for k in (1, 2):
        checkpoint.save(tmp_path, **dict(zip(("learner", "replay", "meta"), payload(k), strict=True)))
    (tmp_path / checkpoint.FILE).write_bytes(b"\x00garbage")
    _, _, meta = checkpoint.load(tmp_path)
    assert meta["version"] == 1


class Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned > /dev/null",))


def test_arbitrary_pickles_are_refused(tmp_path):
    with open(tmp_path / checkpoint.FILE, "wb") as f:
        torch.save(
            {"format": checkpoint.FORMAT, "learner": Evil(), "replay": {}, "meta": "{}"},
            f,
            pickle_module=pickle,
        )
    with pytest.raises(checkpoint.CheckpointError, match="learner.pt"):
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
