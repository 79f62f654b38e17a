"""Validation failures of every message type name the right field: missing, unknown, mistyped, out of range."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from proto.codec import decode, field_table
from proto.msgpack_wire import Limits, ProtocolError, pack
from proto.specs import Arr, Bool, Float, Int, ListOf, MapOf, Nested, Opt, Spec, Str
from tests.helpers.wire_asserts import field_error, names
from tests.helpers.wire_samples import episode, real_message_types, sample, wire_of

pytestmark = pytest.mark.contract


@pytest.mark.parametrize("type_name", real_message_types())
def test_missing_required_field(type_name: str) -> None:
    msg = sample(type_name)
    required = [name for name, _, _, req in field_table(type(msg)) if req]
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


def wrong_values(spec: Spec) -> list[Any]:
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


@pytest.mark.parametrize(
    ("type_name", "name", "bad"),
    [
        ("ResetRequest", "session", "robot 0"),
        ("ResetRequest", "task", "juggle"),
        ("ResetReply", "observation", "rgb"),
        ("ResetReply", "episode", -1),
        ("ResetReply", "policy_version", -2),
        ("ActRequest", "episode", 0),
        ("ActRequest", "step", 1_000_001),
        ("ActRequest", "stamp", -1.0),
        ("ActRequest", "state", np.zeros(4, np.float32)),
        ("ActRequest", "state", np.zeros(5, np.float64)),
        ("ActRequest", "executed", np.zeros((1, 5), np.float32)),
        ("ActReply", "action", np.array([0, 0, 0, 0, 1.5], np.float32)),
        ("ActReply", "action", np.array([0, 0, 0, 0, np.nan], np.float32)),
        ("ActReply", "reasons", ["Estop"]),
        ("ActReply", "reasons", ["estop"] * 17),
        ("ActReply", "compute_seconds", -0.1),
        ("EStop", "operator_id", ""),
        ("EStop", "reason", "x" * 257),
    ],
)
def test_out_of_range_serving_values(type_name: str, name: str, bad: Any) -> None:
    wire = wire_of(sample(type_name))
    wire[name] = bad
    assert names(field_error(wire), f"{type_name}.{name}")


def _act_wire(**obs: Any) -> dict[str, Any]:
    wire = {"_type": "ActRequest", "_v": 1, "session": "robot-0", "episode": 1, "step": 0, "stamp": 0.0,
            "state": np.zeros(5, np.float32)}  # fmt: skip
    return {**wire, **obs}


@pytest.mark.parametrize(
    ("obs", "field"),
    [
        ({}, "image"),  # no observation
        (
            {
                "points": np.zeros((2, 4, 3), np.float32),
                "point_counts": np.zeros(2, np.int32),
                "image": np.zeros((2, 8, 8), np.uint8),
            },
            "image",
        ),  # both
        ({"points": np.zeros((2, 4, 3), np.float32)}, "points"),  # points without their counts
        ({"point_counts": np.zeros(2, np.int32), "image": np.zeros((2, 8, 8), np.uint8)}, "points"),
        ({"points": np.zeros((2, 4, 3), np.float32), "point_counts": np.zeros(3, np.int32)}, "point_counts"),
    ],
    ids=["none", "both", "points-alone", "counts-alone", "counts-mismatch"],
)
def test_act_request_carries_exactly_one_observation(obs: dict[str, Any], field: str) -> None:
    err = field_error(_act_wire(**obs))
    assert err.field == f"ActRequest.{field}", err


def test_act_request_observations_that_decode() -> None:
    points = {"points": np.zeros((2, 4, 3), np.float32), "point_counts": np.zeros(2, np.int32)}
    assert decode(pack(_act_wire(**points))).image is None
    assert decode(pack(_act_wire(image=np.zeros((2, 84, 84), np.uint8), points=None))).points is None
    nan_state = _act_wire(image=np.zeros((3, 64, 64), np.uint8), state=np.full(5, np.nan, np.float32))
    assert np.isnan(decode(pack(nan_state)).state).all()  # not range-checked: the server answers with a hold
