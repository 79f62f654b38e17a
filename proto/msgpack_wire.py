"""msgpack bytes <-> plain Python values and read-only ndarrays: the byte level of every message.

numpy arrays travel as msgpack extension type 1 whose payload is itself a msgpack array
``[dtype, shape, data]``: ``dtype`` is a numpy type string in little-endian form (``"<f4"``,
``"|u1"``...), ``shape`` a list of non-negative ints and ``data`` the C-order bytes. Object and
big-endian dtypes are refused.

Decoding never trusts the input: sizes are capped (:class:`Limits`) before anything is allocated,
and any failure raises :class:`ProtocolError` naming what failed. Typed messages are built on top
of this in :mod:`proto.codec` (envelope, registry) and :mod:`proto.specs` (field checks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

EXT_NDARRAY = 1

# dtype string on the wire -> numpy dtype. Little-endian only, no object/void/str dtypes.
WIRE_DTYPES: dict[str, np.dtype] = {
    s: np.dtype(s)
    for s in ("|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8")
}
_NAME_TO_WIRE = {np.dtype(s).name: s for s in WIRE_DTYPES}


class ProtocolError(ValueError):
    """A message failed to decode or validate; ``field`` names the offending field path."""

    def __init__(self, field_path: str, problem: str) -> None:
        super().__init__(f"{field_path}: {problem}")
        self.field = field_path
        self.problem = problem


@dataclass(frozen=True)
class Limits:
    """Caps applied while decoding untrusted bytes (all configurable per service)."""

    max_message_bytes: int = 256 * 1024 * 1024
    """Largest encoded message accepted, in bytes."""
    max_array_bytes: int = 128 * 1024 * 1024
    """Largest single ndarray payload, in bytes."""
    max_ndim: int = 6
    """Most dimensions an ndarray may have."""
    max_string: int = 1024
    """Longest string field, in characters."""
    max_entries: int = 4096
    """Most entries in any map or list."""
    max_depth: int = 32
    """Deepest nesting of maps and lists."""


DEFAULT_LIMITS = Limits()


def _to_wire(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        wire = wire_dtype(obj)
        # reshape: ascontiguousarray turns a 0-d array into shape (1,), which would not round-trip
        arr = np.ascontiguousarray(obj, dtype=WIRE_DTYPES[wire]).reshape(obj.shape)
        payload = msgpack.packb([wire, list(arr.shape), arr.tobytes()], use_bin_type=True)
        return msgpack.ExtType(EXT_NDARRAY, payload)
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def wire_dtype(arr: np.ndarray) -> str:
    """The wire dtype string for an array, or TypeError if it cannot be sent."""
    wire = _NAME_TO_WIRE.get(arr.dtype.name)
    if wire is None:
        raise TypeError(f"dtype {arr.dtype} cannot be sent (allowed: {sorted(_NAME_TO_WIRE)})")
    return wire


def pack(obj: Any) -> bytes:
    """Encode plain values and ndarrays to msgpack bytes."""
    return msgpack.packb(obj, default=_to_wire, use_bin_type=True, strict_types=False)


def _make_ext_hook(limits: Limits):
    def ext_hook(code: int, payload: bytes) -> Any:
        if code != EXT_NDARRAY:
            raise ProtocolError("<ext>", f"unknown msgpack extension type {code}")
        try:
            # The header is [dtype, shape, data] with at most max_ndim dims: cap array/map headers so
            # forged nested lengths cannot make msgpack preallocate large lists.
            head = msgpack.unpackb(
                payload,
                raw=False,
                strict_map_key=True,
                use_list=True,
                max_array_len=max(3, limits.max_ndim),
                max_map_len=0,
            )
        except Exception as exc:  # noqa: BLE001 - msgpack raises many types
            raise ProtocolError("<ndarray>", f"malformed ndarray header ({type(exc).__name__})") from None
        if not (isinstance(head, list) and len(head) == 3):
            raise ProtocolError("<ndarray>", "header must be [dtype, shape, data]")
        dtype_s, shape, data = head
        if not isinstance(dtype_s, str) or dtype_s not in WIRE_DTYPES:
            raise ProtocolError("<ndarray>", f"dtype {dtype_s!r} not allowed")
        if not isinstance(shape, list) or len(shape) > limits.max_ndim:
            raise ProtocolError("<ndarray>", f"shape must be a list of at most {limits.max_ndim} ints")
        if not all(type(d) is int and d >= 0 for d in shape):
            raise ProtocolError("<ndarray>", "shape entries must be non-negative ints")
        if not isinstance(data, bytes):
            raise ProtocolError("<ndarray>", "data must be bytes")
        dtype = WIRE_DTYPES[dtype_s]
        n = math.prod(shape)
        if n * dtype.itemsize != len(data):
            raise ProtocolError("<ndarray>", f"shape {shape} x {dtype_s} != {len(data)} data bytes")
        if len(data) > limits.max_array_bytes:
            raise ProtocolError("<ndarray>", f"array of {len(data)} bytes over cap {limits.max_array_bytes}")
        # Read-only view over the message buffer: no copy; consumers copy before writing.
        return np.frombuffer(data, dtype=dtype).reshape(shape)

    return ext_hook


def unpack(data: bytes | bytearray | memoryview, limits: Limits = DEFAULT_LIMITS) -> Any:
    """Decode msgpack bytes into plain values and read-only ndarrays, or raise ProtocolError."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("<message>", f"expected bytes, got {type(data).__name__}")
    if len(data) > limits.max_message_bytes:
        raise ProtocolError("<message>", f"{len(data)} bytes over cap {limits.max_message_bytes}")
    try:
        # max_*_len default to len(data): a forged str/bin/ext length cannot allocate more than the
        # message itself holds. Array headers are also capped at max_entries: msgpack preallocates
        # each list it opens, so ~1000 nested forged array headers would otherwise cost up to
        # 1000 x 80 KB from a message of a few KB (now at most ~1024 x max_entries x 8 bytes).
        entries = min(len(data), limits.max_entries)
        obj = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            use_list=True,
            max_array_len=entries,
            max_map_len=entries,
            ext_hook=_make_ext_hook(limits),
        )
    except ProtocolError:
        raise
    except RecursionError:
        raise ProtocolError("<message>", "nested too deeply") from None
    except Exception as exc:  # noqa: BLE001 - msgpack raises ValueError, FormatError, StackError...
        raise ProtocolError("<message>", f"not valid msgpack ({type(exc).__name__}: {exc})"[:300]) from None
    _check_depth(obj, limits.max_depth)
    return obj


def _check_depth(obj: Any, max_depth: int) -> None:
    stack = [(obj, 0)]
    while stack:
        cur, d = stack.pop()
        if d > max_depth:
            raise ProtocolError("<message>", f"nested deeper than {max_depth}")
        if isinstance(cur, dict):
            stack.extend((v, d + 1) for v in cur.values())
        elif isinstance(cur, list):
            stack.extend((v, d + 1) for v in cur)
