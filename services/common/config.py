"""Config plumbing: frozen dataclasses with presets, parsed by tyro, saved with each run.

Every command takes ``--preset NAME`` first (e.g. ``paper``, ``cpu-small``); any other flag then
overrides a field of that preset. Each field's one-line docstring is its ``--help`` line
(details in docs/options.md).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import shlex
import sys
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import tyro

from proto.msgpack_wire import DEFAULT_LIMITS, Limits
from proto.topics import TopicKeyError, by_name
from services.common.bus.zenoh_bus import ZenohConfig

C = TypeVar("C")


@dataclasses.dataclass(frozen=True)
class ServiceConfig:
    """What every service process shares: identity, transport, metrics and logs."""

    instance_id: str = ""
    """Instance id; empty: <service>-<pid>."""
    zenoh: ZenohConfig = ZenohConfig()
    """How to join the Zenoh network."""
    metrics_port: int = -1
    """/metrics port; -1: the service's default, 0: off."""
    metrics_addr: str = "127.0.0.1"
    """/metrics address (0.0.0.0 in containers)."""
    log_format: str = "json"
    """`json` (one object per line) or `text`."""
    log_level: str = "INFO"
    """Python logging level."""
    heartbeat_seconds: float = 1.0
    """Period of the status heartbeat."""
    limits: Limits = DEFAULT_LIMITS
    """Caps checked while decoding every received message."""
    topic_caps: tuple[str, ...] = ()
    """Per-topic size caps, each TOPIC=BYTES."""
    run_key_file: str = ""
    """Run key file (sealed messages); empty: none."""

    def __post_init__(self) -> None:
        if self.log_format not in ("json", "text"):
            raise ValueError(f"log_format must be json or text, not {self.log_format!r}")
        if self.heartbeat_seconds <= 0:
            raise ValueError("heartbeat_seconds must be positive")
        self.caps()  # refuse a malformed --service.topic-caps at start-up

    def caps(self) -> dict[str, int]:
        """``topic_caps`` as {topic name: bytes}; ValueError naming a bad entry."""
        out = {}
        for entry in self.topic_caps:
            name, _, value = entry.partition("=")
            try:
                by_name(name)
                out[name] = int(value)
            except (TopicKeyError, ValueError):
                raise ValueError(
                    f"topic_caps entry {entry!r}: expected TOPIC=BYTES with a known topic"
                ) from None
            if out[name] <= 0:
                raise ValueError(f"topic_caps entry {entry!r}: the cap must be positive")
        return out


class OneLineParser(argparse.ArgumentParser):
    """argparse that refuses bad input in one line (``PROG: what is wrong``), exit code 2."""

    def error(self, message: str):  # type: ignore[override]
        refuse(self.prog, f"{message} (see {self.prog} --help)")


def refuse(prog: str, message: str) -> NoReturn:
    """Bad input: one line on stderr naming what is wrong, exit code 2 (docs/cli.md); characters that
    do not print (a newline in a value) are shown escaped, so it stays one line."""
    line = "".join(c if c.isprintable() else repr(c)[1:-1] for c in f"{prog}: {message}")
    print(line, file=sys.stderr)
    raise SystemExit(2)


class _RefusedError(Exception):
    """tyro is about to refuse the command line: the one line to print instead of its box."""


def _flag(arg: Any) -> str:
    lowered = arg.lowered
    name = "/".join(lowered.name_or_flags) or str(lowered.metavar)
    return f"{name} {lowered.metavar}" if lowered.metavar and lowered.name_or_flags else name


def _one_line(event: Any) -> None:
    """tyro's parse-error hook (tyro pinned: the hook is private API): raise the event as one line;
    events not known here fall through to tyro's own box (still exit code 2)."""
    from tyro import _errors as e  # deferred: private tyro API, reached only once _parse_error_hook found it

    if isinstance(event, e.InstantiationFailure):  # a bad value, or the config's own checks
        message = event.message.strip().splitlines()[0] if event.message.strip() else "invalid value"
        raise _RefusedError(message if event.argument is None else f"{_flag(event.argument)}: {message}")
    if isinstance(event, e.UnrecognizedArgs):
        raise _RefusedError(f"unrecognized option(s) {' '.join(event.tokens)} (see {event.prog} --help)")
    if isinstance(event, e.InvalidChoice):
        choices = ", ".join(event.choices)
        raise _RefusedError(f"{_flag(event.argument)}: {event.value!r} is not one of {choices}")
    if isinstance(event, e.BadValue):
        got = "" if event.offending_value is None else f", not {event.offending_value!r}"
        raise _RefusedError(f"{_flag(event.argument)}: needs a value of that form{got}")
    if isinstance(event, e.MissingArgs):
        raise _RefusedError("missing " + ", ".join(_flag(a.arg) for a in event.missing_arguments))


