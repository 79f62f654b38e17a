"""Weights on disk: the versions a server can be pinned to, as files.

``WeightsBlob`` files, sealed when the run authenticates, written atomically by the learner and the
evaluator and read back with the checks the bus would make (seal, digest; nothing unpickled).

Design notes: docs/architecture-notes.md, services/common/weights_file.py."""

from __future__ import annotations

import os
import re
from pathlib import Path

from proto.msgpack_wire import DEFAULT_LIMITS, Limits, ProtocolError
from proto.seal import is_sealed, seal, unseal
from proto.weights import WeightsBlob
from services.common import retention

FILE_KEY = "mea/v1/file/weights"
"""The key expression a weights file is sealed under (it never travels on the bus)."""
DIRECTORY = "weights"
LEARNER = "learner/weights"
"""Where `mea run`'s learner writes every version it announces (relative to the run dir)."""
EVALUATED = "eval/weights"
"""Where `mea run`'s evaluator keeps the versions it evaluated (relative to the run dir)."""
WRITERS = ("learner", "evaluator")
NAME = re.compile(r"weights-(\d+)\.blob")
KEEP = 3


class WeightsFileError(ValueError):
    """A weights file is missing, unreadable, unsigned where a signature is needed, or corrupt."""


def file_name(version: int) -> str:
    return f"weights-{version:08d}.blob"


def versions(directory: Path) -> list[tuple[int, Path]]:
    """The weights files in ``directory``, oldest version first."""
    if not directory.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in directory.iterdir() if (m := NAME.fullmatch(p.name))]
    return sorted(found)


def write(directory: Path, blob: WeightsBlob, key: bytes | None = None, instance: str = "learner-0",
          keep: int = KEEP, service: str = "learner", body: bytes | None = None) -> Path:  # fmt: skip
    """Write ``blob`` as ``directory/weights-<version>.blob`` (sealed as ``service/instance`` when ``key``
    is given) and keep the newest ``keep`` files; returns the path. ``body``: ``blob.encode()`` when
    the caller has it already."""
    directory.mkdir(parents=True, exist_ok=True)
    body = blob.encode() if body is None else body
    data = body if key is None else seal(key, FILE_KEY, service, instance, body)
    path = directory / file_name(blob.version)
    tmp = directory / ".weights.blob.tmp"
    with tmp.open("wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    files = [(p.name, p.stat().st_size) for _, p in versions(directory)]
    for name in retention.to_delete(files, keep=keep):
        (directory / name).unlink(missing_ok=True)
    return path


def resolve(path: Path, version: int | None = None) -> Path:
    """``path`` itself if it is a file. In a directory: a run dir (its learner's and its evaluator's
    weights), the learner's dir, or a folder of weights files; the file of ``version`` or, without
    one, the newest."""
    if path.is_file():
        return path
    dirs = [d for d in (path / LEARNER, path / EVALUATED, path / DIRECTORY) if d.is_dir()] or [path]
    found = sorted(f for d in dirs for f in versions(d))
    if not found:
        raise WeightsFileError(
            f"{path}: no weights-<version>.blob files (a run dir written by this version of mea?)"
        )
    if version is None:
        return found[-1][1]
    for v, p in found:
        if v == version:
            return p
    have = ", ".join(str(v) for v, _ in found[-20:])
    raise WeightsFileError(f"{path}: no weights file for version {version} (the newest: {have})")


def read(path: Path, key: bytes | None, limits: Limits = DEFAULT_LIMITS) -> WeightsBlob:
    """The blob in ``path``, checked: with ``key`` its seal must verify and name a learner or an
    evaluator; its digest must match; a ``weights-<version>.blob`` must hold that version. ``key``
    None reads only unsealed files (a run that did not authenticate). A refusal names the path and
    the check that failed (seal, digest, version or format)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise WeightsFileError(f"{path}: cannot read it ({exc.strerror})") from None
    try:
        if key is not None:
            sealed = unseal(key, FILE_KEY, data)
            if sealed.service not in WRITERS:
                raise ProtocolError("<sender>", f"written by {sealed.sender}, not a learner or an evaluator")
            data = sealed.body
        elif is_sealed(data):
            raise WeightsFileError(
                f"{path}: the file is signed; give the run's key to check it (--service.run-key-file)"
            )
        if not data:
            raise ProtocolError("<message>", "the file is empty")
        blob = WeightsBlob.decode(data, limits)
    except ProtocolError as exc:
        raise WeightsFileError(f"{path}: refused, {_failure(exc.field)}: {exc}") from None
    named = NAME.fullmatch(path.name)
    if named is not None and int(named.group(1)) != blob.version:  # the digest covers tensors only
        raise WeightsFileError(
            f"{path}: refused, it holds version {blob.version}, not the {int(named.group(1))} of its name "
            "(damaged or renamed)"
        )
    return blob


def _failure(field: str) -> str:
    """Which check a refused file failed, in words (the exception's text has the details)."""
    if field in ("<seal>", "<sender>"):
        return "its seal does not verify (damaged, altered, or sealed by another run or service)"
    if field == "WeightsBlob.digest":
        return "its digest does not match its tensors (damaged or altered)"
    return "not a valid weights file (damaged, or another format)"
