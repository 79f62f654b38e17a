"""Weights broadcast: a small announcement, and the blob consumers pull when it is newer."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass

import numpy as np

from proto.codec import Message
from proto.msgpack_wire import WIRE_DTYPES, ProtocolError, wire_dtype
from proto.specs import ANY_SHAPE, ID_PATTERN, Arr, Float, Int, MapOf, Str, spec

ALGORITHMS = ("equi_rsac", "rsac", "gasv2")
DIGEST_PATTERN = r"[0-9a-f]{64}"
TENSOR_NAME = r"[A-Za-z0-9_.:/-]{1,128}"


def tensors_digest(tensors: dict[str, np.ndarray]) -> str:
    """sha256 over tensors in name order: name, dtype, shape, then the little-endian bytes."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        wire = wire_dtype(tensors[name])
        arr = np.ascontiguousarray(tensors[name], dtype=WIRE_DTYPES[wire]).reshape(np.shape(tensors[name]))
        h.update(f"{name}\0{wire}\0{','.join(map(str, arr.shape))}\0".encode())
        h.update(arr.tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class WeightsAnnouncement(Message):
    """Published by the learner each time it has a new version; consumers compare versions."""

    TYPE = "WeightsAnnouncement"
    VERSION = 1

    version: int = spec(Int(0, 2**62), "monotonic weights version within `run_id`")
    algorithm: str = spec(Str(choices=ALGORITHMS), "algorithm whose policy the weights belong to")
    digest: str = spec(Str(pattern=DIGEST_PATTERN), "sha256 of the tensors (see `tensors_digest`)")
    byte_size: int = spec(Int(0, 2**40), "encoded size of the WeightsBlob in bytes")
    created_at: float = spec(Float(0.0), "UNIX time (s) the version was made")
    run_id: str = spec(Str(pattern=ID_PATTERN), "training run (version lineage) id")


@dataclass(frozen=True)
class WeightsBlob(Message):
    """Policy tensors by name, without pickle; the digest is checked on decode."""

    TYPE = "WeightsBlob"
    VERSION = 1

    version: int = spec(Int(0, 2**62), "weights version")
    algorithm: str = spec(Str(choices=ALGORITHMS), "algorithm")
    digest: str = spec(Str(pattern=DIGEST_PATTERN), "sha256 of the tensors")
    created_at: float = spec(Float(0.0), "UNIX time (s) the version was made")
    run_id: str = spec(Str(pattern=ID_PATTERN), "training run id")
    config_json: str = spec(Str(max_len=65536), "JSON of the network config needed to rebuild the policy")
    tensors: dict = spec(
        MapOf(Arr(("float32", "float16", "int64", "bool"), ANY_SHAPE), key_pattern=TENSOR_NAME),
        "policy parameters and buffers by name",
    )

    @classmethod
    def create(
        cls,
        version: int,
        algorithm: str,
        run_id: str,
        tensors: dict[str, np.ndarray],
        config_json: str = "{}",
    ) -> WeightsBlob:
        return cls(
            version=version,
            algorithm=algorithm,
            digest=tensors_digest(tensors),
            created_at=time.time(),
            run_id=run_id,
            config_json=config_json,
            tensors=dict(tensors),
        )

    def announcement(self, byte_size: int) -> WeightsAnnouncement:
        return WeightsAnnouncement(
            version=self.version,
            algorithm=self.algorithm,
            digest=self.digest,
            byte_size=byte_size,
            created_at=self.created_at,
            run_id=self.run_id,
        )

    def validate(self, dims: dict[str, int]) -> None:
        if tensors_digest(self.tensors) != self.digest:
            raise ProtocolError("digest", "does not match the tensors (corrupt or tampered blob)")
