"""Typed wire messages: the ``{"_type", "_v", <fields>}`` envelope, the type registry and decoding.

Every message is a msgpack map ``{"_type": str, "_v": int, <fields>...}`` (bytes as in
:mod:`proto.msgpack_wire`). A message type is a frozen dataclass subclassing :class:`Message` whose
fields carry specs (:mod:`proto.specs`); defining it registers it for :func:`decode`, which checks
the type tag, the schema version and every field, raising :class:`ProtocolError` naming the field.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Self

from proto.msgpack_wire import DEFAULT_LIMITS, Limits, ProtocolError, pack, unpack


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
