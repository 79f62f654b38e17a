"""Fuzzing ``proto.codec.decode``: hostile bytes may only ever raise ProtocolError, fast and small.

Seeded and deterministic: mutations of valid encoded messages (bit flips, overwrites with
interesting bytes, truncations, insertions, deletions, splices of two messages, forged lengths),
random byte strings, structure-aware mutations of decoded wire maps, and hand-crafted hostile
inputs (2 GB length prefixes with tiny bodies, ndarray shapes of 2**40 elements, deep nesting,
nested forged array headers) whose memory use is measured with tracemalloc.
"""

from __future__ import annotations

import random
import struct
import time
import tracemalloc
from collections.abc import Callable, Iterator
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from proto.codec import Message, decode
from proto.episode import Augmentation, Episode
from proto.inference import ActReply, ActRequest, EStop, ResetReply, ResetRequest
from proto.msgpack_wire import EXT_NDARRAY, ProtocolError, pack
from proto.weights import WeightsBlob
from tests.helpers.wire_samples import fixed_eval_report, fixed_heartbeat, fixed_replay_gate

pytestmark = pytest.mark.contract

SEED = 0x5EED
MAX_SECONDS_PER_INPUT = 2.0
MAX_HOSTILE_BYTES = 50 * 1024 * 1024
INTERESTING = [0x00, 0x01, 0x7F, 0x80, 0x90, 0x91, 0xC0, 0xC1, 0xC2, 0xC4, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCF]
INTERESTING += [0xD3, 0xD4, 0xD8, 0xD9, 0xDB, 0xDC, 0xDD, 0xDE, 0xDF, 0xE0, 0xFF]


# ----------------------------------------------------------------------------------------------
# valid seed messages (small, one or more per registered type)
# ----------------------------------------------------------------------------------------------


def seed_messages() -> list[Message]:
    rng = np.random.default_rng(SEED)
    out: list[Message] = []
    for T, S, P, images, augmented in [
        (1, 1, 1, False, False),
        (3, 3, 4, True, True),
        (2, 2, 2, False, True),
    ]:
        ends = np.zeros(T, bool)
        ends[-1] = True
        aug = Augmentation(
            source_episode_id="actor-0-1-2",
            kind="mea",
            seed=7,
            copy_index=1,
            phase_split=T,
            params={"rotation": np.array([0.5], np.float32), "delta_r": rng.standard_normal(T)},
        )
        out.append(
            Episode(
                episode_id=f"actor-0-{T}-0",
                task="block_pick",
                seed=T,
                actor_id="actor-0",
                policy_version=-1,
                policy_kind="random",
                is_demo=bool(T % 2),
                created_at=1_700_000_000.5,
                segments=["gripper"] + [f"object_{i}" for i in range(S - 1)],
                points=rng.standard_normal((T + 1, S, P, 3)).astype(np.float32),
                point_counts=rng.integers(0, 9, (T + 1, S)).astype(np.int32),
                jaw=rng.random(T + 1).astype(np.float32),
                actions=rng.uniform(-1, 1, (T, 5)).astype(np.float32),
                rewards=rng.standard_normal(T).astype(np.float32),
                terminated=ends,
                truncated=np.zeros(T, bool),
                gripper_pose=rng.standard_normal((T + 1, 4)).astype(np.float32),
                object_poses=rng.standard_normal((T + 1, S - 1, 7)).astype(np.float32),
                contacts=rng.random((T + 1, S - 1)) < 0.5,
                images=rng.integers(0, 255, (T + 1, 1, 4, 4), dtype=np.uint8) if images else None,
                augmentation=aug if augmented else None,
            )
        )
    tensors = {
        "actor.w": rng.standard_normal((4, 3)).astype(np.float32),
        "actor.b": np.zeros(3, np.float16),
        "log_alpha": np.array(0.1, np.float32),
        "mask": np.array([True, False]),
        "steps": np.array([5], np.int64),
    }
    blob = WeightsBlob.create(12, "equi_rsac", "run-1", tensors, config_json='{"hidden": 8}')
    out += [blob, blob.announcement(len(blob.encode()))]
    out.append(fixed_heartbeat(detail="ok"))
    out += [fixed_eval_report(mean_length=47.0), fixed_replay_gate()]  # canonical: a float length
    out.append(ResetRequest(session="robot-0", task="block_pull", created_at=5.0))
    out.append(ResetReply(session="robot-0", accepted=True, reason="", episode=3, policy_version=12,
                          run_id="run-1", observation="voxel"))  # fmt: skip
    state = np.array([0.5, 0.0, 0.1, np.nan, np.inf], np.float32)  # not range-checked on the wire
    out.append(ActRequest(session="robot-0", episode=3, step=0, stamp=6.0, state=state,
                          points=rng.standard_normal((2, 4, 3)).astype(np.float32),
                          point_counts=np.array([4, 9], np.int32)))  # fmt: skip
    out.append(ActRequest(session="robot-0", episode=3, step=1, stamp=6.1, state=np.zeros(5, np.float32),
                          executed=np.array([1, 0, 0, 0, 0], np.float32),
                          image=rng.integers(0, 255, (2, 4, 4), dtype=np.uint8)))  # fmt: skip
    out.append(ActReply(session="robot-0", episode=3, step=1, action=np.array([1, 0, 0, 0, 0], np.float32),
                        policy_version=-1, held=True, reasons=["non_finite_observation", "estop"],
                        compute_seconds=0.002))  # fmt: skip
    out.append(EStop(operator_id="operator-0", engaged=True, created_at=7.0, reason="test"))
    return out


