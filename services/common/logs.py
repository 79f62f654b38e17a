"""Structured logs: one JSON object per line on stderr (or plain text), with service identity."""

from __future__ import annotations

import json
import logging
import sys
import time

_RESERVED = set(vars(logging.makeLogRecord({})).keys()) | {"message", "asctime"}


def _extras(record: logging.LogRecord) -> dict:
    return {k: v for k, v in vars(record).items() if k not in _RESERVED and not k.startswith("_")}


class TextFormatter(logging.Formatter):
    """Human-readable line with the structured fields appended as key=value."""

    converter = time.gmtime

    def format(self, record: logging.LogRecord) -> str:
        line = super().format(record)
        extra = " ".join(f"{k}={v}" for k, v in _extras(record).items())
        return f"{line} {extra}" if extra else line


class JsonFormatter(logging.Formatter):
    def __init__(self, service: str, instance: str) -> None:
        super().__init__()
        self.service = service
        self.instance = instance

    def format(self, record: logging.LogRecord) -> str:
        out = {
            "ts": round(record.created, 3),
            "level": record.levelname.lower(),
            "service": self.service,
            "instance": self.instance,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        for k, v in _extras(record).items():
            out[k] = v if isinstance(v, (int, float, str, bool, type(None))) else str(v)
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


_shared = False
"""Set by ``setup_in_process``: one handler for every service of the process; ``setup`` keeps it."""


def setup_in_process(fmt: str = "json", level: str = "INFO") -> None:
    """Logging for all services in one process (``mea run --in-process``): each line names the
    thread that wrote it (a service's main thread is named after its instance)."""
    global _shared
    setup("process", "%(threadName)s", fmt, level)
    if fmt == "json":
        logging.getLogger().handlers[0].setFormatter(ThreadJsonFormatter())
    _shared = True


class ThreadJsonFormatter(JsonFormatter):
    """JSON lines whose ``instance`` is the writing thread's name (the in-process topology)."""

    def __init__(self) -> None:
        super().__init__("process", "")

    def format(self, record: logging.LogRecord) -> str:
        self.instance = record.threadName or ""
        return super().format(record)


def setup(service: str, instance: str, fmt: str = "json", level: str = "INFO") -> None:
    if _shared:
        return
    handler = logging.StreamHandler(sys.stderr)
    if fmt == "json":
        handler.setFormatter(JsonFormatter(service, instance))
    else:
        handler.setFormatter(
            TextFormatter(f"%(asctime)sZ {service}/{instance} %(levelname)s %(name)s: %(message)s")
        )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
