"""JSON Schema (draft 2020-12) documents for wire messages, generated from their field specs.

Design notes: docs/architecture-notes.md, proto/jsonschema.py."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from proto.codec import Message
from proto.msgpack_wire import EXT_NDARRAY, WIRE_DTYPES
from proto.specs import ANY_SHAPE, Arr, Bool, Float, Int, ListOf, MapOf, Nested, Opt, Spec, Str

DIALECT = "https://json-schema.org/draft/2020-12/schema"
NDARRAY_KEYWORD = "x-mea-ndarray"
_NAME_TO_WIRE = {dt.name: wire for wire, dt in WIRE_DTYPES.items()}
_JSON_SCALARS = (type(None), bool, int, float, str)


def _anchored(pattern: str) -> str:
    # JSON Schema patterns search (ECMA-262); the codec uses re.fullmatch.
    return f"^(?:{pattern})$"


def _summary(cls: type[Message]) -> str:
    doc = (cls.__doc__ or "").strip()
    return doc.split("\n\n", 1)[0].replace("\n", " ").strip()


def _ndarray_schema(s: Arr) -> dict[str, Any]:
    info: dict[str, Any] = {
        "ext_type": EXT_NDARRAY,
        "dtypes": list(s.dtypes),
        "wire_dtypes": [_NAME_TO_WIRE[d] for d in s.dtypes],
        "shape": list(ANY_SHAPE) if s.shape == ANY_SHAPE else list(s.shape),
        "finite": s.finite,
    }
    if s.lo is not None:
        info["minimum"] = s.lo
    if s.hi is not None:
        info["maximum"] = s.hi
    return {
        "type": "object",
        "description": f"msgpack ext type {EXT_NDARRAY} {s.describe()}; payload [dtype, shape, C-order bytes]",
        NDARRAY_KEYWORD: info,
    }


def _spec_schema(s: Spec, stack: tuple[type[Message], ...]) -> dict[str, Any]:
    if isinstance(s, Str):
        out: dict[str, Any] = {"type": "string"}
        if s.choices is not None:
            out["enum"] = list(s.choices)
        if s.pattern is not None:
            out["pattern"] = _anchored(s.pattern)
        if s.max_len is not None:
            out["maxLength"] = s.max_len
        return out
    if isinstance(s, Bool):
        return {"type": "boolean"}
    if isinstance(s, (Int, Float)):
        out = {"type": "integer" if isinstance(s, Int) else "number"}
        if s.lo is not None:
            out["minimum"] = s.lo
        if s.hi is not None:
            out["maximum"] = s.hi
        return out
    if isinstance(s, Arr):
        return _ndarray_schema(s)
    if isinstance(s, Opt):
        return {"anyOf": [_spec_schema(s.inner, stack), {"type": "null"}]}
    if isinstance(s, MapOf):
        return {
            "type": "object",
            "propertyNames": {"pattern": _anchored(s.key_pattern)},
            "additionalProperties": _spec_schema(s.value, stack),
        }
    if isinstance(s, ListOf):
        out = {"type": "array", "items": _spec_schema(s.item, stack)}
        if s.max_len is not None:
            out["maxItems"] = s.max_len
        return out
    if isinstance(s, Nested):
        return _object_schema(s.message, stack, top_level=False)
    raise TypeError(f"no JSON Schema mapping for spec {type(s).__name__}")


def _field_schema(f: dataclasses.Field, stack: tuple[type[Message], ...]) -> dict[str, Any]:
    spec, doc = f.metadata["spec"], f.metadata["doc"]
    inner = _spec_schema(spec, stack)
    out: dict[str, Any] = {}
    # the field's doc first; a spec's own description (ndarray, nested message) follows it
    own = inner.pop("description", None)
    out["description"] = f"{doc} ({own})" if own else doc
    out.update(inner)
    if f.default is not dataclasses.MISSING and isinstance(f.default, _JSON_SCALARS):
        out["default"] = f.default
    return out


def _object_schema(cls: type[Message], stack: tuple[type[Message], ...], top_level: bool) -> dict[str, Any]:
    if cls in stack:
        raise ValueError(f"recursive message nesting: {' -> '.join(c.TYPE for c in (*stack, cls))}")
    stack = (*stack, cls)
    props: dict[str, Any] = {}
    required: list[str] = []
    if top_level:
        props["_type"] = {"description": "message type tag", "const": cls.TYPE}
        props["_v"] = {"description": "schema version of the message type", "const": cls.VERSION}
        required += ["_type", "_v"]
    for f in cls.fields():
        props[f.name] = _field_schema(f, stack)
        if f.default is dataclasses.MISSING:
            required.append(f.name)
    out: dict[str, Any] = {
        "title": cls.TYPE,
        "description": _summary(cls)
        if top_level
        else f"a `{cls.TYPE}` (v{cls.VERSION}) without `_type`/`_v`: {_summary(cls)}",
        "type": "object",
        "properties": props,
        "required": required,
        "additionalProperties": False,
    }
    return out


def json_schema(cls: type[Message]) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of message type ``cls``, as a fresh dict.

    A ``NESTED_ONLY`` message (only ever a field of another one) gets the schema of its map without
    ``_type``/``_v``; any other message the schema of the whole encoded map, tags included.
    """
    if not (isinstance(cls, type) and issubclass(cls, Message) and "TYPE" in cls.__dict__):
        raise TypeError(f"{cls!r} is not a registered message type")
    top_level = not cls.NESTED_ONLY
    body = _object_schema(cls, (), top_level=top_level)
    return {
        "$schema": DIALECT,
        "$id": f"urn:mea-rl:proto:{cls.TYPE}:v{cls.VERSION}",
        **body,
        "x-mea-message": {"type": cls.TYPE, "version": cls.VERSION, "nested_only": cls.NESTED_ONLY},
    }


def json_schema_text(cls: type[Message]) -> str:
    """:func:`json_schema` as compact, deterministic JSON text (what MCAP channels embed)."""
    return json.dumps(json_schema(cls), separators=(",", ":"), ensure_ascii=True, allow_nan=False)
