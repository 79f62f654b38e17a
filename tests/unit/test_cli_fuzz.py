"""Random command lines for every `mea` subcommand (hypothesis: options, values of every type, paths
good and bad), run in this process through ``services.cli.main``: never a traceback, exit code 0, 1
or 2 with a message (one line when refused), no file created or changed outside the test's directory
(an audit hook sees every open for writing, mkdir, rename and removal), no process or thread left.

What would start a service, a training run, a benchmark or a recording is replaced by a function
that raises ``StartedError``: a command line that gets there was accepted (valid) and ran every check
the command makes before starting anything."""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import io
import json
import math
import os
import sys
import threading
import typing
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mea_tools.bench.cli import BENCHES
from services.cli import COMMANDS, main
from services.common import config
from services.run_config import RunConfig

MIN_CASES = 2000
"""Command lines in all, across subcommands."""

TOOLS = {"plot", "recording"}
"""Commands that only read files and return: run as they are."""

CONFIGS = {
    "run": "services.run_config:RunConfig",
    "router": "services.router:RouterConfig",
    "actor": "services.actor.config:ActorConfig",
    "augmenter": "services.augmenter.config:AugmenterConfig",
    "learner": "services.learner.config:LearnerConfig",
    "evaluator": "services.evaluator.config:EvaluatorConfig",
    "serve": "services.inference.config:ServeConfig",
    "robot": "services.inference.robot:RobotConfig",
    "operator": "services.inference.operator:OperatorConfig",
    "audit": "mea_tools.audit.config:AuditConfig",
    "demos": "services.actor.demos:DemosConfig",
}
STARTS = {
    "run": ["services.launcher:run"],
    "router": ["services.router:run"],
    "actor": ["services.actor.main:run"],
    "augmenter": ["services.augmenter.main:run"],
    "learner": ["services.learner.main:run"],
    "evaluator": ["services.evaluator.main:run"],
    "serve": ["services.inference.main:run"],
    "robot": ["services.inference.robot:run", "services.inference.robot:SimRobot"],
    "operator": ["services.inference.operator:run"],
    "audit": ["mea_tools.audit.cli:run_audit"],
    "demos": ["services.actor.demos:record"],
    "bench": [f"{module}:run" for module, _, _ in BENCHES.values()],
    "play": ["services.play:write_video"],  # every check ran: the video was about to be written
}
"""What each command calls to start its long-running work (replaced in these tests)."""

PATHS = ["afile", "afile/x.mcap", "adir", "adir/new", "adir/new/deeper/x.mcap", "run_ok", "run_list", "run_42",
         "missing", "missing/x.json", ".", "", "out.png", "x.mcap", "ünï cøde dir/ x", "limits.json",
         "/proc/version", "/proc/version/x", "/sys/mea-fuzz/x", "/sys/mea-fuzz.mcap"]  # fmt: skip
"""Paths a case may name: under the test's directory, or absolute where even root cannot write."""
TOKENS = ["None", "none", "true", "false", "True", "0", "1", "-1", "2", "3", "10", "1e309", "nan", "inf", "-inf",
          "0x10", "1_000", "9" * 30, "-", "--", "=", "tcp/127.0.0.1:1", "tcp/127.0.0.1:99999", "tcp/", "udp/x:1",
          "paper", "smoke", "cpu-small", "cpu-small-state", "gasv2", "block_pull", "block_pick", "drawer_open",
          "surgical_grasp_any", "mea", "equiobs", "equirsac", "mea-gasv2", "json", "text", "cuda", "cpu",
          "learner", "actor", "evaluator", "augmenter", "demos", "successes", "all", "client", "peer", "router",
          "episodes_raw=100", "episodes_raw=-1", "nope=1", "x:y", "os:getcwd", "DEBUG", "INFO"]  # fmt: skip
GARBAGE_FLAGS = ["--bogus", "-x", "--", "-h", "--help", "--preset", "--service", "--service.", "--=1", "---x",
                 "--task=", "--actors=2", "--env-steps=-1", "--no-", "--run-dir="]  # fmt: skip


def _resolve(spec: str):
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def flags_of(cls: type, prefix: str = "") -> dict[str, list[str]]:
    """{flag: candidate values} for every field of a config dataclass, nested ones dotted (tyro's
    spelling); the candidates start with the field's default, so some command lines are valid."""
    hints = typing.get_type_hints(cls)
    out: dict[str, list[str]] = {}
    for f in dataclasses.fields(cls):
        name = prefix + f.name.replace("_", "-")
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            out |= flags_of(hint, name + ".")
            continue
        default = f.default if f.default is not dataclasses.MISSING else None
        if hint is bool:
            leaf = name.rpartition(".")
            out[f"--{name}"] = []
            out[f"--{leaf[0]}{leaf[1]}no-{leaf[2]}"] = []
            continue
        if isinstance(default, tuple):
            values = [" ".join(map(str, default))] if default else []
        else:
            values = [] if default is None else [str(default)]
        out[f"--{name}"] = values
    return out


