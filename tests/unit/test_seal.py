"""The authentication envelope (proto/seal.py) as a pure function: round trip, and every alteration
refused with a reason."""

from __future__ import annotations

import hashlib
import hmac
import struct

import pytest

from proto.msgpack_wire import ProtocolError
from proto.seal import MAC_BYTES, MAGIC, is_sealed, key_id, read_envelope, seal, unseal

pytestmark = pytest.mark.unit

KEY = bytes(range(32))
OTHER = bytes(range(1, 33))
KX = "mea/v1/default/weights/announce/learner-0"
BODY = b"\x83\xa5_type\xa4Test\xa2_v\x01\xa1x\x07"


def test_round_trip_names_the_sender():
    payload = seal(KEY, KX, "learner", "learner-0", BODY)
    assert is_sealed(payload) and not is_sealed(BODY)
    s = unseal(KEY, KX, payload)
    assert (s.service, s.instance, s.sender, s.body) == ("learner", "learner-0", "learner/learner-0", BODY)
    assert s.key_id == key_id(KEY).hex()


def test_mac_is_the_documented_hmac():
    """A client in another language computes the same bytes from the README's description."""
    payload = seal(KEY, KX, "learner", "learner-0", BODY)
    sender = b"learner/learner-0"
    header = (
        MAGIC
        + b"\x01"
        + hashlib.sha256(b"mea-run-key-id\0" + KEY).digest()[:8]
        + bytes([len(sender)])
        + sender
    )
    mac = hmac.new(KEY, header + struct.pack(">H", len(KX)) + KX.encode() + BODY, hashlib.sha256).digest()
    assert payload == header + mac + BODY


@pytest.mark.parametrize("where", ["body", "mac", "sender", "key_id"])
def test_any_altered_byte_is_refused(where: str):
    payload = bytearray(seal(KEY, KX, "learner", "learner-0", BODY))
    _, sender, mac_at = read_envelope(bytes(payload))
    at = {"body": len(payload) - 1, "mac": mac_at + 3, "sender": mac_at - 1, "key_id": 6}[where]
    payload[at] ^= 0x01
    with pytest.raises(ProtocolError) as e:
        unseal(KEY, KX, bytes(payload))
    assert e.value.field == "<seal>"


def test_moved_to_another_key_expression_is_refused():
    payload = seal(KEY, KX, "learner", "learner-0", BODY)
    unseal(KEY, KX, payload)  # where it was sealed for: fine
    with pytest.raises(ProtocolError, match="bad MAC"):
        unseal(KEY, KX.replace("learner-0", "learner-1"), payload)


def test_another_runs_key_is_named_as_such():
    payload = seal(OTHER, KX, "learner", "learner-0", BODY)
    with pytest.raises(ProtocolError, match="another key"):
        unseal(KEY, KX, payload)
    assert unseal(OTHER, KX, payload).body == BODY


def test_without_a_key_the_envelope_is_only_read():
    payload = seal(OTHER, KX, "actor", "actor-3", BODY)
    s = unseal(None, KX, payload)
    assert (s.sender, s.body) == ("actor/actor-3", BODY)


@pytest.mark.parametrize(
    "payload",
    [
        BODY,
        b"MEAS",
        b"MEAS\x02" + bytes(40),
        b"MEAS\x01" + bytes(8) + b"\x05ab",
        b"MEAS\x01" + bytes(8) + b"\x03a/b",
    ],
    ids=["bare", "magic-only", "version-2", "short-sender", "no-mac"],
)
def test_malformed_envelopes_are_refused(payload: bytes):
    with pytest.raises(ProtocolError):
        unseal(KEY, KX, payload)


def test_bad_sender_or_key_cannot_be_sealed():
    with pytest.raises(ValueError):
        seal(KEY, KX, "Learner", "x", BODY)
    with pytest.raises(ValueError):
        seal(KEY[:16], KX, "learner", "learner-0", BODY)
    assert len(seal(KEY, KX, "a", "b", b"")) == 4 + 1 + 8 + 1 + 3 + MAC_BYTES
