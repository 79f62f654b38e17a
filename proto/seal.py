"""The authentication envelope: a message sealed with the run's key, bound to its key expression
and to the service instance that sent it.

Design notes: docs/architecture-notes.md, proto/seal.py."""

from __future__ import annotations

import hashlib
import hmac
import re
import struct
from dataclasses import dataclass

from proto.msgpack_wire import ProtocolError

MAGIC = b"MEAS"
SEAL_VERSION = 1
KEY_BYTES = 32
KEY_ID_BYTES = 8
MAC_BYTES = 32
SENDER = re.compile(r"[a-z]{1,32}/[A-Za-z0-9_.-]{1,64}")
_FIXED = len(MAGIC) + 1 + KEY_ID_BYTES + 1  # bytes before the sender


@dataclass(frozen=True)
class Sealed:
    """A payload whose envelope was read (and, with a key, verified)."""

    service: str
    instance: str
    key_id: str
    body: bytes

    @property
    def sender(self) -> str:
        return f"{self.service}/{self.instance}"


def key_id(key: bytes) -> bytes:
    return hashlib.sha256(b"mea-run-key-id\0" + key).digest()[:KEY_ID_BYTES]


def is_sealed(payload: bytes) -> bool:
    return payload[: len(MAGIC)] == MAGIC


def _mac(key: bytes, header: bytes, key_expr: str, body: bytes | memoryview) -> bytes:
    kx = key_expr.encode()
    h = hmac.new(key, header, hashlib.sha256)
    h.update(struct.pack(">H", len(kx)) + kx)
    h.update(body)
    return h.digest()


def _check_key(key: bytes) -> None:
    if not isinstance(key, bytes) or len(key) != KEY_BYTES:
        raise ValueError(f"a run key is {KEY_BYTES} bytes")


def seal(key: bytes, key_expr: str, service: str, instance: str, body: bytes) -> bytes:
    """Wrap ``body`` (an encoded message) for ``key_expr``, sent by ``service/instance``."""
    _check_key(key)
    sender = f"{service}/{instance}"
    if not SENDER.fullmatch(sender):
        raise ValueError(f"sender {sender!r} must match {SENDER.pattern}")
    header = MAGIC + bytes([SEAL_VERSION]) + key_id(key) + bytes([len(sender)]) + sender.encode()
    return header + _mac(key, header, key_expr, body) + body


def read_envelope(payload: bytes) -> tuple[bytes, str, int]:
    """(key id, sender, offset of the MAC) of a sealed payload; ProtocolError if malformed."""
    if not is_sealed(payload):
        raise ProtocolError("<seal>", "not sealed (the run requires authenticated messages)")
    if len(payload) < _FIXED or payload[len(MAGIC)] != SEAL_VERSION:
        raise ProtocolError("<seal>", f"unknown envelope version (this build reads {SEAL_VERSION})")
    kid = payload[len(MAGIC) + 1 : len(MAGIC) + 1 + KEY_ID_BYTES]
    n = payload[_FIXED - 1]
    mac_at = _FIXED + n
    if len(payload) < mac_at + MAC_BYTES:
        raise ProtocolError("<seal>", "truncated envelope")
    try:
        sender = payload[_FIXED:mac_at].decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError("<seal>", "sender is not ASCII") from None
    if not SENDER.fullmatch(sender):
        raise ProtocolError("<seal>", f"sender {sender[:80]!r} is not <service>/<instance>")
    return kid, sender, mac_at


def unseal(key: bytes | None, key_expr: str, payload: bytes) -> Sealed:
    """Read a sealed payload. With ``key``: the key id must be this run's and the MAC must verify
    (ProtocolError naming the failure otherwise). Without a key the envelope is only parsed."""
    kid, sender, mac_at = read_envelope(payload)
    body_at = mac_at + MAC_BYTES
    view = memoryview(payload)
    if key is not None:
        if kid != key_id(key):
            raise ProtocolError("<seal>", f"sealed with another key (id {kid.hex()}, this run's is {key_id(key).hex()})")  # fmt: skip
        want = _mac(key, bytes(view[:mac_at]), key_expr, view[body_at:])
        if not hmac.compare_digest(want, bytes(view[mac_at:body_at])):
            raise ProtocolError("<seal>", "bad MAC (forged, altered, or moved to another key expression)")
    service, _, instance = sender.partition("/")
    return Sealed(service, instance, kid.hex(), bytes(view[body_at:]))
