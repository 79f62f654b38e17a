"""JSON Schemas generated from the message specs: well-formed, deterministic, faithful to the specs,
and in agreement with the codec on real (decoded) samples and on invalid ones.

Uses the ``jsonschema`` package when it is installed; otherwise a small validator below that
implements exactly the keywords the generator emits (a test checks that no other keyword appears).
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import json
import math
import pkgutil
import re
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

import proto
from proto.codec import Message, decode, field_table
from proto.control import EpisodeAck, Heartbeat
from proto.episode import Augmentation, Episode
from proto.inference import ActReply, ActRequest, EStop, ResetReply, ResetRequest
from proto.jsonschema import DIALECT, NDARRAY_KEYWORD, json_schema, json_schema_text
from proto.msgpack_wire import ProtocolError, pack
from proto.specs import Arr, Opt
from proto.weights import WeightsBlob
from tests.helpers import build_episode, build_weights
from tests.helpers.wire_samples import fixed_eval_report, fixed_heartbeat, fixed_replay_gate

for _mod in pkgutil.iter_modules(proto.__path__):
    importlib.import_module(f"proto.{_mod.name}")

try:  # optional: not a dependency of the project
    import jsonschema as _jsonschema_lib
except ImportError:  # pragma: no cover - depends on the environment
    _jsonschema_lib = None

pytestmark = pytest.mark.contract


# --------------------------------------------------------------------------------------------
# Samples: one or more valid instances of every registered proto message type
# --------------------------------------------------------------------------------------------


def _augmentation() -> Augmentation:
    return Augmentation(
        source_episode_id="actor-0-1-0",
        kind="mea+isometric",
        seed=2**40,
        copy_index=3,
        phase_split=2,
        params={
            "rotation": np.array([0.5]),
            "delta_r": np.zeros(2, np.float32),
            "k": np.array([1], np.int64),
        },
    )


def _act_request(step: int = 0, **obs: Any) -> ActRequest:
    return ActRequest(session="robot-0", episode=1, step=step, stamp=1_700_000_000.25,
                      state=np.array([0.5, 0.0, 0.12, 0.3, 1.0], np.float32), **obs)  # fmt: skip


def _act_reply(held: bool) -> ActReply:
    action = np.array([1.0, 0, 0, 0, 0] if held else [-1.0, 0.5, -0.25, 0.0, 1.0], np.float32)
    return ActReply(session="robot-0", episode=1, step=4, action=action, policy_version=-1 if held else 7,
                    held=held, reasons=["estop"] if held else [], compute_seconds=0.004)  # fmt: skip


SAMPLES: dict[str, Callable[[], list[Message]]] = {
    "Augmentation": lambda: [_augmentation()],
    "Episode": lambda: [
        build_episode(T=3, seed=1),
        build_episode(T=2, seed=2, truncated=True, with_images=True, image_shape=(1, 4, 4)),
        build_episode(T=4, seed=3, augmentation=_augmentation()),
    ],
    "EvalReport": lambda: [fixed_eval_report()],
    "ReplayGate": lambda: [fixed_replay_gate()],
    "EpisodeAck": lambda: [
        EpisodeAck(learner_id="learner-0", run_id="run-0", episode_ids=[], created_at=1_700_000_000.0),
        EpisodeAck(
            learner_id="learner-0",
            run_id="run-0",
            episode_ids=["actor-0-0-0", "actor-1-1000000-3"],
            created_at=1_700_000_000.0,
        ),
    ],
    "Heartbeat": lambda: [fixed_heartbeat(), fixed_heartbeat(counters={}, detail="x" * 512)],
    "WeightsAnnouncement": lambda: [build_weights(1).announcement(byte_size=123)],
    "WeightsBlob": lambda: [build_weights(2, nbytes=1024)],
    "ResetRequest": lambda: [
        ResetRequest(session="robot-0", task="surgical_grasp_any", created_at=1_700_000_000.0)
    ],
    "ResetReply": lambda: [
        ResetReply(
            session="robot-0",
            accepted=True,
            reason="",
            episode=1,
            policy_version=7,
            run_id="run-0",
            observation="voxel",
        ),
        ResetReply(
            session="robot-0",
            accepted=False,
            reason="no weights yet",
            episode=0,
            policy_version=-1,
            run_id="",
            observation="",
        ),
    ],
    "ActRequest": lambda: [
        _act_request(points=np.zeros((3, 8, 3), np.float32), point_counts=np.array([8, 0, 20], np.int32)),
        _act_request(
            step=4,
            executed=np.array([1.0, 0.2, 0, 0, -0.5], np.float32),
            image=np.zeros((2, 84, 84), np.uint8),
        ),
        dataclasses.replace(
            _act_request(step=5, image=np.zeros((3, 64, 64), np.uint8)),
            state=np.array([np.nan, 0, np.inf, 0, 2.0], np.float32),
        ),  # not range-checked on the wire: the server answers with a hold
    ],
    "ActReply": lambda: [_act_reply(held=False), _act_reply(held=True)],
    "EStop": lambda: [
        EStop(operator_id="operator-0", engaged=True, created_at=1_700_000_000.0, reason="cable caught"),
        EStop(operator_id="operator-0", engaged=False, created_at=1_700_000_010.0),
    ],
}

PROTO_TYPES = sorted(
    (cls for cls in Message._REGISTRY.values() if cls.__module__.startswith("proto.")), key=lambda c: c.TYPE
)


def decoded_samples(cls: type[Message]) -> list[Message]:
    """The samples after a trip through the codec (what a consumer actually holds)."""
    out = []
    for msg in SAMPLES[cls.TYPE]():
        assert type(msg) is cls
        out.append(cls.from_wire(msg.to_wire()) if cls.NESTED_ONLY else decode(msg.encode()))
    return out


def as_json_document(msg: Message) -> dict[str, Any]:
    """The message's wire map as JSON would see it: tags for top-level types, ndarrays as ``{}``."""

    def conv(v: Any) -> Any:
        if isinstance(v, np.ndarray):
            return {}  # msgpack ext type 1: opaque to JSON, described by x-mea-ndarray
        if isinstance(v, Message):
            return conv(v.to_wire())
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        if isinstance(v, list):
            return [conv(x) for x in v]
        return v

    doc = {} if msg.NESTED_ONLY else {"_type": msg.TYPE, "_v": msg.VERSION}
    doc.update(conv(msg.to_wire()))
    # the document must survive JSON itself
    return json.loads(json.dumps(doc, allow_nan=False))