SEEDS = seed_messages()
SEED_BYTES = [m.encode() for m in SEEDS]


def test_seed_messages_cover_every_type_and_decode() -> None:
    assert {m.TYPE for m in SEEDS} >= {"Episode", "WeightsBlob", "WeightsAnnouncement"}
    assert any(m.TYPE == "Episode" and m.augmentation is not None for m in SEEDS)
    assert {m.TYPE for m in SEEDS} >= {"Heartbeat", "EvalReport", "ReplayGate"}
    assert {m.TYPE for m in SEEDS} >= {"ResetRequest", "ResetReply", "ActRequest", "ActReply", "EStop"}
    assert {(m.points is None, m.image is None) for m in SEEDS if m.TYPE == "ActRequest"} == {
        (False, True),
        (True, False),
    }
    for data in SEED_BYTES:
        assert decode(data).encode() == data


# ----------------------------------------------------------------------------------------------
# the harness
# ----------------------------------------------------------------------------------------------


class Outcomes:
    """Runs decode on each input and records anything other than success or ProtocolError."""

    def __init__(self) -> None:
        self.count = 0
        self.accepted = 0
        self.failures: list[str] = []
        self.slowest = (0.0, b"")

    def feed(self, data: bytes) -> None:
        self.count += 1
        t0 = time.perf_counter()
        try:
            decode(data)
            self.accepted += 1
        except ProtocolError as exc:
            assert isinstance(exc.field, str) and exc.field
        except BaseException as exc:  # noqa: BLE001 - anything else is the bug we look for
            if isinstance(exc, KeyboardInterrupt):
                raise
            if len(self.failures) < 20:
                self.failures.append(f"{type(exc).__name__}: {str(exc)[:200]} <- {data[:120].hex()}")
        elapsed = time.perf_counter() - t0
        if elapsed > self.slowest[0]:
            self.slowest = (elapsed, data[:120])

    def check(self) -> None:
        assert not self.failures, "decode raised something other than ProtocolError:\n" + "\n".join(
            self.failures
        )
        assert self.slowest[0] < MAX_SECONDS_PER_INPUT, (
            f"slow decode ({self.slowest[0]:.2f} s): {self.slowest[1].hex()}"
        )


