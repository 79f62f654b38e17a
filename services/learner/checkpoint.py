"""Atomic learner checkpoints, loaded without unpickling arbitrary objects, the newest few kept.

Design notes: docs/architecture-notes.md, services/learner/checkpoint.py."""

from __future__ import annotations

import json
import logging
import os
import pickle
import re
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from services.common import retention
from services.learner import replay_segments
from services.learner.replay_segments import Segment, SegmentError

if TYPE_CHECKING:
    from services.algorithms.trainer import Trainer

log = logging.getLogger(__name__)
STEM, SUFFIX = "learner", ".pt"
TMP = f".{STEM}{SUFFIX}.tmp"
LEGACY = ("learner.pt", "learner.prev.pt")
"""Names of the single checkpoint and its previous copy from before numbering, newest first."""
KEEP = 3
"""Checkpoints kept by default (``LearnerConfig.keep_checkpoints``)."""
FORMAT = 1
PUBLISHED = "published.json"
"""The newest version announced (run id and number), written before each announcement: a learner
resumed from an older checkpoint continues past it, so no version number is published twice."""


def _to_torch(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(x))
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, dict):
        return {k: _to_torch(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_to_torch(v) for v in x]
    return x


def on_cpu(x: Any) -> Any:
    """``x`` (a state dict: dicts, lists and tuples of tensors and plain values) with every tensor on
    the CPU; CPU tensors are kept as they are (no copy)."""
    if isinstance(x, torch.Tensor):
        return x.cpu()
    if isinstance(x, dict):
        return {k: on_cpu(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(on_cpu(v) for v in x)
    return x


def _to_numpy(x: Any) -> Any:
    if isinstance(x, torch.Tensor):
        return x.numpy()
    if isinstance(x, dict):
        return {k: _to_numpy(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_to_numpy(v) for v in x]
    return x


def rng_state(np_rng: np.random.Generator) -> dict:
    return {"torch": torch.get_rng_state(), "numpy": json.dumps(np_rng.bit_generator.state)}


def restore_rng(state: dict, np_rng: np.random.Generator) -> None:
    torch.set_rng_state(state["torch"])
    np_rng.bit_generator.state = json.loads(state["numpy"])


def file_name(n: int) -> str:
    """The name of checkpoint number ``n`` (>= 1): ``learner-<n>.pt``, zero-padded to 6 digits."""
    return f"{STEM}-{n:06d}{SUFFIX}"


def _number(name: str) -> int | None:
    """The number of a checkpoint's file name; legacy names count below every numbered one."""
    if name in LEGACY:
        return -LEGACY.index(name) - 1
    m = re.fullmatch(re.escape(STEM) + r"-(\d+)" + re.escape(SUFFIX), name)
    return None if m is None else int(m.group(1))


def checkpoints(directory: Path) -> list[Path]:
    """The checkpoint files in ``directory``, newest first (by number, numerically); never the
    temporary file of one being written."""
    try:
        names = os.listdir(directory)
    except FileNotFoundError:
        return []
    keyed = [(n, name) for name in names if (n := _number(name)) is not None]
    return [directory / name for _, name in sorted(keyed, reverse=True)]


def next_number(directory: Path) -> int:
    """The number the next checkpoint written in ``directory`` gets."""
    return 1 + max([0, *(_number(p.name) or 0 for p in checkpoints(directory))])


def listed_segments(path: Path) -> list[Segment] | None:
    """The replay segments the checkpoint ``path`` reads (``replay_segments``): [] for one that holds
    its replay whole, None where the file cannot be read. Cheap: the file is mapped, not read."""
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        replay = payload["replay"]
        if not (isinstance(replay, dict) and replay.get("layout") == replay_segments.LAYOUT):
            return []
        return [Segment.from_json(d) for d in replay["segments"]]
    except Exception:  # noqa: BLE001 - a damaged file is the caller's to report when it loads it
        return None


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def prune(directory: Path, keep: int = KEEP, max_bytes: int = 0) -> list[Path]:
    """Delete the oldest checkpoints beyond ``keep`` files and ``max_bytes`` bytes in all (0: no
    budget), then the replay segments no kept checkpoint reads; the newest always stays. A
    checkpoint's bytes are its file's and those of the segments no newer checkpoint reads (what
    deleting it with the older ones frees). Returns the deleted checkpoint paths."""
    if keep < 1:
        raise ValueError(f"keep must be >= 1, got {keep}")
    files, listed, seen = [], {}, set()
    for path in checkpoints(directory):  # newest first
        if not path.exists():
            continue
        names = {seg.name for seg in listed_segments(path) or []}
        listed[path.name] = names
        files.append((path.name, _size(path) + sum(_size(directory / n) for n in names - seen)))
        seen |= names
    files.reverse()  # oldest first
    deleted = []
    for name in retention.to_delete(files, keep=keep, max_bytes=max_bytes):
        try:
            (directory / name).unlink()
        except FileNotFoundError:
            continue
        except OSError as exc:
            log.warning(
                "old checkpoint not deleted", extra={"path": str(directory / name), "error": str(exc)}
            )
            continue
        deleted.append(directory / name)
        listed.pop(name, None)
    if deleted:
        log.info("old checkpoints deleted", extra={"files": ",".join(p.name for p in deleted)})
    gone = replay_segments.delete_unlisted(directory, set().union(*listed.values()))
    if gone:
        log.info("replay segments no kept checkpoint reads deleted", extra={"files": ",".join(gone)})
    return deleted


def save(
    directory: Path, *, learner: dict, replay: dict, meta: dict, keep: int = KEEP, max_bytes: int = 0
) -> Path:
    """Write a checkpoint atomically, as the newest, then apply the retention (``prune``).
    ``learner`` holds tensors (state dicts), ``replay`` numpy arrays and plain values, ``meta``
    JSON-able values (version, run id, counters, config)."""
    if keep < 1:
        raise ValueError(f"keep must be >= 1, got {keep}")
    directory.mkdir(parents=True, exist_ok=True)
    number = next_number(directory)
    path, tmp = directory / file_name(number), directory / TMP
    payload = {"format": FORMAT, "learner": learner, "replay": _to_torch(replay), "meta": json.dumps(meta)}
    with open(tmp, "wb") as f:
        torch.save(payload, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    dir_fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    prune(directory, keep, max_bytes)
    return path


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable or of another format."""


def _why(exc: Exception) -> str:
    """An unreadable checkpoint's reason in one short line (torch's first sentence)."""
    text = str(exc).strip().split("\n")[0].split(". ")[0][:200]
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def read(path: Path) -> tuple[dict, dict, dict]:
    """(learner state, replay state as numpy, meta) of the checkpoint file ``path``; CheckpointError
    naming the file and why it cannot be used."""
    try:
        size = path.stat().st_size
        whole = zipfile.is_zipfile(path)  # torch.save writes a zip archive; a cut one has no directory
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read it ({exc.strerror})") from None
    if not whole:
        raise CheckpointError(
            f"{path}: damaged, not a whole torch archive ({size} bytes; truncated or overwritten)"
        )
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(
            f"{path}: refused, it holds objects other than tensors and plain data ({_why(exc)})"
        ) from None
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a damaged archive
        raise CheckpointError(f"{path}: damaged ({_why(exc)})") from None
    if not isinstance(payload, dict):
        raise CheckpointError(f"{path}: not a learner checkpoint (holds a {type(payload).__name__})")
    if payload.get("format") != FORMAT:
        raise CheckpointError(f"{path}: format {payload.get('format')!r}, expected {FORMAT}")
    missing = [k for k in ("learner", "replay", "meta") if k not in payload]
    if missing:
        raise CheckpointError(f"{path}: not a learner checkpoint (no {', '.join(missing)})")
    try:
        meta = json.loads(payload["meta"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: its metadata is unreadable ({_why(exc)})") from None
    replay = _to_numpy(payload["replay"])
    if isinstance(replay, dict) and replay.get("layout") == replay_segments.LAYOUT:
        replay = _joined(path, replay)
    return payload["learner"], replay, meta


def _joined(path: Path, replay: dict) -> dict:
    """The whole replay state of a checkpoint that keeps it in segments."""
    try:
        listed = [Segment.from_json(d) for d in replay["segments"]]
        parts = [replay_segments.read(path.parent, seg) for seg in listed]
        return replay_segments.join(replay["manifest"], parts, replay["order"])
    except SegmentError as exc:
        raise CheckpointError(f"{path}: its replay is unreadable ({exc})") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: its replay listing is unreadable ({_why(exc)})") from None


def load(directory: Path) -> tuple[dict, dict, dict]:
    """(learner state, replay state as numpy, meta) of the newest readable checkpoint: each unreadable
    one is named in a warning with why, and the next older one tried."""
    return load_newest(directory)[1:]


def load_newest(directory: Path) -> tuple[Path, dict, dict, dict]:
    """``load``, with the path of the checkpoint it read first."""
    errors = []
    candidates = checkpoints(directory)
    for i, path in enumerate(candidates):
        try:
            state = read(path)
        except CheckpointError as exc:
            errors.append(str(exc))
            then = "trying the next older one" if i + 1 < len(candidates) else "no older one"
            log.warning(f"checkpoint skipped: {exc}; {then}", extra={"path": str(path)})
            continue
        if errors:
            log.warning(f"newer checkpoints unreadable; resuming an older one, {path}",
                        extra={"path": str(path), "unreadable": len(errors)})  # fmt: skip
        return (path, *state)
    if not errors:
        raise CheckpointError(f"no checkpoint in {directory}")
    raise CheckpointError(f"no readable checkpoint in {directory}: " + "; ".join(errors))


def record_published(directory: Path, run_id: str, version: int) -> None:
    """Record ``version`` of ``run_id`` as announced (atomically, before the announcement goes out)."""
    directory.mkdir(parents=True, exist_ok=True)
    tmp = directory / f".{PUBLISHED}.tmp"
    with open(tmp, "w") as f:
        f.write(json.dumps({"run_id": run_id, "version": int(version)}))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, directory / PUBLISHED)


def last_published(directory: Path) -> tuple[str, int] | None:
    """(run id, version) of the newest announced version, or None if none is recorded (or the record
    is unreadable, which a resume reports)."""
    try:
        rec = json.loads((directory / PUBLISHED).read_text())
        return str(rec["run_id"]), int(rec["version"])
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CheckpointError(f"{directory / PUBLISHED}: unreadable ({exc})") from None


def continued_lineage(
    restored: Lineage | None, published: tuple[str, int] | None, fresh_run_id: str
) -> Lineage:
    """The lineage a (re)starting learner continues: the checkpoint's, moved past every version its run
    announced after that checkpoint; with no checkpoint, the announced lineage itself (a learner
    killed before its first checkpoint keeps its run id and goes on counting); else a new one."""
    if restored is None:
        if published is None:
            return Lineage(-1, fresh_run_id, {})
        return Lineage(published[1], published[0], {})
    if published is not None and published[0] == restored.run_id and published[1] > restored.version:
        return Lineage(published[1], restored.run_id, restored.last)
    return restored


def exists(directory: Path) -> bool:
    return bool(checkpoints(directory))


# ------------------------------------------------------------------------------------------------
# What a learner checkpoint holds
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Lineage:
    """What a resumed learner carries on besides the trainer's state: its weights version lineage and
    the latest update's statistics."""

    version: int
    run_id: str
    last: dict[str, float]


def due(seconds_since_last: float, updates: int, minutes: float, every: int) -> bool:
    """Whether a checkpoint is due: ``minutes`` (> 0) have passed since the last one, or ``updates`` (> 0)
    is a multiple of ``every`` (> 0)."""
    by_time = minutes > 0 and seconds_since_last >= 60.0 * minutes
    return by_time or (every > 0 and updates > 0 and updates % every == 0)


def save_trainer(
    directory: Path,
    trainer: Trainer,
    lineage: Lineage,
    config: dict[str, Any],
    *,
    keep: int = KEEP,
    max_bytes: int = 0,
    segments: list[Segment] | None = None,
) -> tuple[Path, list[Segment]]:
    """Write ``trainer``'s whole state (networks, optimisers, alpha, RNG states, replay, limiter) with
    ``lineage``, the env steps and ``config`` (the resolved settings, JSON-able) as metadata; keep
    the newest ``keep`` checkpoints within ``max_bytes`` (``save``). Returns the path and the replay
    segments it reads, to pass as ``segments`` next time: the replay's episodes that those hold are
    not written again (``replay_segments``; None or [] writes them all).
    The caller keeps the replay and the limiter still meanwhile."""
    meta = {
        "version": lineage.version,
        "run_id": lineage.run_id,
        "env_steps": trainer.env_steps,
        "limiter": trainer.limiter.state_dict(),
        "last": lineage.last,
        "config": config,
        "saved_at": time.time(),
    }
    # "sac" holds any algorithm's state (the key predates GASv2; checkpoints of older runs keep loading)
    learner = {"sac": on_cpu(trainer.agent.state_dict()), "rng": rng_state(trainer.rng)}
    directory.mkdir(parents=True, exist_ok=True)
    previous = [seg for seg in segments or [] if (directory / seg.name).exists()]
    if len(previous) != len(segments or []):
        previous = []  # a listed segment is gone: write every episode again
    serials, lengths = trainer.replay.live_episodes()
    kept, new = replay_segments.plan(previous, serials, lengths)
    manifest, episodes = replay_segments.split(trainer.replay.state_dict(serials=new))
    if new.size or not kept:  # an empty replay still gets a segment: it carries the arrays' shapes
        kept = [*kept, replay_segments.write(directory, next_number(directory), episodes)]
    replay = {"layout": replay_segments.LAYOUT, "manifest": manifest, "order": serials,
              "segments": [seg.to_json() for seg in kept]}  # fmt: skip
    path = save(directory, learner=learner, replay=replay, meta=meta, keep=keep, max_bytes=max_bytes)
    return path, kept


def restore_trainer(directory: Path, trainer: Trainer) -> tuple[Lineage, list[Segment]]:
    """Load the checkpoint in ``directory`` into ``trainer``; returns the lineage it continues and the
    replay segments it read (``save_trainer``'s ``segments``)."""
    path, learner, replay, meta = load_newest(directory)
    trainer.agent.load_state_dict(learner["sac"])
    restore_rng(learner["rng"], trainer.rng)
    trainer.replay.load_state_dict(replay)
    trainer.limiter.load_state_dict(meta["limiter"])
    lineage = Lineage(int(meta["version"]), str(meta["run_id"]), dict(meta.get("last", {})))
    return lineage, listed_segments(path) or []
