"""The weights digest: the documented test vector and algorithm, and tampered blobs refused."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

import proto
from proto.codec import decode
from proto.msgpack_wire import pack
from proto.weights import WeightsBlob, tensors_digest
from tests.helpers.wire_asserts import field_error
from tests.helpers.wire_samples import SEED, gen_tensors, rand_finite, wire_of

pytestmark = pytest.mark.contract


README = Path(proto.__file__).with_name("README.md").read_text(encoding="utf-8")
DIGEST_VECTOR = "2c98c62b648a76d63b6feeff9e4bcda5bfd082634bdc2bce152430f89df2def7"


def test_digest_test_vector() -> None:
    tensors = {
        "pi.bias": np.array([0.5, -1.0], np.float32),
        "log_alpha": np.array(0.0, np.float32),
        "step": np.array([[7]], np.int64),
    }
    assert tensors_digest(tensors) == DIGEST_VECTOR
    assert DIGEST_VECTOR in README


def reference_digest(tensors: dict[str, np.ndarray]) -> str:
    """The algorithm exactly as proto/README.md states it, written independently of proto.weights."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        a = tensors[name]
        assert a.dtype.str in ("<f4", "<f2", "<i8", "|b1")  # native little-endian test data
        shape = ",".join(str(d) for d in a.shape)  # a 0-d tensor has the empty shape text
        h.update(name.encode() + b"\0" + a.dtype.str.encode() + b"\0" + shape.encode() + b"\0")
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def test_digest_matches_the_documented_algorithm() -> None:
    rng = np.random.default_rng(SEED)
    for _ in range(30):
        tensors = gen_tensors(rng)
        assert tensors_digest(tensors) == reference_digest(tensors)
    # the digest covers names, dtypes and shapes, not only the bytes
    base = {"a": np.zeros((2, 3), np.float32)}
    digests = {
        tensors_digest(t)
        for t in (
            base,
            {"b": np.zeros((2, 3), np.float32)},
            {"a": np.zeros((3, 2), np.float32)},
            {"a": np.zeros(6, np.float32)},
            {"a": np.zeros((2, 3), np.int32)},
            {"a": np.zeros((2, 3), np.float32), "z": np.zeros(0, np.float32)},
        )
    }
    assert len(digests) == 6


def test_digest_mismatch() -> None:
    rng = np.random.default_rng(SEED)
    blob = WeightsBlob.create(
        3, "rsac", "run-1", {"w": rand_finite(rng, (4, 4)), "b": np.zeros(4, np.float32)}
    )
    wire = wire_of(blob)
    decode(pack(wire))
    tampered = wire["tensors"]["w"].copy()
    tampered[1, 2] += 1.0
    wire["tensors"] = {**wire["tensors"], "w": tampered}
    err = field_error(wire)
    assert err.field == "WeightsBlob.digest" and "match" in err.problem
    # renaming a tensor, reshaping it or changing the digest string are caught as well
    for tensors, digest in [
        ({"v": blob.tensors["w"], "b": blob.tensors["b"]}, blob.digest),
        ({"w": blob.tensors["w"].reshape(2, 8), "b": blob.tensors["b"]}, blob.digest),
        (blob.tensors, "0" * 64),
    ]:
        wire = wire_of(blob)
        wire["tensors"], wire["digest"] = tensors, digest
        assert field_error(wire).field == "WeightsBlob.digest"