def mutate(rng: random.Random, data: bytes) -> bytes:
    buf = bytearray(data)
    op = rng.randrange(9)
    if op == 0:  # flip a few bits
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(len(buf))
            buf[i] ^= 1 << rng.randrange(8)
    elif op == 1:  # overwrite bytes with msgpack-significant values
        for _ in range(rng.randint(1, 4)):
            buf[rng.randrange(len(buf))] = rng.choice(INTERESTING)
    elif op == 2:  # truncate
        del buf[rng.randrange(len(buf)) :]
    elif op == 3:  # insert random bytes
        i = rng.randrange(len(buf) + 1)
        buf[i:i] = rng.randbytes(rng.randint(1, 16))
    elif op == 4:  # delete a range
        i = rng.randrange(len(buf))
        del buf[i : i + rng.randint(1, 32)]
    elif op == 5:  # splice two messages
        other = rng.choice(SEED_BYTES)
        buf = buf[: rng.randrange(len(buf) + 1)] + other[rng.randrange(len(other)) :]
    elif op == 6:  # duplicate a range
        i = rng.randrange(len(buf))
        j = min(len(buf), i + rng.randint(1, 64))
        buf[j:j] = buf[i:j]
    elif op == 7:  # forge a 16/32-bit big-endian length after a byte
        i = rng.randrange(len(buf))
        forged = rng.choice([0xFFFF, 0xFFFFFFF0, 0x7FFFFFFF, 0, 1, len(buf), len(buf) + 1])
        width = rng.choice([2, 4])
        buf[i + 1 : i + 1 + width] = (forged & (256**width - 1)).to_bytes(width, "big")
    else:  # random bytes overwrite a whole range
        i = rng.randrange(len(buf))
        n = rng.randint(1, 32)
        buf[i : i + n] = rng.randbytes(n)
    return bytes(buf)


def random_value(rng: random.Random, depth: int = 0) -> Any:
    """A random msgpack-able value, arrays of any wire dtype included."""
    kind = rng.randrange(12 if depth < 3 else 8)
    if kind == 0:
        return None
    if kind == 1:
        return rng.choice([True, False])
    if kind == 2:
        return rng.choice([0, -1, 1, 2**31, 2**62, 2**63 - 1, -(2**63), 2**64 - 1, rng.randint(-1000, 1000)])
    if kind == 3:
        return rng.choice([0.0, -0.0, 1.5, -1e300, float("nan"), float("inf"), rng.random()])
    if kind == 4:
        return rng.choice(["", "gripper", "actor-0", "x" * 2000, "ünï", "a/b", "block_pull", "rsac"])
    if kind == 5:
        return rng.randbytes(rng.randint(0, 16))
    if kind == 6:
        dtype = rng.choice(["<f4", "<f8", "<f2", "<i4", "<i8", "|u1", "|b1", "<u2"])
        shape = tuple(rng.randint(0, 3) for _ in range(rng.randint(0, 4)))
        return np.frombuffer(rng.randbytes(int(np.prod(shape)) * np.dtype(dtype).itemsize), dtype).reshape(
            shape
        )
    if kind == 7:
        if rng.random() < 0.2:
            return msgpack.Timestamp(rng.randint(-(2**40), 2**40), rng.randint(0, 999_999_999))  # ext -1
        return msgpack.ExtType(rng.choice([1, 1, 2, 127]), rng.randbytes(rng.randint(0, 12)))
    if kind in (8, 9):
        return [random_value(rng, depth + 1) for _ in range(rng.randint(0, 4))]
    return {rng.choice(["a", "_type", "_v", "x", "gripper"]): random_value(rng, depth + 1) for _ in range(3)}


