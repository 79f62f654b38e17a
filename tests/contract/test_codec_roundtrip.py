"""Round trips of every registered message type, and validation errors that name the right field.

Two generators per message type: a seeded numpy one (many shapes and dtypes, including empty and
edge values) and a hypothesis strategy. ``test_every_registered_type_has_generators`` fails when a
message type is added to the registry without both, so new messages cannot be forgotten here.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import math
import pkgutil
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import proto
from proto import codec
from proto.actions import ACTION_DIM
from proto.codec import (
    DEFAULT_LIMITS,
    EXT_NDARRAY,
    Arr,
    Bool,
    Float,
    Int,
    Limits,
    ListOf,
    MapOf,
    Message,
    Nested,
    Opt,
    ProtocolError,
    Str,
    decode,
    pack,
    unpack,
)
from proto.control import SERVICES, STATES, EvalReport, Heartbeat, ReplayGate
from proto.episode import AUGMENTATION_KINDS, POLICY_KINDS, TASKS, Augmentation, Episode
from proto.weights import ALGORITHMS, WeightsAnnouncement, WeightsBlob, tensors_digest

pytestmark = pytest.mark.contract

# make sure every proto module has registered its messages before the registry is inspected
for _mod in pkgutil.iter_modules(proto.__path__):
    importlib.import_module(f"proto.{_mod.name}")

SEED = 20240611
ID_CHARS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-"
HYPOTHESIS = settings(
    max_examples=30,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


# ----------------------------------------------------------------------------------------------
# comparison
# ----------------------------------------------------------------------------------------------


def assert_same(a: Any, b: Any, path: str = "") -> None:
    """Deep equality: same types, arrays with the same dtype, shape and bytes, floats bit for bit."""
    assert type(a) is type(b), f"{path}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, Message):
        for f in a.fields():
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype, f"{path}: dtype {a.dtype} != {b.dtype}"
        assert a.shape == b.shape, f"{path}: shape {a.shape} != {b.shape}"
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), f"{path}: values differ"
        assert a.tobytes() == b.tobytes(), f"{path}: bytes differ"
    elif isinstance(a, dict):
        assert list(a) == list(b), f"{path}: keys {list(a)} != {list(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, list):
        assert len(a) == len(b), f"{path}: length {len(a)} != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        assert struct.pack("<d", a) == struct.pack("<d", b), f"{path}: {a!r} != {b!r}"
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


def check_roundtrip(msg: Message) -> Message:
    data = msg.encode()
    out = decode(data)
    assert_same(msg, out, msg.TYPE)
    assert_same(msg, type(msg).decode(data), msg.TYPE)
    assert out.encode() == data, "re-encoding a decoded message changed its bytes"
    return out


# ----------------------------------------------------------------------------------------------
# seeded numpy generators: rng -> valid message
# ----------------------------------------------------------------------------------------------


def rand_id(rng: np.random.Generator, max_len: int = 24) -> str:
    n = int(rng.integers(1, max_len + 1))
    return "".join(ID_CHARS[i] for i in rng.integers(0, len(ID_CHARS), n))


def rand_time(rng: np.random.Generator) -> float:
    return float(rng.choice([0.0, 1_700_000_000.0 + rng.random() * 1e6, rng.random()]))


def rand_finite(rng: np.random.Generator, shape: tuple[int, ...], dtype: Any = np.float32) -> np.ndarray:
    return (rng.standard_normal(shape) * rng.choice([1e-3, 1.0, 1e3])).astype(dtype)


def gen_augmentation(rng: np.random.Generator, max_phase: int = 50) -> Augmentation:
    phase = int(rng.integers(0, max_phase + 1))
    params = {"rotation": rand_finite(rng, (1,)), "delta_r": rand_finite(rng, (phase,), np.float64)}
    if rng.random() < 0.5:
        params["flip:index"] = rng.integers(-(2**40), 2**40, size=int(rng.integers(0, 4)), dtype=np.int64)
    return Augmentation(
        source_episode_id=rand_id(rng),
        kind=str(rng.choice(AUGMENTATION_KINDS)),
        seed=int(rng.integers(0, 2**63 - 1, dtype=np.int64)),
        copy_index=int(rng.integers(0, 1_000_001)),
        phase_split=phase,
        params=params,
    )


def gen_episode(
    rng: np.random.Generator, *, images: bool | None = None, augmented: bool | None = None
) -> Episode:
    T = int(rng.integers(1, 7))
    S = int(rng.integers(1, 5))
    P = int(rng.integers(0, 6))
    images = bool(rng.random() < 0.5) if images is None else images
    augmented = bool(rng.random() < 0.5) if augmented is None else augmented
    ends = np.zeros(T, dtype=bool)
    ends[-1] = True
    truncated = bool(rng.random() < 0.5)
    actions = rng.uniform(-1.0, 1.0, (T, ACTION_DIM)).astype(np.float32)
    actions[0, 0] = rng.choice([-1.0, 1.0, 0.0])  # the bounds themselves are valid
    img = None
    if images:
        C, H, W = int(rng.choice([1, 3])), int(rng.integers(1, 9)), int(rng.integers(1, 9))
        dtype = rng.choice(["uint8", "uint16", "float16", "float32"])
        if dtype in ("uint8", "uint16"):
            img = rng.integers(0, np.iinfo(dtype).max + 1, (T + 1, C, H, W)).astype(dtype)
        else:
            img = rng.random((T + 1, C, H, W)).astype(dtype)
    return Episode(
        episode_id=rand_id(rng),
        task=str(rng.choice(TASKS)),
        seed=int(rng.integers(0, 2**63 - 1, dtype=np.int64)),
        actor_id=rand_id(rng),
        policy_version=int(rng.integers(-1, 1000)),
        policy_kind=str(rng.choice(POLICY_KINDS)),
        is_demo=bool(rng.random() < 0.5),
        created_at=rand_time(rng),
        segments=["gripper"] + [f"object_{i}" for i in range(S - 1)],
        points=rand_finite(rng, (T + 1, S, P, 3)),
        point_counts=rng.integers(0, 1000, (T + 1, S)).astype(np.int32),
        jaw=rng.uniform(0.0, 1.0, T + 1).astype(np.float32),
        actions=actions,
        rewards=rand_finite(rng, (T,)),
        terminated=ends & (not truncated),
        truncated=ends & truncated,
        gripper_pose=rand_finite(rng, (T + 1, 4)),
        object_poses=rand_finite(rng, (T + 1, S - 1, 7)),
        contacts=rng.random((T + 1, S - 1)) < 0.3,
        images=img,
        augmentation=gen_augmentation(rng, max_phase=T) if augmented else None,
    )


def gen_weights_announcement(rng: np.random.Generator) -> WeightsAnnouncement:
    return WeightsAnnouncement(
        version=int(rng.integers(0, 2**62, dtype=np.int64)),
        algorithm=str(rng.choice(ALGORITHMS)),
        digest=rng.bytes(32).hex(),
        byte_size=int(rng.integers(0, 2**40)),
        created_at=rand_time(rng),
        run_id=rand_id(rng),
    )


def gen_tensors(rng: np.random.Generator) -> dict[str, np.ndarray]:
    tensors: dict[str, np.ndarray] = {}
    for i in range(int(rng.integers(0, 6))):
        ndim = int(rng.integers(0, 5))
        shape = tuple(int(d) for d in rng.integers(0, 5, ndim))
        kind = rng.choice(["float32", "float16", "int64", "bool"])
        if kind == "bool":
            arr = rng.random(shape) < 0.5
        elif kind == "int64":
            arr = rng.integers(-(2**62), 2**62, shape, dtype=np.int64)
        else:
            arr = rand_finite(rng, shape, kind)
        tensors[f"layer{i}.{rand_id(rng, 8)}"] = np.asarray(arr, dtype=kind)
    return tensors


def gen_weights_blob(rng: np.random.Generator) -> WeightsBlob:
    tensors = gen_tensors(rng)
    blob = WeightsBlob.create(
        int(rng.integers(0, 2**62, dtype=np.int64)),
        str(rng.choice(ALGORITHMS)),
        rand_id(rng),
        tensors,
        config_json='{"hidden": [256, 256], "note": "ünïcödé ✓"}',
    )
    return dataclasses.replace(blob, created_at=rand_time(rng))


def gen_heartbeat(rng: np.random.Generator) -> Heartbeat:
    counters = {
        f"c{i}_{rand_id(rng, 6)}": float(rng.standard_normal() * 1e6) for i in range(int(rng.integers(0, 6)))
    }
    kwargs: dict[str, Any] = {}
    if rng.random() < 0.5:
        kwargs["detail"] = "last error: ✗ " + rand_id(rng, 40)
    return Heartbeat(
        service=str(rng.choice(SERVICES)),
        instance_id=rand_id(rng),
        pid=int(rng.integers(0, 2**31)),
        state=str(rng.choice(STATES)),
        started_at=rand_time(rng),
        created_at=rand_time(rng),
        policy_version=int(rng.integers(-1, 2**40)),
        counters=counters,
        **kwargs,
    )


def gen_eval_report(rng: np.random.Generator) -> EvalReport:
    return EvalReport(
        evaluator_id=rand_id(rng),
        run_id=rand_id(rng),
        task=str(rng.choice(TASKS)),
        policy_version=int(rng.integers(0, 2**40)),
        env_steps=int(rng.integers(-1, 2**40)),
        episodes=int(rng.integers(1, 1_000_001)),
        success_rate=float(rng.random()),
        mean_return=float(rng.standard_normal() * 100),
        mean_length=float(rng.random() * 500),
        grasp_score=float(rng.random()),
        created_at=rand_time(rng),
    )


def gen_replay_gate(rng: np.random.Generator) -> ReplayGate:
    inserted = int(rng.integers(0, 2**40))
    return ReplayGate(
        learner_id=rand_id(rng),
        run_id=rand_id(rng),
        inserted_steps=inserted,
        allowed_steps=inserted + int(rng.integers(0, 1000)),
        updates=int(rng.integers(0, 2**40)),
        policy_version=int(rng.integers(-1, 2**40)),
        replay_transitions=int(rng.integers(0, 2**40)),
        created_at=rand_time(rng),
    )


GENERATORS: dict[str, Callable[[np.random.Generator], Message]] = {
    "Augmentation": gen_augmentation,
    "Episode": gen_episode,
    "WeightsAnnouncement": gen_weights_announcement,
    "WeightsBlob": gen_weights_blob,
    "Heartbeat": gen_heartbeat,
    "EvalReport": gen_eval_report,
    "ReplayGate": gen_replay_gate,
}


# ----------------------------------------------------------------------------------------------
# hypothesis strategies
# ----------------------------------------------------------------------------------------------


def spec_strategy(spec: codec.Spec) -> st.SearchStrategy:
    """Valid values for scalar-ish specs (arrays and nested messages need message context)."""
    if isinstance(spec, Str):
        if spec.choices is not None:
            return st.sampled_from(spec.choices)
        if spec.pattern is not None:
            return st.from_regex(spec.pattern, fullmatch=True)
        return st.text(st.characters(codec="utf-8"), max_size=min(spec.max_len or 1024, 64))
    if isinstance(spec, Int):
        return st.integers(spec.lo, spec.hi)
    if isinstance(spec, Float):
        return st.floats(spec.lo, spec.hi, allow_nan=False, allow_infinity=False)
    if isinstance(spec, Bool):
        return st.booleans()
    if isinstance(spec, MapOf):
        return st.dictionaries(
            st.from_regex(spec.key_pattern, fullmatch=True), spec_strategy(spec.value), max_size=4
        )
    if isinstance(spec, ListOf):
        return st.lists(spec_strategy(spec.item), max_size=min(spec.max_len or 8, 8))
    if isinstance(spec, Opt):
        return st.none() | spec_strategy(spec.inner)
    raise NotImplementedError(f"no generic strategy for {spec!r}")


def message_strategy(cls: type[Message], **overrides: st.SearchStrategy) -> st.SearchStrategy:
    fields = {
        f.name: overrides[f.name] if f.name in overrides else spec_strategy(f.metadata["spec"])
        for f in cls.fields()
    }
    return st.fixed_dictionaries(fields).map(lambda kw: cls(**kw))


def finite_arrays(
    dtype: str, shape: Any, lo: float | None = None, hi: float | None = None
) -> st.SearchStrategy:
    if dtype == "bool":
        elements = st.booleans()
    elif dtype.startswith(("int", "uint")):
        info = np.iinfo(dtype)
        elements = st.integers(int(info.min), int(info.max))
    else:
        width = {"float16": 16, "float32": 32, "float64": 64}[dtype]
        elements = st.floats(lo, hi, allow_nan=False, allow_infinity=False, width=width)
    return hnp.arrays(np.dtype(dtype), shape, elements=elements)


def augmentation_strategy(max_phase: int = 20) -> st.SearchStrategy:
    params = st.dictionaries(
        st.from_regex(r"[A-Za-z0-9_.:/-]{1,16}", fullmatch=True),
        st.sampled_from(["float32", "float64", "int64"]).flatmap(
            lambda dt: finite_arrays(dt, st.tuples(st.integers(0, 6)))
        ),
        max_size=3,
    )
    return message_strategy(Augmentation, params=params, phase_split=st.integers(0, max_phase))


@st.composite
def episode_strategy(draw: st.DrawFn) -> Episode:
    T, S, P = draw(st.integers(1, 5)), draw(st.integers(1, 4)), draw(st.integers(0, 4))
    names = draw(
        st.lists(
            st.from_regex(r"[a-z0-9_]{1,32}", fullmatch=True), min_size=S - 1, max_size=S - 1, unique=True
        )
    )
    if "gripper" in names:
        names = [f"o{i}" for i in range(S - 1)]
    ends = np.zeros(T, dtype=bool)
    ends[-1] = True
    trunc = draw(st.booleans())
    images = draw(
        st.none()
        | st.tuples(
            st.sampled_from(["uint8", "uint16", "float16", "float32"]), st.integers(1, 3), st.integers(1, 4)
        ).flatmap(lambda a: finite_arrays(a[0], (T + 1, a[1], a[2], a[2])))
    )
    aug = draw(st.none() | augmentation_strategy(max_phase=T))
    scalars = draw(
        st.fixed_dictionaries(
            {
                f.name: spec_strategy(f.metadata["spec"])
                for f in Episode.fields()
                if not isinstance(f.metadata["spec"], (Arr, Opt, ListOf)) and f.name != "fixed_object"
            }
        )
    )
    return Episode(
        **scalars,
        fixed_object=draw(st.integers(-1, S - 2)),  # one of the S - 1 objects, or none
        segments=["gripper", *names],
        points=draw(finite_arrays("float32", (T + 1, S, P, 3))),
        point_counts=draw(hnp.arrays(np.int32, (T + 1, S), elements=st.integers(0, 2**31 - 1))),
        jaw=draw(finite_arrays("float32", (T + 1,), 0.0, 1.0)),
        actions=draw(finite_arrays("float32", (T, ACTION_DIM), -1.0, 1.0)),
        rewards=draw(finite_arrays("float32", (T,))),
        terminated=ends & (not trunc),
        truncated=ends & trunc,
        gripper_pose=draw(finite_arrays("float32", (T + 1, 4))),
        object_poses=draw(finite_arrays("float32", (T + 1, S - 1, 7))),
        contacts=draw(finite_arrays("bool", (T + 1, S - 1))),
        images=images,
        augmentation=aug,
    )


@st.composite
def weights_blob_strategy(draw: st.DrawFn) -> WeightsBlob:
    tensors = draw(
        st.dictionaries(
            st.from_regex(r"[A-Za-z0-9_.:/-]{1,32}", fullmatch=True),
            st.sampled_from(["float32", "float16", "int64", "bool"]).flatmap(
                # any values, NaN included: tensors are not required to be finite
                lambda dt: hnp.arrays(
                    np.dtype(dt), hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=3)
                )
            ),
            max_size=4,
        )
    )
    blob = draw(message_strategy(WeightsBlob, digest=st.just("0" * 64), tensors=st.just(tensors)))
    return dataclasses.replace(blob, digest=tensors_digest(tensors))


STRATEGIES: dict[str, st.SearchStrategy] = {
    "Augmentation": augmentation_strategy(),
    "Episode": episode_strategy(),
    "WeightsAnnouncement": message_strategy(WeightsAnnouncement),
    "WeightsBlob": weights_blob_strategy(),
    "Heartbeat": message_strategy(Heartbeat),
    "EvalReport": message_strategy(EvalReport),
    "ReplayGate": message_strategy(ReplayGate),
}


def real_message_types() -> list[str]:
    """Registered top-level types, except throwaway ones that test modules may define.

    Nested-only types (Augmentation) are covered inside the messages that carry them."""
    return sorted(
        name
        for name, cls in Message._REGISTRY.items()
        if "test" not in cls.__module__.split(".")[0] and not cls.NESTED_ONLY
    )


# ----------------------------------------------------------------------------------------------
# round trips
# ----------------------------------------------------------------------------------------------


def test_every_registered_type_has_generators() -> None:
    registered = set(real_message_types())
    assert registered >= {
        "Episode",
        "WeightsAnnouncement",
        "WeightsBlob",
        "Heartbeat",
        "EvalReport",
        "ReplayGate",
    }
    assert not registered - set(GENERATORS), (
        f"no seeded round-trip generator for {sorted(registered - set(GENERATORS))}"
    )
    assert not registered - set(STRATEGIES), (
        f"no hypothesis strategy for {sorted(registered - set(STRATEGIES))}"
    )
    for name, cls in Message._REGISTRY.items():
        assert name == cls.TYPE


@pytest.mark.parametrize("type_name", real_message_types())
def test_seeded_roundtrip(type_name: str) -> None:
    rng = np.random.default_rng([SEED, len(type_name)])
    gen = GENERATORS[type_name]
    for _ in range(40):
        msg = gen(rng)
        assert type_name == msg.TYPE
        check_roundtrip(msg)


@pytest.mark.parametrize("type_name", real_message_types())
def test_hypothesis_roundtrip(type_name: str) -> None:
    @HYPOTHESIS
    @given(STRATEGIES[type_name])
    def run(msg: Message) -> None:
        assert type_name == msg.TYPE
        check_roundtrip(msg)

    run()


@pytest.mark.parametrize(
    ("images", "augmented"), [(False, False), (True, False), (False, True), (True, True)]
)
def test_episode_variants_roundtrip(images: bool, augmented: bool) -> None:
    rng = np.random.default_rng([SEED, images, augmented])
    for _ in range(10):
        ep = gen_episode(rng, images=images, augmented=augmented)
        assert (ep.images is not None) == images and (ep.augmentation is not None) == augmented
        out = check_roundtrip(ep)
        assert isinstance(out, Episode) and out.num_steps == ep.num_steps
        assert (out.augmentation is None) != augmented


def test_decoded_arrays_are_read_only_views() -> None:
    out = decode(gen_episode(np.random.default_rng(SEED), images=True).encode())
    assert isinstance(out, Episode)
    for name in ("points", "actions", "terminated", "images"):
        assert not getattr(out, name).flags.writeable, name


def test_big_endian_array_is_sent_little_endian() -> None:
    ep = gen_episode(np.random.default_rng(SEED))
    big = dataclasses.replace(ep, rewards=ep.rewards.astype(">f4"), points=np.asfortranarray(ep.points))
    out = decode(big.encode())
    assert out.rewards.dtype == np.dtype("<f4") and np.array_equal(out.rewards, ep.rewards)
    assert out.encode() == ep.encode()


def test_optional_fields_may_be_absent_or_nil() -> None:
    rng = np.random.default_rng(SEED)
    hb = gen_heartbeat(rng)
    wire = {"_type": "Heartbeat", "_v": 1, **hb.to_wire()}
    del wire["detail"]
    assert decode(pack(wire)).detail == ""
    ep = gen_episode(rng, images=False, augmented=False)
    wire = {"_type": "Episode", "_v": 2, **ep.to_wire()}
    del wire["images"], wire["augmentation"]
    out = decode(pack(wire))
    assert out.images is None and out.augmentation is None
    wire["augmentation"] = None
    assert decode(pack(wire)).augmentation is None


def test_field_order_on_the_wire_does_not_matter() -> None:
    ep = gen_episode(np.random.default_rng(SEED), images=True, augmented=True)
    wire = {"_type": "Episode", "_v": 2, **ep.to_wire()}
    shuffled = dict(reversed(list(wire.items())))
    assert_same(decode(pack(shuffled)), ep)


def test_decode_as_the_wrong_class_names_type() -> None:
    data = gen_heartbeat(np.random.default_rng(SEED)).encode()
    with pytest.raises(ProtocolError) as ei:
        Episode.decode(data)
    assert ei.value.field == "_type"


# ----------------------------------------------------------------------------------------------
# documented wire examples (proto/README.md) stay true
# ----------------------------------------------------------------------------------------------

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


def test_ndarray_extension_example_bytes() -> None:
    expected = bytes.fromhex("c7 12 01 93 a3 3c 66 34 92 01 02 c4 08 00 00 80 3f 00 00 00 c0")
    assert pack(np.array([[1.0, -2.0]], dtype=np.float32)) == expected
    assert "c4 08 00 00 80 3f 00 00 00 c0" in README
    out = unpack(expected)
    assert out.dtype == np.float32 and out.tolist() == [[1.0, -2.0]]


# ----------------------------------------------------------------------------------------------
# validation: every failure names the right field
# ----------------------------------------------------------------------------------------------


def wire_of(msg: Message) -> dict[str, Any]:
    return {"_type": msg.TYPE, "_v": msg.VERSION, **msg.to_wire()}


def field_error(wire: Any, limits: Limits = DEFAULT_LIMITS) -> ProtocolError:
    data = wire if isinstance(wire, bytes) else pack(wire)
    with pytest.raises(ProtocolError) as ei:
        decode(data, limits)
    assert isinstance(ei.value, ValueError)
    return ei.value


def names(err: ProtocolError, path: str) -> bool:
    """Whether the error is about ``path`` or something inside it."""
    return err.field == path or err.field.startswith((path + ".", path + "["))


def sample(type_name: str, seed: int = SEED) -> Message:
    return GENERATORS[type_name](np.random.default_rng(seed))


def episode(
    *, images: bool = False, augmented: bool = False, min_T: int = 1, min_S: int = 1, min_P: int = 1
) -> Episode:
    """A valid episode with at least the given sizes (deterministic)."""
    rng = np.random.default_rng(SEED)
    while True:
        ep = gen_episode(rng, images=images, augmented=augmented)
        _, S, P, _ = ep.points.shape
        if ep.num_steps >= min_T and min_S <= S and min_P <= P:
            return ep


@pytest.mark.parametrize("type_name", real_message_types())
def test_missing_required_field(type_name: str) -> None:
    msg = sample(type_name)
    required = [name for name, _, _, req in codec.field_table(type(msg)) if req]
    assert required
    for name in required:
        wire = wire_of(msg)
        del wire[name]
        assert field_error(wire).field == f"{type_name}.{name}"


@pytest.mark.parametrize("type_name", real_message_types())
def test_unknown_field(type_name: str) -> None:
    wire = wire_of(sample(type_name))
    wire["bogus_field"] = 1
    err = field_error(wire)
    assert err.field == f"{type_name}.bogus_field" and "unknown" in err.problem


def test_type_tags_are_refused_inside_nested_messages() -> None:
    wire = wire_of(episode(augmented=True))
    wire["augmentation"]["_type"] = "Augmentation"
    assert field_error(wire).field == "Episode.augmentation._type"


def test_nested_only_message_cannot_be_sent_alone() -> None:
    data = pack(dict(wire_of(episode(augmented=True))["augmentation"], _type="Augmentation", _v=1))
    with pytest.raises(ProtocolError) as ei:
        decode(data)
    assert ei.value.field == "_type"


def test_unknown_field_in_nested_message() -> None:
    wire = wire_of(episode(augmented=True))
    wire["augmentation"]["extra"] = 0
    assert field_error(wire).field == "Episode.augmentation.extra"


def wrong_values(spec: codec.Spec) -> list[Any]:
    """Values of the wrong type for a spec."""
    if isinstance(spec, Opt):
        return wrong_values(spec.inner)
    if isinstance(spec, Str):
        return [123, b"bytes", None, ["x"]]
    if isinstance(spec, Int):
        return ["1", 1.0, True, None]
    if isinstance(spec, Float):
        return ["1.0", None, [1.0], math.nan, math.inf, -math.inf]
    if isinstance(spec, Bool):
        return [1, 0, "true", None]
    if isinstance(spec, Arr):
        return [[1.0, 2.0], b"\0\0\0\0", 1.0, None, np.zeros(3, np.float64)]
    if isinstance(spec, MapOf):
        return [[], "x", None, {"bad key!": None}]
    if isinstance(spec, ListOf):
        return [{}, "x", None]
    if isinstance(spec, Nested):
        return [5, "x", []]
    raise NotImplementedError(spec)


@pytest.mark.parametrize("type_name", real_message_types())
def test_wrong_type_names_the_field(type_name: str) -> None:
    msg = sample(type_name)
    for f in msg.fields():
        spec = f.metadata["spec"]
        for bad in wrong_values(spec):
            if bad is None and isinstance(spec, Opt):
                continue
            wire = wire_of(msg)
            wire[f.name] = bad
            err = field_error(wire)
            assert names(err, f"{type_name}.{f.name}"), (f.name, bad, err)


@pytest.mark.parametrize(
    ("type_name", "name", "bad"),
    [
        ("Episode", "task", "block_push"),
        ("Episode", "episode_id", "has space"),
        ("Episode", "episode_id", "x" * 97),
        ("Episode", "episode_id", ""),
        ("Episode", "seed", -1),
        ("Episode", "seed", 2**64 - 1),
        ("Episode", "policy_version", -2),
        ("Episode", "created_at", -0.5),
        ("Heartbeat", "pid", 2**31 + 1),
        ("Heartbeat", "detail", "x" * 513),
        ("Heartbeat", "counters", {"ok": 1.0, "not ok": 2.0}),
        ("Heartbeat", "counters", {"x": math.nan}),
        ("EvalReport", "success_rate", 1.0000001),
        ("EvalReport", "episodes", 0),
        ("WeightsAnnouncement", "digest", "A" * 64),
        ("WeightsAnnouncement", "digest", "0" * 63),
        ("WeightsBlob", "tensors", {"bad name!": np.zeros(1, np.float32)}),
        ("WeightsBlob", "tensors", {"x": np.zeros(1, np.float64)}),
    ],
)
def test_out_of_range_values(type_name: str, name: str, bad: Any) -> None:
    wire = wire_of(sample(type_name))
    wire[name] = bad
    assert names(field_error(wire), f"{type_name}.{name}")


@pytest.mark.parametrize("bad", [{"r": np.zeros((1, 1), np.float32)}, {"r": np.array([np.nan], np.float32)}])
def test_bad_augmentation_params_are_named(bad: Any) -> None:
    wire = wire_of(episode(augmented=True))
    wire["augmentation"]["params"] = bad
    assert names(field_error(wire), "Episode.augmentation.params")


def test_strings_capped_by_limits() -> None:
    wire = wire_of(sample("Heartbeat"))
    wire["instance_id"] = "a" * 50
    decode(pack(wire), Limits(max_string=50))
    assert field_error(wire, Limits(max_string=49)).field == "Heartbeat.instance_id"


def episode_wire(**kw: Any) -> dict[str, Any]:
    wire = wire_of(episode(**kw))
    for k, v in wire.items():
        if isinstance(v, np.ndarray):
            wire[k] = v.copy()
    return wire


@pytest.mark.parametrize(
    "name", ["points", "jaw", "actions", "rewards", "gripper_pose", "object_poses", "images"]
)
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_in_finite_arrays(name: str, bad: float) -> None:
    wire = episode_wire(images=True, min_S=2)
    arr = wire[name].astype(np.float32) if name == "images" else wire[name]
    arr.reshape(-1)[arr.size // 2] = bad
    wire[name] = arr
    assert field_error(wire).field == f"Episode.{name}"


@pytest.mark.parametrize("bad", [1.0001, -1.0001, 2.0, -50.0])
def test_action_out_of_bounds(bad: float) -> None:
    wire = episode_wire()
    wire["actions"][-1, -1] = bad
    err = field_error(wire)
    assert err.field == "Episode.actions"


@pytest.mark.parametrize("bad", [-0.01, 1.01])
def test_jaw_out_of_bounds(bad: float) -> None:
    wire = episode_wire()
    wire["jaw"][0] = bad
    assert field_error(wire).field == "Episode.jaw"


def grow(a: np.ndarray, axis: int, by: int) -> np.ndarray:
    """``a`` with ``by`` rows added (by > 0) or removed (by < 0) along ``axis``."""
    if by < 0:
        return np.take(a, range(a.shape[axis] + by), axis=axis)
    pad = np.take(a, [0] * by, axis=axis)
    return np.concatenate([a, pad], axis=axis)


@pytest.mark.parametrize(
    ("name", "axis", "by"),
    [
        ("actions", 0, +1),  # T+2 rows of actions for T+1 observations
        ("actions", 0, -1),
        ("rewards", 0, +1),
        ("terminated", 0, -1),
        ("truncated", 0, +1),
        ("jaw", 0, -1),
        ("point_counts", 0, +1),
        ("gripper_pose", 0, +1),
        ("object_poses", 0, -1),
        ("contacts", 0, +1),
        ("images", 0, +1),
        ("point_counts", 1, +1),  # S segments
        ("contacts", 1, +1),  # S-1 objects, as in object_poses
        ("object_poses", 1, -1),  # S-1 is tied to the S of points
        ("actions", 1, +1),  # fixed dims
        ("gripper_pose", 1, -1),
        ("points", 3, +1),
    ],
)
def test_inconsistent_step_counts(name: str, axis: int, by: int) -> None:
    wire = episode_wire(images=True, min_T=2, min_S=2)
    wire[name] = grow(wire[name], axis, by)
    err = field_error(wire)
    assert err.field == f"Episode.{name}", err


def test_objects_axis_must_be_one_fewer_than_segments() -> None:
    wire = episode_wire(min_S=3)
    wire["object_poses"] = grow(wire["object_poses"], 1, +1)
    wire["contacts"] = grow(wire["contacts"], 1, +1)
    assert field_error(wire).field == "Episode.object_poses"


def test_points_bind_the_step_count() -> None:
    # points come first: with one more observation row everything after it is inconsistent
    wire = episode_wire(min_T=2)
    wire["points"] = grow(wire["points"], 0, +1)
    assert field_error(wire).field == "Episode.point_counts"


def test_episode_needs_a_step() -> None:
    wire = episode_wire()
    for name in ("points", "point_counts", "jaw", "gripper_pose", "object_poses", "contacts"):
        wire[name] = wire[name][:1]
    for name in ("actions", "rewards", "terminated", "truncated"):
        wire[name] = wire[name][:0]
    assert field_error(wire).field == "Episode.actions"
    wire["points"] = wire["points"][:0]
    assert field_error(wire).field == "Episode.points"


@pytest.mark.parametrize("flag", ["terminated", "truncated"])
def test_end_flag_on_a_non_final_step(flag: str) -> None:
    wire = episode_wire(min_T=2)
    wire[flag][0] = True
    assert field_error(wire).field == "Episode.terminated"


def test_neither_flag_on_the_last_step() -> None:
    wire = episode_wire()
    wire["terminated"][:] = False
    wire["truncated"][:] = False
    assert field_error(wire).field == "Episode.terminated"


def test_both_flags_on_the_last_step() -> None:
    wire = episode_wire()
    wire["terminated"][-1] = True
    wire["truncated"][-1] = True
    assert field_error(wire).field == "Episode.truncated"


@pytest.mark.parametrize(
    ("segments", "field"),
    [
        (["object_0", "gripper"], "Episode.segments"),  # gripper must come first
        (["gripper", "gripper"], "Episode.segments"),  # unique
        (["gripper"], "Episode.segments"),  # one name per point segment (S = 2)
        (["gripper", "a", "b"], "Episode.segments"),
        (["gripper", "Object-0"], "Episode.segments[1]"),  # [a-z0-9_]{1,32}
        (["gripper", ""], "Episode.segments[1]"),
        (["gripper", "x" * 33], "Episode.segments[1]"),
        (["gripper", 7], "Episode.segments[1]"),
        (["gripper"] + [f"o{i}" for i in range(16)], "Episode.segments"),  # at most 16
    ],
)
def test_bad_segment_names(segments: list[Any], field: str) -> None:
    wire = episode_wire(min_S=2)
    for name in ("points", "point_counts"):
        wire[name] = wire[name][:, :2]
    for name in ("object_poses", "contacts"):
        wire[name] = wire[name][:, :1]
    wire["segments"] = ["gripper", "object_0"]
    decode(pack(wire))  # the S = 2 episode itself is valid
    wire["segments"] = segments
    assert field_error(wire).field == field


def test_fixed_object_names_one_of_the_objects_or_none() -> None:
    wire = episode_wire(min_S=3)
    n_objects = len(wire["segments"]) - 1
    for ok in (-1, 0, n_objects - 1):
        wire["fixed_object"] = ok
        assert decode(pack(wire)).fixed_object == ok
    for bad in (n_objects, -2, 16):
        wire["fixed_object"] = bad
        assert field_error(wire).field == "Episode.fixed_object", bad
    del wire["fixed_object"]
    assert decode(pack(wire)).fixed_object == -1  # producers that do not know it leave it out


def test_negative_point_count() -> None:
    wire = episode_wire()
    wire["point_counts"][0, 0] = -1
    assert field_error(wire).field == "Episode.point_counts"


def test_wrong_dtype_refused() -> None:
    wire = episode_wire()
    wire["points"] = wire["points"].astype(np.float64)
    assert field_error(wire).field == "Episode.points"
    wire = episode_wire()
    wire["point_counts"] = wire["point_counts"].astype(np.int64)
    assert field_error(wire).field == "Episode.point_counts"


def test_phase_split_beyond_last_step() -> None:
    wire = episode_wire(augmented=True)
    wire["augmentation"]["phase_split"] = len(wire["actions"]) + 1
    assert field_error(wire).field == "Episode.augmentation.phase_split"
    wire["augmentation"]["kind"] = "rotate"
    assert field_error(wire).field == "Episode.augmentation.kind"


@pytest.mark.parametrize(
    "arr",
    [
        np.array([object(), None], dtype=object),
        np.array(["ab", "c"]),
        np.zeros(2, np.complex64),
        np.zeros(2, "datetime64[s]"),
        np.zeros(2, [("a", "<f4")]),
    ],
    ids=["object", "unicode", "complex", "datetime", "structured"],
)
def test_unsendable_dtype_refused_at_encode(arr: np.ndarray) -> None:
    ep = gen_episode(np.random.default_rng(SEED))
    with pytest.raises(TypeError):
        dataclasses.replace(ep, points=arr).encode()
    with pytest.raises(TypeError):
        pack({"x": arr})


def ext(dtype: Any, shape: Any, data: Any) -> msgpack.ExtType:
    return msgpack.ExtType(EXT_NDARRAY, msgpack.packb([dtype, shape, data], use_bin_type=True))


@pytest.mark.parametrize(
    "payload",
    [
        ext(">f4", [1], b"\0\0\x80\x3f"),  # big-endian
        ext(">i8", [1], b"\0" * 8),
        ext("|O", [1], b"\0" * 8),  # object
        ext("<U1", [1], b"\0" * 4),
        ext("<c8", [1], b"\0" * 8),
        ext("float32", [1], b"\0" * 4),  # numpy name instead of the wire string
        ext("<f4", [2], b"\0" * 4),  # data shorter than the shape says
        ext("<f4", [1], b"\0" * 5),
        ext("<f4", [-1], b""),
        ext("<f4", [True], b"\0" * 4),
        ext("<f4", [1.0], b"\0" * 4),
        ext("<f4", [1] * 7, b"\0" * 4),  # over max_ndim
        ext("<f4", (1,), "\0\0\0\0"),  # data must be bin, not str
        ext("<f4", 1, b"\0" * 4),
        ext(4, [1], b"\0" * 4),
        msgpack.ExtType(EXT_NDARRAY, msgpack.packb(["<f4", [1]])),
        msgpack.ExtType(EXT_NDARRAY, msgpack.packb({"dtype": "<f4"})),
        msgpack.ExtType(EXT_NDARRAY, b"\xc1"),
        msgpack.ExtType(EXT_NDARRAY, b""),
    ],
)
def test_bad_ndarray_on_the_wire(payload: msgpack.ExtType) -> None:
    wire = episode_wire()
    wire["rewards"] = payload
    assert field_error(wire).field == "<ndarray>"


def test_unknown_extension_type() -> None:
    wire = episode_wire()
    wire["rewards"] = msgpack.ExtType(2, b"\0")
    assert field_error(wire).field == "<ext>"


@pytest.mark.parametrize("bad", ["Episod", "", "episode", None, 1, b"Episode", ["Episode"]])
def test_unknown_type(bad: Any) -> None:
    wire = wire_of(sample("Heartbeat"))
    wire["_type"] = bad
    assert field_error(wire).field == "_type"
    del wire["_type"]
    assert field_error(wire).field == "_type"


@pytest.mark.parametrize("type_name", real_message_types())
def test_unsupported_version(type_name: str) -> None:
    msg = sample(type_name)
    for bad in (
        msg.VERSION + 1,
        msg.VERSION - 1,
        -1,
        2**63,
        str(msg.VERSION),
        float(msg.VERSION),
        True,
        None,
    ):
        if bad in type(msg).OLDER_READABLE:
            continue  # read as the current version (test_an_episode_recorded_before_fixed_object_...)
        wire = wire_of(msg)
        wire["_v"] = bad
        assert field_error(wire).field == "_v", bad
    wire = wire_of(msg)
    del wire["_v"]
    assert field_error(wire).field == "_v"


def test_an_episode_recorded_before_fixed_object_reads_as_the_current_version() -> None:
    wire = episode_wire()
    wire["_v"] = 1
    wire.pop("fixed_object", None)
    ep = decode(pack(wire))
    assert isinstance(ep, Episode) and ep.fixed_object == -1
    assert unpack(ep.encode(), DEFAULT_LIMITS)["_v"] == Episode.VERSION  # written back as the current one
    wire["fixed_object"] = 0  # a field that version did not have
    assert field_error(wire).field == "Episode.fixed_object"
    wire["_v"] = 0
    assert field_error(wire).field == "_v"


@pytest.mark.parametrize("data", [pack([1, 2]), pack("Episode"), pack(None), pack(1), b"", b"\x80\x00"])
def test_top_level_must_be_one_map(data: bytes) -> None:
    assert field_error(data).field == "<message>"


def test_non_bytes_input() -> None:
    with pytest.raises(ProtocolError) as ei:
        decode("not bytes")  # type: ignore[arg-type]
    assert ei.value.field == "<message>"


def test_trailing_bytes_refused() -> None:
    data = sample("Heartbeat").encode()
    decode(data)
    assert field_error(data + b"\xc0").field == "<message>"


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


def test_message_over_max_message_bytes() -> None:
    data = sample("Episode").encode()
    decode(data, Limits(max_message_bytes=len(data)))
    err = field_error(data, Limits(max_message_bytes=len(data) - 1))
    assert err.field == "<message>" and "over cap" in err.problem


def test_array_over_max_array_bytes() -> None:
    ep = episode()
    data = ep.encode()
    biggest = max(
        getattr(ep, f.name).nbytes for f in ep.fields() if isinstance(getattr(ep, f.name), np.ndarray)
    )
    decode(data, Limits(max_array_bytes=biggest))
    err = field_error(data, Limits(max_array_bytes=biggest - 1))
    assert err.field == "<ndarray>" and "over cap" in err.problem


def test_array_over_max_ndim() -> None:
    blob = WeightsBlob.create(1, "rsac", "r", {"x": np.zeros((1,) * 6, np.float32)})
    data = blob.encode()
    decode(data)
    assert field_error(data, Limits(max_ndim=5)).field == "<ndarray>"


def nested(depth: int) -> Any:
    value: Any = 0
    for _ in range(depth):
        value = [value]
    return value


def test_nesting_over_max_depth() -> None:
    limits = Limits(max_depth=10)
    unpack(pack(nested(10)), limits)
    with pytest.raises(ProtocolError) as ei:
        unpack(pack(nested(11)), limits)
    assert ei.value.field == "<message>" and "deeper" in ei.value.problem
    wire = wire_of(sample("Heartbeat"))
    wire["counters"] = {"x": nested(40)}
    err = field_error(wire)
    assert err.field == "<message>" and "deeper" in err.problem
    # within the depth limit the same value is refused by the field check instead
    wire["counters"] = {"x": nested(3)}
    assert field_error(wire).field == "Heartbeat.counters.x"


def test_entries_over_max_entries() -> None:
    hb = sample("Heartbeat")
    wire = wire_of(hb)
    wire["counters"] = {f"k{i}": float(i) for i in range(12)}
    decode(pack(wire), Limits(max_entries=12))
    field_error(wire, Limits(max_entries=11))
    with pytest.raises(ProtocolError) as ei:
        MapOf(Float()).check("m", wire["counters"], {}, Limits(max_entries=11))
    assert ei.value.field == "m"
    with pytest.raises(ProtocolError) as ei:
        ListOf(Int(), max_len=2).check("l", [1, 2, 3], {}, DEFAULT_LIMITS)
    assert ei.value.field == "l"
