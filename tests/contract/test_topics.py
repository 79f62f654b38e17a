"""The topic registry: keys build and parse back, bad chunks are refused, QoS rules, docs in sync."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import proto
from proto import docs, topics
from proto.codec import Message
from proto.control import SERVICES
from proto.inference import ActRequest, ResetRequest
from proto.topics import (
    ALIVE,
    CHUNK,
    EPISODE_ACKS,
    EPISODES_AUGMENTED,
    EPISODES_RAW,
    ESTOP,
    EVAL_REPORTS,
    PREFIX,
    REPLAY_GATE,
    SERVE_ACT,
    SERVE_RESET,
    STATUS,
    TOPICS,
    WEIGHTS_ANNOUNCE,
    WEIGHTS_LATEST,
    Congestion,
    Kind,
    Priority,
    Topic,
    TopicKeyError,
    by_name,
    key,
    may_request,
    may_write,
    parse,
    pattern,
)

pytestmark = pytest.mark.contract

BAD_CHUNKS = ["a/b", "*", "**", "", "$", "$*", "a b", " a", "a ", "a?b", "a#b", "é", "x" * 97, "a\nb", "a\0b"]


def sample_parts(topic: Topic, salt: str = "") -> dict[str, str]:
    return {p: f"{p}-{i}{salt}.x_Y" for i, p in enumerate(topic.placeholders)}


def ids(ts: tuple[Topic, ...] | list[Topic]) -> list[str]:
    return [t.name for t in ts]


@pytest.mark.parametrize("topic", TOPICS, ids=ids(TOPICS))
@pytest.mark.parametrize("namespace", ["default", "run-7", "a", "x" * 96])
def test_every_topic_builds_and_parses_back(topic: Topic, namespace: str) -> None:
    parts = sample_parts(topic)
    k = key(topic, namespace, **parts)
    assert k == f"{PREFIX}/{namespace}/" + topic.path.format(**parts)
    assert k.startswith(f"mea/v1/{namespace}/")
    assert "{" not in k and "*" not in k
    got_topic, got_ns, got_parts = parse(k)
    assert got_topic is topic
    assert got_ns == namespace
    assert got_parts == parts


def test_default_namespace() -> None:
    assert key(EPISODES_RAW, source="actor-0") == "mea/v1/default/episodes/raw/actor-0"
    assert parse("mea/v1/default/status/actor/actor-0") == (
        STATUS,
        "default",
        {"service": "actor", "instance": "actor-0"},
    )


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(
    st.sampled_from(TOPICS),
    st.from_regex(CHUNK, fullmatch=True),
    st.lists(st.from_regex(CHUNK, fullmatch=True), min_size=2, max_size=2),
)
def test_any_valid_chunks_round_trip(topic: Topic, namespace: str, values: list[str]) -> None:
    parts = dict(zip(topic.placeholders, values, strict=False))
    assert parse(key(topic, namespace, **parts)) == (topic, namespace, parts)


def test_topics_are_distinct() -> None:
    assert len({t.name for t in TOPICS}) == len(TOPICS)
    assert len({t.path for t in TOPICS}) == len(TOPICS)
    for t in TOPICS:
        assert by_name(t.name) is t
        # placeholders are whole chunks, and every literal chunk is a valid chunk itself
        for chunk in t.path.split("/"):
            assert re.fullmatch(r"\{\w+\}", chunk) or CHUNK.fullmatch(chunk), (t.name, chunk)
    with pytest.raises(TopicKeyError):
        by_name("nope")


WILDCARD_PATTERNS = [
    (EPISODES_RAW, "default", "mea/v1/default/episodes/raw/*"),
    (EPISODES_AUGMENTED, "ns", "mea/v1/ns/episodes/augmented/*"),
    (WEIGHTS_ANNOUNCE, "default", "mea/v1/default/weights/announce/*"),
    (WEIGHTS_LATEST, "default", "mea/v1/default/weights/latest/*"),
    (EVAL_REPORTS, "default", "mea/v1/default/eval/reports/*"),
    (REPLAY_GATE, "default", "mea/v1/default/learner/gate/*"),
    (EPISODE_ACKS, "default", "mea/v1/default/learner/acks/*"),
    (SERVE_RESET, "default", "mea/v1/default/serve/reset/*"),
    (SERVE_ACT, "cell-2", "mea/v1/cell-2/serve/act/*"),
    (ESTOP, "default", "mea/v1/default/safety/estop/*"),
    (STATUS, "run-1", "mea/v1/run-1/status/*/*"),
    (ALIVE, "default", "mea/v1/default/alive/*/*"),
]


@pytest.mark.parametrize(("topic", "namespace", "expected"), WILDCARD_PATTERNS)
def test_wildcard_pattern(topic: Topic, namespace: str, expected: str) -> None:
    assert pattern(topic, namespace) == expected


def test_every_topic_has_a_pattern_test() -> None:
    covered = {topic for topic, _, _ in WILDCARD_PATTERNS}
    assert set(TOPICS) == covered, "a topic was added: extend test_wildcard_pattern and the QoS rules"


def test_partial_wildcards() -> None:
    assert key(STATUS, service="actor", instance="*") == "mea/v1/default/status/actor/*"
    assert key(ALIVE, service="*", instance="learner-0") == "mea/v1/default/alive/*/learner-0"


def test_serving_keys() -> None:
    assert key(SERVE_ACT, source="inference-0") == "mea/v1/default/serve/act/inference-0"
    assert key(SERVE_RESET, "cell-2", source="inference-0") == "mea/v1/cell-2/serve/reset/inference-0"
    assert parse("mea/v1/default/safety/estop/operator-0") == (ESTOP, "default", {"source": "operator-0"})
    for bad in ("mea/v1/default/serve/act", "mea/v1/default/serve/act/a/b", "mea/v1/default/serve/step/a"):
        with pytest.raises(TopicKeyError):
            parse(bad)


@pytest.mark.parametrize("bad", BAD_CHUNKS + [None, 3])
@pytest.mark.parametrize("topic", [EPISODES_RAW, STATUS], ids=["episodes_raw", "status"])
def test_invalid_chunks_rejected_when_building(topic: Topic, bad: object) -> None:
    parts = sample_parts(topic)
    first = topic.placeholders[0]
    if bad != "*":  # "*" is the wildcard when building, never a namespace
        with pytest.raises(TopicKeyError):
            key(topic, **{**parts, first: bad})  # type: ignore[arg-type]
    with pytest.raises(TopicKeyError):
        key(topic, bad, **parts)  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", BAD_CHUNKS)
@pytest.mark.parametrize("topic", [EPISODES_RAW, STATUS], ids=["episodes_raw", "status"])
def test_invalid_chunks_rejected_when_parsing(topic: Topic, bad: str) -> None:
    parts = sample_parts(topic)
    good = key(topic, "ns", **parts)
    first = topic.placeholders[0]
    with pytest.raises(TopicKeyError):
        parse(good.replace(parts[first], bad, 1))
    with pytest.raises(TopicKeyError):
        parse(good.replace("/ns/", f"/{bad}/", 1))


@pytest.mark.parametrize(
    "bad",
    [
        "mea/v2/default/episodes/raw/a",
        "mea/v1",
        "mea/v1/",
        "mea/v1/default",
        "mea/v1/default/",
        "other/v1/default/episodes/raw/a",
        "/mea/v1/default/episodes/raw/a",
        "mea/v1/default/episodes/raw",
        "mea/v1/default/episodes/raw/a/b",
        "mea/v1/default/episodes/cooked/a",
        "mea/v1/default/status/actor",
        "mea/v1/default/status/actor/a/b",
        "mea/v1/default/episodes/raw/a/",
        "mea/v1/default//episodes/raw/a",
        "mea/v1/default/weights/latest/a?min_version=3",
        "",
    ],
)
def test_unknown_keys_rejected(bad: str) -> None:
    with pytest.raises(TopicKeyError):
        parse(bad)


def test_missing_or_extra_placeholders_rejected() -> None:
    with pytest.raises(TopicKeyError):
        key(EPISODES_RAW)
    with pytest.raises(TopicKeyError):
        key(EPISODES_RAW, source="a", instance="b")
    with pytest.raises(TopicKeyError):
        key(STATUS, service="actor")
    assert issubclass(TopicKeyError, ValueError)


@pytest.mark.parametrize("topic", TOPICS, ids=ids(TOPICS))
def test_message_types(topic: Topic) -> None:
    if topic.kind in (Kind.PUBSUB, Kind.QUERY):
        assert topic.message is not None, f"{topic.name} carries no message type"
        assert issubclass(topic.message, Message)
        assert Message._REGISTRY.get(topic.message.TYPE) is topic.message
    else:
        assert topic.kind is Kind.LIVELINESS
        assert topic.message is None
    if topic.request is not None:
        assert topic.kind is Kind.QUERY, f"only queries carry a request, not {topic.kind.value} {topic.name}"
        assert issubclass(topic.request, Message) and not topic.request.NESTED_ONLY
        assert Message._REGISTRY.get(topic.request.TYPE) is topic.request
        assert topic.request is not topic.message
    else:
        assert not topic.requesters, f"{topic.name} names requesters but carries no request"
    assert set(topic.writers) <= set(SERVICES), topic.name
    assert set(topic.requesters) <= set(SERVICES), topic.name


def test_message_type_per_topic() -> None:
    expected = {
        "episodes_raw": "Episode",
        "episodes_augmented": "Episode",
        "weights_announce": "WeightsAnnouncement",
        "weights_latest": "WeightsBlob",
        "eval_reports": "EvalReport",
        "replay_gate": "ReplayGate",
        "status": "Heartbeat",
        "episode_acks": "EpisodeAck",
        "serve_reset": "ResetReply",
        "serve_act": "ActReply",
        "estop": "EStop",
    }
    assert {t.name: t.message.TYPE for t in TOPICS if t.message is not None} == expected
    assert WEIGHTS_LATEST.kind is Kind.QUERY and ALIVE.kind is Kind.LIVELINESS
    assert {t.name: t.request.TYPE for t in TOPICS if t.request is not None} == {
        "serve_reset": "ResetRequest",
        "serve_act": "ActRequest",
    }


def test_serving_topics_carry_requests_from_robots_answered_by_inference() -> None:
    for topic, request in [(SERVE_RESET, ResetRequest), (SERVE_ACT, ActRequest)]:
        assert topic.kind is Kind.QUERY and topic.placeholders == ("source",)
        assert topic.request is request
        assert topic.requesters == ("robot",)
        assert topic.writers == ("inference",)
    assert WEIGHTS_LATEST.request is None and WEIGHTS_LATEST.requesters == ()  # a plain query, anyone asks
    assert ESTOP.kind is Kind.PUBSUB and ESTOP.request is None and ESTOP.requesters == ()
    assert ESTOP.writers == ("operator",)


def test_an_act_request_fits_the_topic_cap() -> None:
    """The largest observation a robot sends (1,024 points in each of 3 segments, or a (3, 84, 84)
    image) is far below SERVE_ACT's cap."""
    req = ActRequest(session="r" * 96, episode=2**62, step=1_000_000, stamp=0.0, state=np.zeros(5, np.float32),
                     executed=np.zeros(5, np.float32), points=np.zeros((3, 1024, 3), np.float32),
                     point_counts=np.zeros(3, np.int32))  # fmt: skip
    assert len(req.encode()) * 4 < SERVE_ACT.max_bytes
    image = dataclasses.replace(req, points=None, point_counts=None, image=np.zeros((3, 84, 84), np.uint8))
    assert len(image.encode()) * 4 < SERVE_ACT.max_bytes
    assert SERVE_RESET.max_bytes >= 64 * 1024


