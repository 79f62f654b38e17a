"""Field specs: what each message field may hold, how a decoded value is checked and described.

Every message field is declared with :func:`spec` (a spec and a one-line description); the decoder
checks each decoded value against its spec (types, ranges, patterns, array dtypes and shapes with
symbolic step dims) and raises :class:`~proto.msgpack_wire.ProtocolError` naming the field. The
same specs generate the field tables of proto/README.md and the JSON Schemas.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from proto.msgpack_wire import Limits, ProtocolError

if TYPE_CHECKING:
    from proto.codec import Message

ID_PATTERN = r"[A-Za-z0-9_.-]{1,96}"
"""Ids of runs, actors, service instances and episodes; also what a key-expression chunk may hold
(:mod:`proto.topics`), since ids travel in keys."""


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
            return "str, one of " + ", ".join(f"`{c}`" if c else '`""`' for c in self.choices)
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