def cli(cls: type[C], argv: Sequence[str], prog: str, description: str, default: C | None = None) -> C:
    """``tyro.cli`` whose refusals are one line (``prog: what is wrong``) with exit code 2, like every
    other refusal of bad input; ``--help`` is one line per option (`help_text`)."""
    args = list(argv)
    if any(a in HELP_FLAGS for a in (args[: args.index("--")] if "--" in args else args)):  # as tyro
        print(help_text(cls, prog, description, default))
        raise SystemExit(0)
    if repeated := repeated_flags(cls, args, default):
        refuse(prog, f"{repeated[0]} given more than once; give all its values after one {repeated[0]}")
    try:
        with _parse_error_hook(_one_line):
            return tyro.cli(cls, prog=prog, description=description, args=list(argv), default=default)
    except _RefusedError as exc:
        refuse(prog, str(exc))
    except ValueError as exc:  # the checks of a config tyro builds past its hook (a union's member)
        refuse(prog, str(exc).strip().splitlines()[0] if str(exc).strip() else "invalid value")


def _parser(cls: type, prog: str = "", description: str = "", default: Any = None) -> argparse.ArgumentParser:
    with warnings.catch_warnings():  # tyro's flags, metavars and groups (get_parser: tyro pinned)
        warnings.simplefilter("ignore", DeprecationWarning)
        return tyro.extras.get_parser(
            cls,
            prog=prog,
            description=description,
            default=default,
            config=(tyro.conf.HelptextFromCommentsOff,),
        )  # `#` comments explain the code; only docstrings are help


_COLLECTING = ("_AppendAction", "_AppendConstAction", "_ExtendAction", "_CountAction")


def repeated_flags(cls: type, argv: Sequence[str], default: Any = None) -> list[str]:
    """The options of ``cls`` that take a list of values and are given more than once in ``argv``
    (before a ``--``): argparse keeps the last list and drops the others without a word. A scalar
    given twice is left to the usual rule, the last one wins (wrappers append overrides that way);
    options that collect every occurrence (``tyro.conf.UseAppendAction``) are not counted."""
    args = list(argv)
    args = args[: args.index("--")] if "--" in args else args
    names = [a.split("=", 1)[0] for a in args if a.startswith("--")]
    if len(names) == len(set(names)):
        return []  # the usual case, without building the parser
    lists = {
        flag
        for action in _parser(cls, default=default)._actions
        if type(action).__name__ not in _COLLECTING  # tyro vendors its own argparse: by name
        and (action.nargs in ("*", "+") or (isinstance(action.nargs, int) and action.nargs > 1))
        for flag in action.option_strings
    }
    seen: dict[str, int] = {}
    for flag in names:
        if flag in lists:
            seen[flag] = seen.get(flag, 0) + 1
    return [flag for flag, n in seen.items() if n > 1]


HELP_FLAGS = ("-h", "--help")
HELP_DEFAULT_CHARS = 32
"""Longer defaults are cut in ``--help`` (the saved config.json holds every value)."""


def help_text(cls: type, prog: str, description: str, default: Any = None) -> str:
    """``--help``: each option's flags, the first line of its docstring and its default on one line,
    grouped as tyro groups them (docs/options.md has the details). tyro's own boxed help wraps every
    docstring whole and pads every line, four times the bytes for the same options."""
    parser = _parser(cls, prog, description, default)
    out = [f"usage: {prog} [-h] [OPTIONS]", ""]
    out += [description, ""] if description else []
    for group in parser._action_groups:
        actions = [a for a in group._group_actions if a.help != argparse.SUPPRESS]
        if not actions:
            continue
        about = _first_line(group.description or "")
        out.append(f"{group.title}:" + (f" {about}" if about else ""))
        for action in actions:
            out.append(_option_line(action))
        out.append("")
    return "\n".join(out).rstrip() + "\n"