@pytest.mark.parametrize("topic", TOPICS, ids=ids(TOPICS))
def test_congestion_rules(topic: Topic) -> None:
    if topic.path.split("/")[0] in ("episodes", "weights", "eval"):
        assert topic.qos.congestion is Congestion.BLOCK, f"{topic.name} must never drop"
        assert topic.qos.reliable
    if topic.qos.congestion is Congestion.DROP:
        assert topic is STATUS, f"only status heartbeats may be dropped, not {topic.name}"


def test_drop_is_status_only() -> None:
    assert [t for t in TOPICS if t.qos.congestion is Congestion.DROP] == [STATUS]
    assert WEIGHTS_ANNOUNCE.qos.express


@pytest.mark.parametrize("topic", [SERVE_RESET, SERVE_ACT, ESTOP], ids=ids([SERVE_RESET, SERVE_ACT, ESTOP]))
def test_serving_and_safety_never_drop(topic: Topic) -> None:
    assert topic.qos.congestion is Congestion.BLOCK and topic.qos.reliable, f"{topic.name} must never drop"
    assert topic.qos.priority.value <= Priority.INTERACTIVE_HIGH.value, f"{topic.name} must beat data traffic"


def test_real_time_priority_is_for_the_control_loop_only() -> None:
    real_time = [t for t in TOPICS if t.qos.priority is Priority.REAL_TIME]
    assert real_time == [SERVE_ACT, ESTOP]
    assert all(t.qos.express for t in real_time), "control-loop messages are sent at once, never batched"