# --------------------------------------------------------------------------------------------
# A minimal draft 2020-12 validator for the keywords the generator emits
# --------------------------------------------------------------------------------------------

ANNOTATIONS = {"$schema", "$id", "title", "description", "default", "x-mea-message", NDARRAY_KEYWORD}
ASSERTIONS = {
    "type",
    "const",
    "enum",
    "pattern",
    "maxLength",
    "minimum",
    "maximum",
    "properties",
    "required",
    "additionalProperties",
    "propertyNames",
    "items",
    "maxItems",
    "anyOf",
}
JSON_TYPES = {"object", "array", "string", "integer", "number", "boolean", "null"}


def _json_type_ok(value: Any, t: str) -> bool:
    return {
        "object": isinstance(value, dict),
        "array": isinstance(value, list),
        "string": isinstance(value, str),
        "integer": type(value) is int or (type(value) is float and value.is_integer()),
        "number": type(value) in (int, float),
        "boolean": type(value) is bool,
        "null": value is None,
    }[t]


def _json_equal(a: Any, b: Any) -> bool:
    # JSON equality: true is not 1
    return type(a) is type(b) and a == b if isinstance(a, bool) or isinstance(b, bool) else a == b


def mini_errors(inst: Any, schema: dict[str, Any], path: str = "$") -> list[str]:  # noqa: C901
    errs: list[str] = []
    if "type" in schema and not _json_type_ok(inst, schema["type"]):
        return [f"{path}: not of type {schema['type']}"]
    if "const" in schema and not _json_equal(inst, schema["const"]):
        errs.append(f"{path}: != const {schema['const']!r}")
    if "enum" in schema and not any(_json_equal(inst, e) for e in schema["enum"]):
        errs.append(f"{path}: not in enum")
    if isinstance(inst, str):
        if "pattern" in schema and not re.search(schema["pattern"], inst):
            errs.append(f"{path}: does not match {schema['pattern']}")
        if "maxLength" in schema and len(inst) > schema["maxLength"]:
            errs.append(f"{path}: too long")
    if type(inst) in (int, float):
        if "minimum" in schema and inst < schema["minimum"]:
            errs.append(f"{path}: below minimum")
        if "maximum" in schema and inst > schema["maximum"]:
            errs.append(f"{path}: above maximum")
    if isinstance(inst, dict):
        props = schema.get("properties", {})
        errs += [f"{path}: missing {k}" for k in schema.get("required", []) if k not in inst]
        for k, v in inst.items():
            if "propertyNames" in schema:
                errs += mini_errors(k, schema["propertyNames"], f"{path}.<key {k}>")
            if k in props:
                errs += mini_errors(v, props[k], f"{path}.{k}")
            elif schema.get("additionalProperties") is False:
                errs.append(f"{path}: unexpected {k}")
            elif isinstance(schema.get("additionalProperties"), dict):
                errs += mini_errors(v, schema["additionalProperties"], f"{path}.{k}")
    if isinstance(inst, list):
        if "maxItems" in schema and len(inst) > schema["maxItems"]:
            errs.append(f"{path}: too many items")
        if "items" in schema:
            for i, v in enumerate(inst):
                errs += mini_errors(v, schema["items"], f"{path}[{i}]")
    if "anyOf" in schema and all(mini_errors(inst, s, path) for s in schema["anyOf"]):
        errs.append(f"{path}: matches no anyOf branch")
    return errs


