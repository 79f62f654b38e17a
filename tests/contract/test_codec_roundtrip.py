"""Round trips of every registered message type through the codec, bit for bit.

Two generators per message type: a seeded numpy one (:mod:`tests.helpers.wire_samples`) and a
hypothesis strategy (here). ``test_every_registered_type_has_generators`` fails when a message type
is added to the registry without both, so new messages cannot be forgotten here.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from proto.actions import ACTION_DIM
from proto.codec import Message, decode
from proto.control import EpisodeAck, EvalReport, Heartbeat, ReplayGate
from proto.episode import Augmentation, Episode
from proto.inference import STATE_DIM, ActReply, ActRequest, EStop, ResetReply, ResetRequest
from proto.msgpack_wire import ProtocolError, pack
from proto.specs import Arr, Bool, Float, Int, ListOf, MapOf, Opt, Spec, Str
from proto.weights import WeightsAnnouncement, WeightsBlob, tensors_digest
from tests.helpers.wire_asserts import assert_same, check_roundtrip
from tests.helpers.wire_samples import (
    GENERATORS,
    SEED,
    gen_act_request,
    gen_episode,
    gen_heartbeat,
    real_message_types,
)

pytestmark = pytest.mark.contract


HYPOTHESIS = settings(
    max_examples=30,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


# ----------------------------------------------------------------------------------------------
# hypothesis strategies
# ----------------------------------------------------------------------------------------------


def spec_strategy(spec: Spec) -> st.SearchStrategy:
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


def any_float32_arrays(shape: Any) -> st.SearchStrategy:
    """float32 arrays of any values: drawn as floats (NaN and inf included) or as raw bit patterns
    (every NaN payload, signalling ones too); the codec must carry them bit for bit."""
    as_floats = hnp.arrays(np.float32, shape, elements=st.floats(width=32))
    as_bits = hnp.arrays(np.uint32, shape).map(lambda a: a.view(np.float32))
    return as_floats | as_bits


@st.composite
def act_request_strategy(draw: st.DrawFn) -> ActRequest:
    """Exactly one observation (points with point_counts, or an image: ``ActRequest.validate``);
    ``state``, ``executed`` and ``points`` are not range-checked, so any float32 goes."""
    obs: dict[str, Any] = {}
    if draw(st.booleans()):
        S, P = draw(st.integers(1, 4)), draw(st.integers(0, 4))
        obs["points"] = draw(any_float32_arrays((S, P, 3)))
        obs["point_counts"] = draw(hnp.arrays(np.int32, (S,), elements=st.integers(0, 2**31 - 1)))
    else:
        shape = st.tuples(st.integers(1, 3), st.integers(1, 6), st.integers(1, 6))
        obs["image"] = draw(hnp.arrays(np.uint8, shape))
    return draw(
        message_strategy(
            ActRequest,
            state=any_float32_arrays((STATE_DIM,)),
            executed=st.none() | any_float32_arrays((ACTION_DIM,)),
            points=st.just(obs.get("points")),
            point_counts=st.just(obs.get("point_counts")),
            image=st.just(obs.get("image")),
        )
    )


STRATEGIES: dict[str, st.SearchStrategy] = {
    "Augmentation": augmentation_strategy(),
    "Episode": episode_strategy(),
    "WeightsAnnouncement": message_strategy(WeightsAnnouncement),
    "WeightsBlob": weights_blob_strategy(),
    "Heartbeat": message_strategy(Heartbeat),
    "EvalReport": message_strategy(EvalReport),
    "ReplayGate": message_strategy(ReplayGate),
    "EpisodeAck": message_strategy(EpisodeAck),
    "ResetRequest": message_strategy(ResetRequest),
    "ResetReply": message_strategy(ResetReply),
    "ActRequest": act_request_strategy(),
    "ActReply": message_strategy(ActReply, action=finite_arrays("float32", (ACTION_DIM,), -1.0, 1.0)),
    "EStop": message_strategy(EStop),
}


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
        "ResetRequest",
        "ResetReply",
        "ActRequest",
        "ActReply",
        "EStop",
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
    wire = {"_type": "Episode", "_v": Episode.VERSION, **ep.to_wire()}
    del wire["images"], wire["augmentation"]
    out = decode(pack(wire))
    assert out.images is None and out.augmentation is None
    wire["augmentation"] = None
    assert decode(pack(wire)).augmentation is None


def test_field_order_on_the_wire_does_not_matter() -> None:
    ep = gen_episode(np.random.default_rng(SEED), images=True, augmented=True)
    wire = {"_type": "Episode", "_v": Episode.VERSION, **ep.to_wire()}
    shuffled = dict(reversed(list(wire.items())))
    assert_same(decode(pack(shuffled)), ep)


def test_decode_as_the_wrong_class_names_type() -> None:
    data = gen_heartbeat(np.random.default_rng(SEED)).encode()
    with pytest.raises(ProtocolError) as ei:
        Episode.decode(data)
    assert ei.value.field == "_type"


@pytest.mark.parametrize("points", [True, False], ids=["points", "image"])
def test_act_request_variants_roundtrip(points: bool) -> None:
    rng = np.random.default_rng([SEED, points])
    for _ in range(10):
        req = gen_act_request(rng, points=points)
        assert (req.points is not None) == (req.point_counts is not None) == points != (req.image is not None)
        out = check_roundtrip(req)
        assert isinstance(out, ActRequest) and (out.image is None) == points


def test_act_request_state_keeps_nan_and_inf_bit_for_bit() -> None:
    bits = np.array([0x7FC00000, 0xFFC00000, 0x7F800001, 0x7FC0BEEF, 0xFF800000], np.uint32)
    req = ActRequest(session="robot-0", episode=1, step=0, stamp=0.0, state=bits.view(np.float32),
                     image=np.zeros((2, 3, 3), np.uint8))  # fmt: skip
    out = check_roundtrip(req)
    assert np.array_equal(np.asarray(out.state).view(np.uint32), bits)  # payloads and signalling NaN kept
    assert out.executed is None and out.points is None and out.point_counts is None