def test_estop_is_latched_per_operator() -> None:
    """Latest value per key: a subscriber keeps each operator's newest EStop, so a flood of them
    cannot stall the transport that also carries everything else."""
    assert ESTOP.qos.latest_only and "{source}" in ESTOP.path
    assert not SERVE_ACT.qos.latest_only and not SERVE_RESET.qos.latest_only  # queries: not subscriptions


# ----------------------------------------------------------------------------------------------
# proto/README.md generated section
# ----------------------------------------------------------------------------------------------


def test_readme_reference_is_in_sync() -> None:
    assert docs.main(["--check"]) == 0, "proto/README.md is stale: run `python -m proto.docs`"


def test_readme_has_one_generated_section() -> None:
    text = docs.README.read_text(encoding="utf-8")
    assert Path(proto.__file__).with_name("README.md") == docs.README
    assert text.count(docs.BEGIN) == 1 and text.count(docs.END) == 1
    assert text.index(docs.BEGIN) < text.index(docs.END)


def test_reference_is_deterministic_and_complete() -> None:
    ref = docs.render_reference()
    assert ref == docs.render_reference()
    for cls in Message._REGISTRY.values():
        if cls.__module__.startswith("proto."):
            assert f"### `{cls.TYPE}` (v{cls.VERSION})" in ref
            for f in cls.fields():
                assert f"| `{f.name}` |" in ref, (cls.TYPE, f.name)
    for t in TOPICS:
        assert f"`mea/v1/<namespace>/{t.path}`" in ref
    assert "| `max_message_bytes` | 268435456 (256 MiB) |" in ref
    # the table cells escape pipes, so dtype lists stay in one column
    assert "float32\\|float64\\|int64" in ref