def schema_errors(inst: Any, schema: dict[str, Any]) -> list[str]:
    if _jsonschema_lib is not None:  # pragma: no cover - depends on the environment
        validator = _jsonschema_lib.Draft202012Validator(schema)
        return [e.message for e in validator.iter_errors(inst)]
    return mini_errors(inst, schema)


def walk(schema: Any, path: str = "$"):
    """Every subschema with its path."""
    yield path, schema
    for key in ("properties",):
        for name, sub in schema.get(key, {}).items():
            yield from walk(sub, f"{path}.properties.{name}")
    for key in ("items", "additionalProperties", "propertyNames"):
        if isinstance(schema.get(key), dict):
            yield from walk(schema[key], f"{path}.{key}")
    for i, sub in enumerate(schema.get("anyOf", [])):
        yield from walk(sub, f"{path}.anyOf[{i}]")


# --------------------------------------------------------------------------------------------
# Tests
# --------------------------------------------------------------------------------------------


def test_every_registered_type_has_samples():
    assert PROTO_TYPES, "no message types registered"
    assert {c.TYPE for c in PROTO_TYPES} == set(SAMPLES)


@pytest.mark.parametrize("cls", PROTO_TYPES, ids=lambda c: c.TYPE)
def test_schema_is_well_formed(cls):
    schema = json_schema(cls)
    assert schema["$schema"] == DIALECT == "https://json-schema.org/draft/2020-12/schema"
    assert schema["type"] == "object" and schema["title"] == cls.TYPE and schema["description"]
    if _jsonschema_lib is not None:  # pragma: no cover - depends on the environment
        _jsonschema_lib.Draft202012Validator.check_schema(schema)
    for path, sub in walk(schema):
        assert isinstance(sub, dict), path
        unknown = set(sub) - ANNOTATIONS - ASSERTIONS
        assert not unknown, f"{path}: keywords {unknown} (teach the validator here)"
        if "type" in sub:
            assert sub["type"] in JSON_TYPES, path
        if "pattern" in sub:
            re.compile(sub["pattern"])
            assert sub["pattern"].startswith("^") and sub["pattern"].endswith("$"), path
        if "required" in sub:
            assert len(set(sub["required"])) == len(sub["required"]), path
            assert set(sub["required"]) <= set(sub.get("properties", {})), path
        if "properties" in sub:
            assert sub.get("additionalProperties") is False, f"{path}: messages refuse unknown fields"
        for bound in ("minimum", "maximum", "maxLength", "maxItems"):
            if bound in sub:
                assert type(sub[bound]) in (int, float) and math.isfinite(sub[bound]), path
        if NDARRAY_KEYWORD in sub:
            assert sub["type"] == "object" and "msgpack ext type 1 ndarray" in sub["description"]