def mutate_wire(rng: random.Random, msg: Message) -> bytes:
    """Structure-aware: change, drop or add fields of a valid wire map, then re-pack."""
    wire: dict[Any, Any] = {"_type": msg.TYPE, "_v": msg.VERSION, **msg.to_wire()}
    for _ in range(rng.randint(1, 3)):
        op = rng.randrange(5)
        name = rng.choice(list(wire))
        if op == 0:
            del wire[name]
        elif op == 1:
            wire[name] = random_value(rng)
        elif op == 2:
            wire[rng.choice(["bogus", "_extra", "Points"])] = random_value(rng)
        elif op == 3 and isinstance(wire[name], np.ndarray) and wire[name].size:
            arr = wire[name].copy()
            bad = rng.choice([1, -2, 255, 1e30, np.nan, -np.inf] if arr.dtype.kind == "f" else [1, -2, 255])
            arr.reshape(-1)[rng.randrange(arr.size)] = np.array(bad).astype(arr.dtype)  # wraps, as C would
            wire[name] = arr
        elif op == 4 and isinstance(wire[name], np.ndarray):
            a = wire[name]
            wire[name] = a.reshape(-1) if rng.random() < 0.5 else a[: max(0, a.shape[0] - 1)] if a.ndim else a
    return pack(wire)


# ----------------------------------------------------------------------------------------------
# fuzz runs
# ----------------------------------------------------------------------------------------------


@pytest.mark.timeout(120)
def test_fuzz_mutated_and_random_bytes() -> None:
    rng = random.Random(SEED)
    out = Outcomes()
    for _ in range(30_000):
        data = rng.choice(SEED_BYTES)
        for _ in range(rng.choice([1, 1, 1, 2, 4])):
            data = mutate(rng, data) or b"\x80"
        out.feed(data)
    for _ in range(1_500):
        out.feed(rng.randbytes(rng.randint(0, 64)))
    for _ in range(500):  # random bytes behind a plausible envelope prefix
        out.feed(b"\x83\xa5_type\xa7Episode\xa2_v\x01" + rng.randbytes(rng.randint(0, 64)))
    for _ in range(5_000):
        out.feed(mutate_wire(rng, rng.choice(SEEDS)))
    assert out.count >= 35_000
    # the mutations must not be so destructive that nothing ever gets past the msgpack layer
    assert out.accepted > 0
    out.check()