def command_flags(command: str) -> dict[str, list[str]]:
    if command in CONFIGS:
        return flags_of(_resolve(CONFIGS[command]))
    if command == "plot":
        return {
            "--out": ["out.png"],
            "--label-by": ["variant"],
            "--interp": ["hold", "linear"],
            "--title": ["t"],
        }
    if command == "play":
        return {"--out": ["out.mp4", "x.gif"], "--recording": ["x.mcap", "afile"], "--version": ["1"],
                "--episodes": ["1"], "--seed": ["0"], "--task": ["block_pull"], "--size": ["128"],
                "--fps": ["10"], "--no-replay": []}  # fmt: skip
    return {}


def value(candidates: list[str]) -> st.SearchStrategy[str]:
    choices = [st.sampled_from(TOKENS), st.sampled_from(PATHS), st.integers(-(2**70), 2**70).map(str),
               st.floats(allow_nan=True, allow_infinity=True).map(repr),
               st.text(st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",)), max_size=12)]  # fmt: skip
    if candidates:
        choices = [st.sampled_from(candidates)] * 3 + choices
    return st.one_of(choices)


@st.composite
def argv_of(draw, command: str, flags: dict[str, list[str]], bench_flags: dict[str, dict[str, list[str]]]):
    """A command line for ``command``: a few options (known, garbage or positional) with 0-2 values."""
    head: list[str] = []
    if command == "bench":
        name = draw(st.sampled_from([*BENCHES, "nope", "--help"]))
        head, flags = [name], bench_flags.get(name, {})
    elif command == "recording":
        head = [draw(st.sampled_from(["check", "check", "check", "nope", "--help"]))]
    elif command in ("plot", "play"):
        head = draw(st.lists(st.sampled_from(PATHS), max_size=2))
    parts: list[str] = []
    if draw(st.integers(0, 9)) == 0:
        parts += ["--preset", draw(st.sampled_from(["default", "paper", "smoke", "nope"]))]
    names = sorted(flags)
    for _ in range(draw(st.integers(0, 5))):
        kind = draw(st.integers(0, 11))
        if kind < 9 and names:
            flag = draw(st.sampled_from(names))
            parts.append(flag)
            n = draw(st.sampled_from([1, 1, 1, 0, 2])) if flags[flag] or kind % 3 else draw(st.integers(0, 1))
            parts += [draw(value(flags[flag])) for _ in range(n)]
        elif kind < 11:
            parts.append(draw(st.sampled_from(GARBAGE_FLAGS)))
        else:
            parts.append(draw(value([])))
    return [command, *head, *parts]


class StartedError(Exception):
    """The command accepted its command line and was about to start."""


def started(*_args, **_kw):
    raise StartedError


WRITES = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND
PATH_EVENTS = {"os.mkdir": (0,), "os.remove": (0,), "os.rmdir": (0,), "os.truncate": (0,), "os.chmod": (0,),
               "os.chown": (0,), "os.utime": (0,), "os.rename": (0, 1), "os.replace": (0, 1), "os.link": (0, 1),
               "os.symlink": (0, 1), "shutil.rmtree": (0,), "shutil.copyfile": (0, 1), "shutil.move": (0, 1)}  # fmt: skip


class Watch:
    """An audit hook noting every path outside ``root`` that a case opens for writing, creates,
    renames, changes or removes, with its state before; ``outside()`` lists those that changed."""

    def __init__(self) -> None:
        self.root = ""
        self.notes: dict[str, tuple | None] = {}
        self.active = False
        sys.addaudithook(self._hook)

    @staticmethod
    def state(path: str) -> tuple | None:
        try:
            st_ = os.lstat(path)
        except OSError:
            return None
        return (st_.st_mode, st_.st_size, st_.st_mtime_ns)

    def _note(self, path: object) -> None:
        if isinstance(path, int) or path is None:
            return
        try:
            p = os.path.abspath(os.fsdecode(path))  # type: ignore[arg-type]
        except (TypeError, ValueError):
            return
        if p == self.root or p.startswith(self.root + os.sep) or p in self.notes:
            return
        self.notes[p] = self.state(p)

    def _hook(self, event: str, args: tuple) -> None:
        if not self.active:
            return
        if event == "open":
            path, mode, flags = args
            if (isinstance(flags, int) and flags & WRITES) or (
                isinstance(mode, str) and any(c in mode for c in "wax+")
            ):
                self._note(path)
        elif event in PATH_EVENTS:
            for i in PATH_EVENTS[event]:
                if i < len(args):
                    self._note(args[i])

    def outside(self) -> list[str]:
        """Paths outside ``root`` created, removed or changed (character devices like /dev/null aside)."""
        changed = []
        for p, before in self.notes.items():
            after = self.state(p)
            if before is not None and after is not None and before[0] & 0o170000 != 0o100000:
                continue  # an existing device or directory written through (e.g. /dev/null)
            if before != after:
                changed.append(p)
        return changed


WATCH = Watch()


def children() -> set[int]:
    """Child processes of this process."""
    pids: set[int] = set()
    for task in Path("/proc/self/task").iterdir():
        with contextlib.suppress(OSError):
            pids |= {int(x) for x in (task / "children").read_text().split()}
    return pids


def make_fixtures(root: Path) -> dict[str, dict]:
    """The files cases may name; returns their state, which no case may change."""
    from tests.helpers.tree import snapshot

    (root / "afile").write_text("a file, not a directory\n")
    (root / "adir").mkdir()
    config.save(RunConfig(task="drawer_open", env_steps=300, learner_preset="smoke", run_dir=root / "run_ok"),
                root / "run_ok" / "config.json")  # fmt: skip
    (root / "run_list").mkdir()
    (root / "run_list" / "config.json").write_text("[1, 2]\n")
    (root / "run_42").mkdir()
    (root / "run_42" / "config.json").write_text(json.dumps({"task": 42}) + "\n")
    (root / "limits.json").write_text(json.dumps({"default": {}}) + "\n")
    return {name: snapshot(root / name) for name in ("adir", "run_ok", "run_list", "run_42")}


def outcome(argv: list[str]) -> tuple[int | str, str, str]:
    """(exit code or "started", stdout, stderr) of ``mea ARGV`` in this process."""
    out, err = io.StringIO(), io.StringIO()
    code: int | str
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except StartedError:
            code = "started"
        except SystemExit as exc:
            if exc.code is None or isinstance(exc.code, int):
                code = exc.code or 0
            else:  # SystemExit("message"): Python prints the message, exit code 1
                code = 1
                print(exc.code, file=sys.stderr)
    return code, out.getvalue(), err.getvalue()


CASES = math.ceil(MIN_CASES / len(COMMANDS))


def test_the_watch_sees_what_is_written_outside_its_root(tmp_path):
    (tmp_path / "root").mkdir()
    (tmp_path / "kept.txt").write_text("x")
    WATCH.root, WATCH.notes, WATCH.active = str(tmp_path / "root"), {}, True
    try:
        (tmp_path / "root" / "inside.txt").write_text("fine")
        (tmp_path / "new.txt").write_text("outside")
        os.mkdir(tmp_path / "new-dir")
        (tmp_path / "kept.txt").read_text()  # reading is not writing
    finally:
        WATCH.active = False
    assert sorted(WATCH.outside()) == [str(tmp_path / "new-dir"), str(tmp_path / "new.txt")]


def test_every_command_is_fuzzed_and_the_cases_add_up():
    assert set(COMMANDS) == set(CONFIGS) | set(STARTS) | TOOLS
    assert CASES * len(COMMANDS) >= MIN_CASES


@pytest.mark.timeout(600)
@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.slow
def test_random_command_lines_never_crash_write_outside_or_leave_processes(command, tmp_path, monkeypatch):
    for spec in STARTS.get(command, []):
        module, _, name = spec.partition(":")
        monkeypatch.setattr(importlib.import_module(module), name, started)
    fixtures = make_fixtures(tmp_path)
    monkeypatch.chdir(tmp_path)
    bench_flags = {name: flags_of(_resolve(f"{m}:{c}")) for name, (m, c, _) in BENCHES.items()}
    flags = command_flags(command)
    processes, threads = children(), set(threading.enumerate())
    seen: dict[int | str, int] = {}

    @settings(max_examples=CASES, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(argv_of(command, flags, bench_flags))
    def case(argv: list[str]) -> None:
        WATCH.root, WATCH.notes, WATCH.active = str(tmp_path), {}, True
        try:
            code, out, err = outcome(argv)
        finally:
            WATCH.active = False
        seen[code] = seen.get(code, 0) + 1
        assert "Traceback" not in out + err, (argv, out, err)
        assert code in (0, 1, 2, "started"), (argv, code, err)
        if code in (1, 2):
            assert err.strip(), (argv, "no message")
        if code == 2:  # refused: one line naming what is wrong (`mea recording check`: one per path)
            lines = err.strip().splitlines()
            assert all(line.startswith("mea") for line in lines), (argv, err)
            assert len(lines) == 1 or command == "recording", (argv, err)
        assert WATCH.outside() == [], (argv, WATCH.outside())
        assert children() == processes, (argv, "a process was left behind")
        assert set(threading.enumerate()) <= threads, (argv, "a thread was left behind")

    case()
    from tests.helpers.tree import snapshot

    assert {name: snapshot(tmp_path / name) for name in fixtures} == fixtures  # no refusal changed a run
    assert seen.get(2, 0) > 0, seen  # bad input was generated and refused