@pytest.mark.parametrize("cls", PROTO_TYPES, ids=lambda c: c.TYPE)
def test_schema_is_deterministic_json(cls):
    text = json_schema_text(cls)
    assert text == json_schema_text(cls)
    assert json.loads(text) == json_schema(cls)
    assert json_schema(cls) is not json_schema(cls)  # fresh dicts: callers may mutate them


@pytest.mark.parametrize("cls", PROTO_TYPES, ids=lambda c: c.TYPE)
def test_schema_mirrors_the_field_specs(cls):
    schema = json_schema(cls)
    props = schema["properties"]
    rows = field_table(cls)
    tags = [] if cls.NESTED_ONLY else ["_type", "_v"]
    assert list(props) == tags + [name for name, *_ in rows]
    assert schema["required"] == tags + [name for name, _, _, required in rows if required]
    if not cls.NESTED_ONLY:
        assert props["_type"]["const"] == cls.TYPE and props["_v"]["const"] == cls.VERSION
    for f in cls.fields():
        prop = props[f.name]
        assert prop["description"].startswith(f.metadata["doc"]), f.name
        spec = f.metadata["spec"]
        if isinstance(spec, Opt):
            assert {"type": "null"} in prop["anyOf"], f.name
            assert prop["default"] is None
            spec = spec.inner
            prop = prop["anyOf"][0]
        if isinstance(spec, Arr):
            info = prop[NDARRAY_KEYWORD]
            assert prop["type"] == "object"
            assert info["dtypes"] == list(spec.dtypes)
            assert info["shape"] == list(spec.shape)
            assert info["finite"] is spec.finite
            assert np.dtype(info["wire_dtypes"][0]).name == spec.dtypes[0]


def test_episode_schema_details():
    props = json_schema(Episode)["properties"]
    assert props["points"][NDARRAY_KEYWORD]["shape"] == ["T+1", "S", "P", 3]
    assert props["actions"][NDARRAY_KEYWORD] == {
        "ext_type": 1,
        "dtypes": ["float32"],
        "wire_dtypes": ["<f4"],
        "shape": ["T", 5],
        "finite": True,
        "minimum": -1.0,
        "maximum": 1.0,
    }
    assert props["task"]["enum"] == ["block_pull", "block_pick", "drawer_open", "surgical_grasp_any"]
    assert props["seed"] == {
        "description": "seed passed to the environment's reset",
        "type": "integer",
        "minimum": 0,
        "maximum": 2**63 - 1,
    }
    aug = props["augmentation"]["anyOf"][0]
    assert aug["title"] == "Augmentation" and "_type" not in aug["properties"]
    assert aug["properties"]["params"]["additionalProperties"][NDARRAY_KEYWORD]["shape"] == ["N"]
    assert json_schema(WeightsBlob)["properties"]["tensors"]["additionalProperties"][NDARRAY_KEYWORD][
        "shape"
    ] == ["..."]
    assert json_schema(Heartbeat)["properties"]["detail"]["default"] == ""