def test_docs_check_detects_a_stale_readme(tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    text = docs.README.read_text(encoding="utf-8")
    stale = text.replace("| `episode_id` |", "| `episode_identifier` |", 1)
    assert stale != text
    readme.write_text(stale, encoding="utf-8")
    assert docs.main(["--check", "--readme", str(readme)]) == 1
    assert readme.read_text(encoding="utf-8") == stale  # --check never writes
    assert docs.main(["--readme", str(readme)]) == 0
    assert readme.read_text(encoding="utf-8") == text
    assert docs.main(["--check", "--readme", str(readme)]) == 0


def test_docs_refuses_a_readme_without_markers(tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    readme.write_text("# no markers\n", encoding="utf-8")
    with pytest.raises(ValueError):
        docs.main(["--check", "--readme", str(readme)])


def test_topics_module_lists_every_topic() -> None:
    declared = [v for v in vars(topics).values() if isinstance(v, Topic)]
    assert set(declared) == set(TOPICS)


@pytest.mark.parametrize(
    ("topic", "parts", "sender", "allowed"),
    [
        (EPISODES_RAW, {"source": "actor-0"}, ("actor", "actor-0"), True),
        (EPISODES_RAW, {"source": "actor-0"}, ("actor", "actor-1"), False),  # as another actor
        (EPISODES_RAW, {"source": "learner-0"}, ("learner", "learner-0"), False),  # wrong kind
        (EPISODES_AUGMENTED, {"source": "augmenter-0"}, ("augmenter", "augmenter-0"), True),
        (EPISODES_AUGMENTED, {"source": "actor-0"}, ("actor", "actor-0"), False),
        (WEIGHTS_ANNOUNCE, {"source": "learner-0"}, ("learner", "learner-0"), True),
        (WEIGHTS_ANNOUNCE, {"source": "actor-0"}, ("actor", "actor-0"), False),
        (WEIGHTS_LATEST, {"source": "learner-0"}, ("evaluator", "learner-0"), False),
        (REPLAY_GATE, {"source": "learner-0"}, ("learner", "learner-0"), True),
        (REPLAY_GATE, {"source": "learner-0"}, ("actor", "learner-0"), False),
        (EPISODE_ACKS, {"source": "learner-0"}, ("learner", "learner-0"), True),
        (EPISODE_ACKS, {"source": "augmenter-0"}, ("augmenter", "augmenter-0"), False),
        (EVAL_REPORTS, {"source": "evaluator-0"}, ("evaluator", "evaluator-0"), True),
        (EVAL_REPORTS, {"source": "evaluator-0"}, ("learner", "evaluator-0"), False),
        (STATUS, {"service": "actor", "instance": "actor-0"}, ("actor", "actor-0"), True),
        (STATUS, {"service": "learner", "instance": "learner-0"}, ("actor", "actor-0"), False),
        (STATUS, {"service": "actor", "instance": "actor-1"}, ("actor", "actor-0"), False),
        (ESTOP, {"source": "operator-0"}, ("operator", "operator-0"), True),
        (ESTOP, {"source": "operator-0"}, ("operator", "operator-1"), False),  # as another operator
        (ESTOP, {"source": "robot-0"}, ("robot", "robot-0"), False),  # a robot cannot release an e-stop
        (ESTOP, {"source": "inference-0"}, ("inference", "inference-0"), False),
        (SERVE_ACT, {"source": "inference-0"}, ("inference", "inference-0"), True),  # the reply
        (SERVE_ACT, {"source": "inference-0"}, ("inference", "inference-1"), False),  # another server's key
        (SERVE_ACT, {"source": "robot-0"}, ("robot", "robot-0"), False),  # a robot cannot answer
        (SERVE_RESET, {"source": "inference-0"}, ("inference", "inference-0"), True),
        (SERVE_RESET, {"source": "inference-0"}, ("learner", "inference-0"), False),
    ],
)
def test_who_may_write(topic: Topic, parts: dict, sender: tuple[str, str], allowed: bool) -> None:
    why = may_write(topic, parts, *sender)
    assert (why is None) is allowed, why


@pytest.mark.parametrize(
    ("topic", "service", "allowed"),
    [
        (SERVE_ACT, "robot", True),
        (SERVE_ACT, "actor", False),
        (SERVE_ACT, "inference", False),  # a server does not ask another server
        (SERVE_ACT, "operator", False),
        (SERVE_RESET, "robot", True),
        (SERVE_RESET, "evaluator", False),
        (SERVE_RESET, "test", False),
        (WEIGHTS_LATEST, "actor", True),  # no requesters: any service of the run may ask
        (WEIGHTS_LATEST, "robot", True),
    ],
)
def test_who_may_request(topic: Topic, service: str, allowed: bool) -> None:
    why = may_request(topic, service)
    assert (why is None) is allowed, why
    if not allowed:
        assert topic.name in why and service in why and "robot" in why


def test_may_request_refuses_every_non_robot() -> None:
    for topic in (SERVE_RESET, SERVE_ACT):
        assert may_request(topic, "robot") is None
        assert all(may_request(topic, s) is not None for s in SERVICES if s != "robot")