@settings(max_examples=500, deadline=None, derandomize=True, database=None)
@given(st.binary(max_size=256) | st.sampled_from(SEED_BYTES).flatmap(lambda b: st.just(b[: len(b) // 2])))
def test_fuzz_hypothesis_bytes(data: bytes) -> None:
    out = Outcomes()
    out.feed(data)
    out.check()


# ----------------------------------------------------------------------------------------------
# hand-crafted hostile inputs, with their memory measured
# ----------------------------------------------------------------------------------------------

HUGE = 0xFFFFFFF0  # a ~4 GB claim in a 32-bit length (the brief's "2 GB" class and beyond)
ENVELOPE = b"\x83\xa5_type\xa7Episode\xa2_v\x02\xa6points"  # a map of 3, two entries, a key


def ext_ndarray(dtype: str, shape: list[int], data: bytes) -> bytes:
    return pack(
        {
            "_type": "WeightsBlob",
            "_v": 1,
            "tensors": {"x": msgpack.ExtType(EXT_NDARRAY, pack([dtype, shape, data]))},
        }
    )


def ext_raw(payload: bytes, code: int = EXT_NDARRAY) -> bytes:
    """An ext 32 with exactly this payload."""
    return b"\xc9" + struct.pack(">I", len(payload)) + bytes([code]) + payload


def nested_headers(header: bytes, depth: int, pad: int = 0) -> bytes:
    return header * depth + b"\x00" * pad


def hostile_inputs() -> Iterator[tuple[str, bytes]]:
    huge = struct.pack(">I", HUGE)
    for name, header in [
        ("array32", b"\xdd" + huge),
        ("map32", b"\xdf" + huge),
        ("bin32", b"\xc6" + huge),
        ("str32", b"\xdb" + huge),
        ("ext32", b"\xc9" + huge + b"\x01"),
    ]:
        yield f"{name} claiming {HUGE} bytes", header + b"\x00" * 8
        yield f"{name} claiming {HUGE} bytes as a field value", ENVELOPE + header + b"\x00" * 8
        yield (
            f"{name} claiming {HUGE} bytes inside an ndarray ext",
            (ENVELOPE + ext_raw(b"\x93\xa3<f4\x91\x01" + header + b"\x00" * 2)),
        )
    yield "array32 of 2**31 inside map32 of 2**31", b"\xdf\x80\x00\x00\x00\xa1a\xdd\x80\x00\x00\x00"
    yield "ext8 claiming more than present", ENVELOPE + b"\xc7\xff\x01\x93"
    yield "ndarray of 2**40 elements", ext_ndarray("<f4", [2**40], b"\x00" * 4)
    yield "ndarray of 2**20 x 2**20 elements", ext_ndarray("|u1", [2**20, 2**20], b"\x00")
    yield "ndarray of 2**64-1 elements", ext_ndarray("<f8", [2**64 - 1], b"")
    yield "ndarray 0 x 2**63", ext_ndarray("<f8", [0, 2**63], b"")
    yield "ndarray 0 x 2**40 x 2**40", ext_ndarray("<f8", [0, 2**40, 2**40], b"")
    yield "ndarray with 1000 dims", ext_ndarray("<f8", [1] * 1000, b"\x00" * 8)
    yield "fixarray nesting x100000", b"\x91" * 100_000
    yield "fixmap nesting x100000", b"\x81\xa1a" * 100_000
    yield "array16 nesting x50000", b"\xdc\x00\x01" * 50_000
    yield "nesting inside an ndarray ext", ENVELOPE + ext_raw(b"\x91" * 100_000)
    # each array header makes msgpack preallocate its list: ~1000 nested forged headers
    yield "nested array32 headers of 10000", nested_headers(b"\xdd\x00\x00\x27\x10", 1100, 10_000)
    yield "nested array32 headers of 4096", nested_headers(b"\xdd\x00\x00\x10\x00", 1100, 10_000)
    yield "nested array16 headers of 65535", nested_headers(b"\xdc\xff\xff", 1100, 70_000)
    yield "nested map32 headers of 10000", nested_headers(b"\xdf\x00\x00\x27\x10\xa1a", 1100, 10_000)
    yield (
        "nested array headers inside an ndarray ext",
        (ENVELOPE + ext_raw(nested_headers(b"\xdd\x00\x00\x27\x10", 1100, 10_000))),
    )
    yield "many small arrays", b"\xdc\xff\xff" + b"\x90" * 65_535
    yield (
        "wide map of maps",
        b"\xde\xff\xff" + b"".join(b"\xa1" + bytes([65 + i % 26]) + b"\x80" for i in range(65_535)),
    )
    yield "timestamp ext (-1) with a bad length", ENVELOPE + b"\xc7\x05\xff" + b"\x00" * 5
    yield "timestamp ext (-1) as a field value", ENVELOPE + b"\xd6\xff" + b"\x00" * 4


def measured(fn: Callable[[], None]) -> tuple[int, float]:
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        fn()
    finally:
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return peak, elapsed


@pytest.mark.timeout(120)
@pytest.mark.parametrize(("name", "data"), list(hostile_inputs()), ids=[n for n, _ in hostile_inputs()])
def test_hostile_input_is_refused_cheaply(name: str, data: bytes) -> None:
    raised: list[BaseException] = []

    def run() -> None:
        try:
            decode(data)
        except BaseException as exc:  # noqa: BLE001 - recorded and judged below
            raised.append(exc)

    peak, elapsed = measured(run)
    assert raised, f"{name}: decoded without error"
    assert isinstance(raised[0], ProtocolError), f"{name}: {type(raised[0]).__name__}: {raised[0]}"
    assert peak < MAX_HOSTILE_BYTES, f"{name}: decoding allocated {peak / 2**20:.1f} MiB"
    assert elapsed < MAX_SECONDS_PER_INPUT, f"{name}: took {elapsed:.2f} s"


def test_measurement_sees_allocations() -> None:
    """The memory bound above is only meaningful if tracemalloc sees msgpack's allocations."""
    data = pack([b"\x00" * (8 * 2**20)])
    peak, _ = measured(lambda: msgpack.unpackb(data))
    assert peak >= 8 * 2**20