def test_serving_schema_details():
    props = json_schema(ActRequest)["properties"]
    state = props["state"][NDARRAY_KEYWORD]
    assert state["shape"] == [5] and state["finite"] is False  # NaN travels; the server holds on it
    assert "minimum" not in state and "maximum" not in state
    for name, shape in [("points", ["S", "P", 3]), ("point_counts", ["S"]), ("image", ["C", "H", "W"])]:
        assert {"type": "null"} in props[name]["anyOf"] and name not in json_schema(ActRequest)["required"]
        assert props[name]["anyOf"][0][NDARRAY_KEYWORD]["shape"] == shape
    assert props["image"]["anyOf"][0][NDARRAY_KEYWORD]["dtypes"] == ["uint8"]
    action = json_schema(ActReply)["properties"]["action"][NDARRAY_KEYWORD]
    assert (action["shape"], action["finite"], action["minimum"], action["maximum"]) == ([5], True, -1.0, 1.0)
    assert json_schema(ResetReply)["properties"]["observation"]["enum"] == ["voxel", "depth", "dsa", ""]
    assert json_schema(EStop)["properties"]["reason"]["default"] == ""


def test_schema_cannot_express_the_one_observation_rule_but_the_codec_enforces_it():
    """JSON Schema sees ndarrays as opaque objects: an ActRequest with no observation passes the schema;
    ``ActRequest.validate`` refuses it on decode."""
    doc = as_json_document(_act_request(image=np.zeros((2, 4, 4), np.uint8)))
    doc["image"] = None
    assert schema_errors(doc, json_schema(ActRequest)) == []
    wire = {**_act_request(image=np.zeros((2, 4, 4), np.uint8)).to_wire(), "image": None}
    with pytest.raises(ProtocolError):
        decode(pack({"_type": "ActRequest", "_v": 1, **wire}))


@pytest.mark.parametrize("cls", PROTO_TYPES, ids=lambda c: c.TYPE)
def test_decoded_samples_validate(cls):
    schema = json_schema(cls)
    for msg in decoded_samples(cls):
        doc = as_json_document(msg)
        assert schema_errors(doc, schema) == []


def _mutations() -> list[tuple[str, Callable[[dict], None]]]:
    def setter(key, value):
        return lambda d: d.__setitem__(key, value)

    return [
        ("bad enum", setter("state", "sleeping")),
        ("bad pattern", setter("instance_id", "has space")),
        ("too long", setter("detail", "x" * 513)),
        ("below minimum", setter("pid", -1)),
        ("above maximum", setter("policy_version", 2**62 + 1)),
        ("str for int", setter("pid", "12")),
        ("bool for int", setter("pid", True)),
        ("float for int", setter("pid", 12.5)),
        ("bool for float", setter("created_at", False)),
        ("bad map key", lambda d: d["counters"].__setitem__("bad key!", 1.0)),
        ("bad map value", lambda d: d["counters"].__setitem__("ok", "1.0")),
        ("unknown field", setter("extra", 1)),
        ("missing field", lambda d: d.pop("state")),
        ("wrong version", setter("_v", 2)),
        ("wrong type tag", setter("_type", "EvalReport")),
    ]


@pytest.mark.parametrize("name,mutate", _mutations(), ids=[n for n, _ in _mutations()])
def test_schema_and_codec_agree_on_invalid_heartbeats(name, mutate):
    schema = json_schema(Heartbeat)
    doc = as_json_document(fixed_heartbeat())
    assert schema_errors(doc, schema) == []
    bad = copy.deepcopy(doc)
    mutate(bad)
    assert schema_errors(bad, schema), f"schema accepts {name}"
    with pytest.raises(ProtocolError):
        decode(pack(bad))


def test_schema_and_codec_agree_on_invalid_episode_fields():
    schema = json_schema(Episode)
    ep = build_episode(T=2, seed=5)
    for field_name, value in [
        ("segments", ["Gripper"]),
        ("segments", ["g"] * 17),
        ("task", "fly"),
        ("augmentation", {"kind": "mea"}),
        ("images", 3),
    ]:
        doc = as_json_document(ep)
        doc[field_name] = value
        assert schema_errors(doc, schema), field_name
        wire = {"_type": "Episode", "_v": Episode.VERSION, **ep.to_wire(), field_name: value}
        with pytest.raises(ProtocolError):
            decode(pack(wire))
