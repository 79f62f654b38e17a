"""msgpack wire codec: ndarray extension, strict typed decoding, one error type.

Every message is a msgpack map ``{"_type": str, "_v": int, <fields>...}``. numpy arrays travel as
msgpack extension type 1 whose payload is itself a msgpack array ``[dtype, shape, data]``:
``dtype`` is a numpy type string in little-endian form (``"<f4"``, ``"|u1"``...), ``shape`` a list
of non-negative ints and ``data`` the C-order bytes. Object and big-endian dtypes are refused.

Decoding never trusts the input: sizes are capped before anything is allocated, every field is
checked against its declared spec, and any failure raises :class:`ProtocolError` naming the field.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

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
    """Most entries in any map or list of a message (checked at each msgpack header)."""
    max_depth: int = 32
    """Deepest nesting of maps and lists."""


DEFAULT_LIMITS = Limits()


# --------------------------------------------------------------------------------------------
# Low level: bytes <-> plain Python / numpy values
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# Field specs: each message field declares what it may hold
# --------------------------------------------------------------------------------------------


def _range(lo: float | None, hi: float | None) -> str:
    if lo is None and hi is None:
        return ""
    if hi is None:
        return f", >= {lo}"
    if lo is None:
        return f", <= {hi}"
    return f", in [{lo}, {hi}]"


class Spec:
    """Validates and normalises one decoded field value."""

    def check(self, path: str, value: Any, dims: dict[str, int], limits: Limits) -> Any:
        raise NotImplementedError

    def describe(self) -> str:
        raise NotImplementedError


@dataclass(frozen=True)
class Str(Spec):
    choices: tuple[str, ...] | None = None
    pattern: str | None = None
    max_len: int | None = None

    def check(self, path, value, dims, limits):
        if not isinstance(value, str):
            raise ProtocolError(path, f"expected str, got {type(value).__name__}")
        cap = self.max_len or limits.max_string
        if len(value) > cap:
            raise ProtocolError(path, f"string longer than {cap}")
        if self.choices is not None and value not in self.choices:
            raise ProtocolError(path, f"{value[:64]!r} not one of {list(self.choices)}")
        if self.pattern is not None and not re.fullmatch(self.pattern, value):
            raise ProtocolError(path, f"{value[:64]!r} does not match {self.pattern}")
        return value

    def describe(self):
        if self.choices:
            return "str, one of " + ", ".join(f"`{c}`" for c in self.choices)
        return f"str matching `{self.pattern}`" if self.pattern else "str"


@dataclass(frozen=True)
class Int(Spec):
    lo: int | None = None
    hi: int | None = None

    def check(self, path, value, dims, limits):
        if type(value) is not int:
            raise ProtocolError(path, f"expected int, got {type(value).__name__}")
        if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
            raise ProtocolError(path, f"{value} outside [{self.lo}, {self.hi}]")
        return value

    def describe(self):
        return "int" + _range(self.lo, self.hi)


@dataclass(frozen=True)
class Float(Spec):
    lo: float | None = None
    hi: float | None = None

    def check(self, path, value, dims, limits):
        if type(value) not in (int, float):
            raise ProtocolError(path, f"expected number, got {type(value).__name__}")
        value = float(value)
        if not math.isfinite(value):
            raise ProtocolError(path, "must be finite")
        if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
            raise ProtocolError(path, f"{value} outside [{self.lo}, {self.hi}]")
        return value

    def describe(self):
        return "float64, finite" + _range(self.lo, self.hi)


@dataclass(frozen=True)
class Bool(Spec):
    def check(self, path, value, dims, limits):
        if type(value) is not bool:
            raise ProtocolError(path, f"expected bool, got {type(value).__name__}")
        return value

    def describe(self):
        return "bool"


ANY_SHAPE = ("...",)
Dim = int | str  # an int is fixed; a str names a symbolic dimension, optionally "+k"


def _parse_dim(d: str) -> tuple[str, int]:
    """``"T"`` -> ("T", 0), ``"T+1"`` -> ("T", 1), ``"S-1"`` -> ("S", -1)."""
    m = re.fullmatch(r"([A-Za-z_]\w*)([+-]\d+)?", d)
    if m is None:
        raise ValueError(f"bad symbolic dim {d!r}")
    return m.group(1), int(m.group(2) or 0)


@dataclass(frozen=True)
class Arr(Spec):
    """An ndarray with allowed dtypes and a shape of fixed and symbolic dims.

    Symbolic dims (``"T"``, ``"T+1"``, ``"S"``) are bound by the first array that uses them; every
    later array in the same message must agree, which is how step counts are kept consistent.
    """

    dtypes: tuple[str, ...]
    shape: tuple[Dim, ...]
    finite: bool = False
    lo: float | None = None
    hi: float | None = None

    def check(self, path, value, dims, limits):
        if not isinstance(value, np.ndarray):
            raise ProtocolError(path, f"expected ndarray, got {type(value).__name__}")
        if value.dtype.name not in self.dtypes:
            raise ProtocolError(path, f"dtype {value.dtype.name} not in {list(self.dtypes)}")
        if self.shape != ANY_SHAPE:
            self._check_shape(path, value.shape, dims)
        if value.dtype.kind == "f" and value.size:
            self._check_values(path, value)
        return value

    def _check_shape(self, path: str, shape: tuple[int, ...], dims: dict[str, int]) -> None:
        if len(shape) != len(self.shape):
            raise ProtocolError(path, f"expected {len(self.shape)} dims, got shape {shape}")
        for axis, (want, got) in enumerate(zip(self.shape, shape, strict=True)):
            if isinstance(want, int):
                if got != want:
                    raise ProtocolError(path, f"axis {axis} must be {want}, got {got}")
                continue
            name, off = _parse_dim(want)
            if name in dims:
                if got != dims[name] + off:
                    raise ProtocolError(
                        path, f"axis {axis} is {got}, expected {want}={dims[name] + off} (inconsistent steps)"
                    )
            elif got - off < 0:
                raise ProtocolError(path, f"axis {axis} is {got}, too small for {want}")
            else:
                dims[name] = got - off

    def _check_values(self, path: str, value: np.ndarray) -> None:
        if self.finite and not np.isfinite(value).all():
            raise ProtocolError(path, "contains NaN or inf")
        if self.lo is not None and float(np.nanmin(value)) < self.lo:
            raise ProtocolError(path, f"values below {self.lo}")
        if self.hi is not None and float(np.nanmax(value)) > self.hi:
            raise ProtocolError(path, f"values above {self.hi}")

    def describe(self):
        if self.shape == ANY_SHAPE:
            return f"ndarray {'|'.join(self.dtypes)}, any shape"
        shape = "(" + ", ".join(str(d) for d in self.shape) + ("," if len(self.shape) == 1 else "") + ")"
        extra = ", finite" if self.finite else ""
        extra += _range(self.lo, self.hi)
        return f"ndarray {'|'.join(self.dtypes)} {shape}{extra}"


@dataclass(frozen=True)
class Opt(Spec):
    inner: Spec

    def check(self, path, value, dims, limits):
        return None if value is None else self.inner.check(path, value, dims, limits)

    def describe(self):
        return f"nil or {self.inner.describe()}"


@dataclass(frozen=True)
class MapOf(Spec):
    """A map from str keys (matching ``key_pattern``) to values of one spec."""

    value: Spec
    key_pattern: str = r"[A-Za-z0-9_.:/-]{1,128}"

    def check(self, path, value, dims, limits):
        if not isinstance(value, dict):
            raise ProtocolError(path, f"expected map, got {type(value).__name__}")
        if len(value) > limits.max_entries:
            raise ProtocolError(path, f"more than {limits.max_entries} entries")
        out = {}
        for k, v in value.items():
            if not isinstance(k, str) or not re.fullmatch(self.key_pattern, k):
                raise ProtocolError(path, f"bad key {str(k)[:64]!r}")
            # symbolic dims inside a map are local to each entry
            out[k] = self.value.check(f"{path}.{k}", v, {}, limits)
        return out

    def describe(self):
        return f"map str -> {self.value.describe()}"


@dataclass(frozen=True)
class ListOf(Spec):
    item: Spec
    max_len: int | None = None

    def check(self, path, value, dims, limits):
        if not isinstance(value, list):
            raise ProtocolError(path, f"expected list, got {type(value).__name__}")
        cap = self.max_len or limits.max_entries
        if len(value) > cap:
            raise ProtocolError(path, f"more than {cap} items")
        return [self.item.check(f"{path}[{i}]", v, dims, limits) for i, v in enumerate(value)]

    def describe(self):
        return f"list of {self.item.describe()}"


@dataclass(frozen=True)
class Nested(Spec):
    message: type[Message]

    def check(self, path, value, dims, limits):
        return self.message.from_wire(value, limits, path=path)

    def describe(self):
        return f"map, a `{self.message.TYPE}` without `_type`/`_v`"


def spec(s: Spec, doc: str, default: Any = dataclasses.MISSING) -> Any:
    """Declare a message field with its wire spec and a one-line description."""
    kwargs: dict[str, Any] = {"metadata": {"spec": s, "doc": doc}}
    if default is not dataclasses.MISSING:
        kwargs["default"] = default
    return field(**kwargs)


# --------------------------------------------------------------------------------------------
# Messages
# --------------------------------------------------------------------------------------------


class Message:
    """Base of every wire message: a frozen dataclass whose fields carry specs."""

    TYPE: ClassVar[str]
    VERSION: ClassVar[int]
    NESTED_ONLY: ClassVar[bool] = False  # only ever a field of another message
    OLDER_READABLE: ClassVar[dict[int, frozenset[str]]] = {}
    """Older versions this decoder still reads, each with the optional fields added since: such a
    message is the current version with those fields at their defaults (so recordings stay readable)."""
    _REGISTRY: ClassVar[dict[str, type[Message]]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "TYPE" in cls.__dict__:
            Message._REGISTRY[cls.TYPE] = cls

    # validation hook for cross-field rules; raise ProtocolError
    def validate(self, dims: dict[str, int]) -> None:  # noqa: B027 - optional hook
        pass

    @classmethod
    def fields(cls) -> tuple[dataclasses.Field, ...]:
        return dataclasses.fields(cls)  # type: ignore[arg-type]

    def to_wire(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in self.fields():
            v = getattr(self, f.name)
            out[f.name] = v.to_wire() if isinstance(v, Message) else v
        return out

    @classmethod
    def from_wire(
        cls, obj: Any, limits: Limits = DEFAULT_LIMITS, path: str = "", top_level: bool = False
    ) -> Self:
        where = path or cls.TYPE
        if not isinstance(obj, dict):
            raise ProtocolError(where, f"expected map, got {type(obj).__name__}")
        known = {f.name for f in cls.fields()}
        for k in obj:
            if k not in known and not (top_level and k in ("_type", "_v")):
                raise ProtocolError(f"{where}.{str(k)[:64]}", "unknown field")
        dims: dict[str, int] = {}
        values: dict[str, Any] = {}
        for f in cls.fields():
            fpath = f"{where}.{f.name}"
            if f.name not in obj:
                if f.default is not dataclasses.MISSING:
                    values[f.name] = f.default
                    continue
                raise ProtocolError(fpath, "required field missing")
            values[f.name] = f.metadata["spec"].check(fpath, obj[f.name], dims, limits)
        msg = cls(**values)
        try:
            msg.validate(dims)
        except ProtocolError as e:
            raise ProtocolError(f"{where}.{e.field}", e.problem) from None
        return msg

    def encode(self) -> bytes:
        """Serialise with the type tag and schema version."""
        if self.NESTED_ONLY:
            raise TypeError(f"{self.TYPE} is only sent inside another message")
        wire = {"_type": self.TYPE, "_v": self.VERSION}
        wire.update(self.to_wire())
        return pack(wire)

    @classmethod
    def decode(cls, data: bytes | bytearray | memoryview, limits: Limits = DEFAULT_LIMITS) -> Self:
        """Decode bytes that must hold exactly this message type."""
        msg = decode(data, limits)
        if not isinstance(msg, cls):
            raise ProtocolError("_type", f"expected {cls.TYPE}, got {msg.TYPE}")
        return msg


def decode(data: bytes | bytearray | memoryview, limits: Limits = DEFAULT_LIMITS) -> Message:
    """Decode bytes into whichever registered message type they carry."""
    obj = unpack(data, limits)
    if not isinstance(obj, dict):
        raise ProtocolError("<message>", f"top level must be a map, got {type(obj).__name__}")
    type_name = obj.get("_type")
    cls = Message._REGISTRY.get(type_name) if isinstance(type_name, str) else None
    if cls is None or cls.NESTED_ONLY:
        raise ProtocolError("_type", f"unknown message type {str(type_name)[:64]!r}")
    version = obj.get("_v")
    if type(version) is not int:
        raise ProtocolError("_v", "schema version missing or not an int")
    if version != cls.VERSION and version not in cls.OLDER_READABLE:
        reads = ", ".join(str(v) for v in sorted({cls.VERSION, *cls.OLDER_READABLE}))
        raise ProtocolError("_v", f"{cls.TYPE} schema version {version} not supported (reads {reads})")
    for name in sorted(cls.OLDER_READABLE.get(version, ())):
        if name in obj:
            raise ProtocolError(f"{cls.TYPE}.{name}", f"unknown field in version {version}")
    return cls.from_wire(obj, limits, top_level=True)


def field_table(cls: type[Message]) -> list[tuple[str, str, str, bool]]:
    """(name, type description, doc, required) per field: the source of proto/README.md tables."""
    rows = []
    for f in cls.fields():
        required = f.default is dataclasses.MISSING
        rows.append((f.name, f.metadata["spec"].describe(), f.metadata["doc"], required))
    return rows
