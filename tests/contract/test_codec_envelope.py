"""The message envelope: type tag, schema version (older readable ones included), one top-level map."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from proto.codec import decode
from proto.episode import Episode
from proto.msgpack_wire import DEFAULT_LIMITS, ProtocolError, pack, unpack
from tests.helpers.wire_asserts import field_error
from tests.helpers.wire_samples import episode_wire, real_message_types, sample, wire_of

pytestmark = pytest.mark.contract


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
    wire.pop("conditions", None)
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


def test_an_episode_recorded_before_conditions_reads_as_the_current_version() -> None:
    wire = episode_wire()
    wire["_v"] = 2
    wire.pop("conditions", None)
    ep = decode(pack(wire))
    assert isinstance(ep, Episode) and ep.conditions is None
    wire["conditions"] = {"randomised": np.array([1])}  # a field version 2 did not have
    assert field_error(wire).field == "Episode.conditions"