def _first_line(text: str) -> str:
    return text.strip().split("\n", 1)[0].strip()


def _paired(flags: Sequence[str]) -> list[str]:
    """A boolean's ``--x.flag, --x.no-flag`` as ``--x.[no-]flag``."""
    if len(flags) == 2:
        on, off = flags
        head, dot, leaf = on.rpartition(".")
        prefix, leaf = (head + dot, leaf) if dot else ("--", on[2:])
        if off == f"{prefix}no-{leaf}":
            return [f"{prefix}[no-]{leaf}"]
    return list(flags)


def _option_line(action: argparse.Action) -> str:
    flags = ", ".join(_paired(action.option_strings)) or str(action.metavar or action.dest)
    if action.option_strings and action.metavar and action.nargs != 0:
        flags += f" {action.metavar}"
    text = (action.help or "").replace("%%", "%").strip()  # argparse escapes % in help
    hint = ""
    if text.endswith(")") and "(default: " in text:  # tyro appends the default to the whole docstring
        text, _, value = text.rpartition("(default: ")
        value = value[:-1]
        if len(value) > HELP_DEFAULT_CHARS:
            value = value[: HELP_DEFAULT_CHARS - 3] + "..."
        hint = f" (default: {value})"
    return f"  {flags:<26} {_first_line(text)}{hint}".rstrip()


def _parse_error_hook(hook):
    try:
        from tyro._errors import on_parse_error  # deferred: private tyro API that another tyro may lack
    except ImportError:  # another tyro: its own error boxes
        return contextlib.nullcontext()
    return on_parse_error(hook)


def presets_line(presets: Mapping[str, Any]) -> str:
    """The ``--help`` line naming a command's presets ("" when it has only its default)."""
    if len(presets) < 2:
        return ""
    return (f"Presets (--preset NAME, read before the other flags): {', '.join(presets)}; "
            f"default {next(iter(presets))}.")  # fmt: skip


def parse(cls: type[C], presets: Mapping[str, C], argv: Sequence[str], prog: str, description: str) -> C:
    """Parse ``[--preset NAME] [field flags...]`` into a frozen config; bad input (a flag, a value or
    the config's own checks in ``__post_init__``) is refused in one line, exit code 2."""
    pre = OneLineParser(prog=prog, add_help=False)
    pre.add_argument("--preset", choices=list(presets), default=next(iter(presets)))
    known, rest = pre.parse_known_args(list(argv))
    desc = "\n\n".join(filter(None, (description, presets_line(presets))))
    return cli(cls, rest, prog, desc, default=presets[known.preset])


def override(cfg: C, flags: str, what: str) -> C:
    """``cfg`` with command-line ``flags`` (one string, shell-quoted, e.g. ``"--sac.bc-weight 0"``)
    applied by the same parser as the service's own command; ValueError with tyro's one-line reason
    (``what`` names the option) on a bad flag, and nothing printed."""
    args = shlex.split(flags)
    if not args:
        return cfg
    buf = io.StringIO()
    try:
        with contextlib.redirect_stderr(buf), contextlib.redirect_stdout(buf):
            return tyro.cli(type(cfg), args=args, default=cfg, prog=what)
    except SystemExit:
        # tyro's message box: its first line with a colon says what is wrong
        lines = [ln.strip(" │|-─╭╮╰╯") for ln in buf.getvalue().splitlines()]
        reason = next((ln for ln in lines if ": " in ln), "bad flags")
        raise ValueError(f"{what} {flags!r}: {reason}") from None
    except ValueError as exc:  # the checks of a config tyro builds past its box (a union's member)
        raise ValueError(f"{what} {flags!r}: {str(exc).strip().splitlines()[0]}") from None


def to_jsonable(cfg: Any) -> Any:
    if dataclasses.is_dataclass(cfg):
        return {f.name: to_jsonable(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_jsonable(v) for v in cfg]
    if isinstance(cfg, Path):
        return str(cfg)
    return cfg


def save(cfg: Any, path: Path) -> None:
    """Write the resolved config as JSON (atomically)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(to_jsonable(cfg), indent=2, sort_keys=True) + "\n")
    tmp.replace(path)
