"""Weights files: what the learner writes for every version, and what a pinned server accepts."""

from __future__ import annotations

import os

import numpy as np
import pytest

from proto.seal import seal
from proto.weights import WeightsBlob
from services.common import weights_file
from services.common.weights_file import WeightsFileError

KEY = bytes(range(32))
OTHER = bytes(range(1, 33))


def blob(version: int) -> WeightsBlob:
    t = {"w": np.arange(6, dtype=np.float32).reshape(2, 3) * version}
    return WeightsBlob.create(version, "equi_rsac", "run-a", t, "{}")


def test_sealed_round_trip_and_retention(tmp_path):
    for v in range(1, 6):
        weights_file.write(tmp_path, blob(v), KEY, "learner-0", keep=3)
    assert [v for v, _ in weights_file.versions(tmp_path)] == [3, 4, 5]
    assert not list(tmp_path.glob(".*tmp"))
    newest = weights_file.resolve(tmp_path)
    assert weights_file.read(newest, KEY).version == 5
    assert weights_file.read(weights_file.resolve(tmp_path, 4), KEY).version == 4
    with pytest.raises(WeightsFileError, match="no weights file for version 1"):
        weights_file.resolve(tmp_path, 1)


def test_a_run_dir_is_searched_for_the_learners_weights(tmp_path):
    weights_file.write(tmp_path / "learner" / "weights", blob(2))
    assert weights_file.resolve(tmp_path).name == "weights-00000002.blob"
    with pytest.raises(WeightsFileError, match="no weights"):
        weights_file.resolve(tmp_path / "learner" / "checkpoints-none")


@pytest.mark.parametrize(
    "case", ["other_key", "unsigned", "signed_no_key", "flipped", "truncated", "not_learner"]
)
def test_files_that_must_be_refused_are(tmp_path, case):
    path = tmp_path / "weights-00000001.blob"
    body = blob(1).encode()
    data = {
        "other_key": seal(OTHER, weights_file.FILE_KEY, "learner", "l0", body),
        "unsigned": body,
        "signed_no_key": seal(KEY, weights_file.FILE_KEY, "learner", "l0", body),
        "flipped": bytearray(seal(KEY, weights_file.FILE_KEY, "learner", "l0", body)),
        "truncated": seal(KEY, weights_file.FILE_KEY, "learner", "l0", body)[:-7],
        "not_learner": seal(KEY, weights_file.FILE_KEY, "actor", "a0", body),
    }[case]
    if case == "flipped":
        data[-5] ^= 0x40
    path.write_bytes(bytes(data))
    key = None if case == "signed_no_key" else KEY
    with pytest.raises(WeightsFileError, match="refused|signed|run's key"):
        weights_file.read(path, key)


def test_an_unsigned_file_with_a_tampered_tensor_fails_its_digest(tmp_path):
    b = blob(1)
    tampered = WeightsBlob(**{**b.__dict__, "tensors": {"w": b.tensors["w"] + 1}})
    path = tmp_path / "weights-00000001.blob"
    path.write_bytes(tampered.encode())
    with pytest.raises(WeightsFileError, match="digest"):
        weights_file.read(path, None)
    assert weights_file.read(weights_file.write(tmp_path, b), None).digest == b.digest


def test_unreadable_file_is_named(tmp_path):
    path = tmp_path / "weights-00000001.blob"
    path.write_bytes(blob(1).encode())
    os.chmod(path, 0)
    if os.access(path, os.R_OK):  # root reads anything: check the missing-file message instead
        path = tmp_path / "missing.blob"
    with pytest.raises(WeightsFileError, match="cannot read"):
        weights_file.read(path, None)


def test_the_evaluators_kept_versions_are_found_in_a_run_dir_and_accepted(tmp_path):
    weights_file.write(tmp_path / weights_file.LEARNER, blob(9), KEY, "learner-0")
    weights_file.write(tmp_path / weights_file.EVALUATED, blob(4), KEY, "evaluator-0", service="evaluator")
    assert weights_file.resolve(tmp_path).name == "weights-00000009.blob"  # the newest of either
    old = weights_file.resolve(tmp_path, 4)
    assert old.parent == tmp_path / "eval" / "weights" and weights_file.read(old, KEY).version == 4
