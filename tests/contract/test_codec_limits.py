"""Decoding limits: message and array bytes, dimensions, nesting depth and entries are capped."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from proto.codec import decode
from proto.msgpack_wire import DEFAULT_LIMITS, Limits, ProtocolError, pack, unpack
from proto.specs import Float, Int, ListOf, MapOf
from proto.weights import WeightsBlob
from tests.helpers.wire_asserts import field_error
from tests.helpers.wire_samples import episode, sample, wire_of

pytestmark = pytest.mark.contract


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
