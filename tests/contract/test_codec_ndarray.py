"""The ndarray extension: the documented example bytes, unsendable dtypes, malformed payloads."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

import proto
from proto.msgpack_wire import EXT_NDARRAY, pack, unpack
from tests.helpers.wire_asserts import field_error
from tests.helpers.wire_samples import SEED, episode_wire, gen_episode

pytestmark = pytest.mark.contract


README = Path(proto.__file__).with_name("README.md").read_text(encoding="utf-8")


def test_ndarray_extension_example_bytes() -> None:
    expected = bytes.fromhex("c7 12 01 93 a3 3c 66 34 92 01 02 c4 08 00 00 80 3f 00 00 00 c0")
    assert pack(np.array([[1.0, -2.0]], dtype=np.float32)) == expected
    assert "c4 08 00 00 80 3f 00 00 00 c0" in README
    out = unpack(expected)
    assert out.dtype == np.float32 and out.tolist() == [[1.0, -2.0]]


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
