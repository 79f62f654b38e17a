"""Assertions of the codec contract tests: deep message equality, round trips, named field errors."""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
import pytest

from proto.codec import Message, decode
from proto.msgpack_wire import DEFAULT_LIMITS, Limits, ProtocolError, pack


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


def field_error(wire: Any, limits: Limits = DEFAULT_LIMITS) -> ProtocolError:
    data = wire if isinstance(wire, bytes) else pack(wire)
    with pytest.raises(ProtocolError) as ei:
        decode(data, limits)
    assert isinstance(ei.value, ValueError)
    return ei.value


def names(err: ProtocolError, path: str) -> bool:
    """Whether the error is about ``path`` or something inside it."""
    return err.field == path or err.field.startswith((path + ".", path + "["))
