"""The run's secret key on disk: created once at run start (owner-only file), read by every service.

Every service of a run seals its messages with this key and accepts only messages sealed with it
(``proto/seal.py``). Services on other hosts get a copy of the file (``--service.run-key-file``);
whoever can read it can write to the run's bus, so it is created readable by its owner only.
"""

from __future__ import annotations

import os
import secrets
import stat
from pathlib import Path

from proto.seal import KEY_BYTES, key_id

FILE_NAME = "run.key"


class RunKeyError(ValueError):
    """The key file is missing, unreadable, malformed or readable by others."""


def create(path: Path) -> bytes:
    """Write a new random key to ``path`` (hex, mode 0600) unless one is there; returns the key."""
    path = Path(path)
    if path.exists():
        return load(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    key = secrets.token_bytes(KEY_BYTES)
    tmp = path.with_suffix(".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key.hex() + "\n")
    tmp.replace(path)
    return key


def load(path: Path) -> bytes:
    """The key in ``path``; RunKeyError naming the file and the problem otherwise."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
        text = path.read_text().strip()
    except OSError as exc:
        raise RunKeyError(f"run key file {path}: {exc.strerror or exc}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise RunKeyError(f"run key file {path}: readable by group or others (chmod 600 {path})")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise RunKeyError(f"run key file {path}: expected {2 * KEY_BYTES} hex digits")
    return key


def describe(key: bytes) -> str:
    """The key's public id (safe to log)."""
    return key_id(key).hex()
