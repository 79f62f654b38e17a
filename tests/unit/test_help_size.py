"""Every `mea` command's `--help` stays a page: at most 8 KB, one short line per option, each option
once (docs/options.md holds the details)."""

from __future__ import annotations

import dataclasses
import importlib
import re

import pytest

from services.cli import COMMANDS, available
from services.common import config
from tests.helpers.cli import run_cli

pytestmark = pytest.mark.unit

MAX_HELP_BYTES = 8 * 1024
MAX_SUMMARY_CHARS = 100
"""An option's help (its docstring, without the default) longer than this is not a summary."""
MAX_LINE_CHARS = 180


def help_commands() -> list[list[str]]:
    """Every command line whose `--help` a user can ask for: each command under each of its presets,
    each benchmark, each recording action."""
    out: list[list[str]] = []
    for name, (module_name, _) in COMMANDS.items():
        if not available(name):
            continue
        module = importlib.import_module(module_name)
        out.append([name])
        presets = getattr(module, "PRESETS", {})
        out += [[name, "--preset", preset] for preset in list(presets)[1:]]
        out += [[name, bench] for bench in getattr(module, "BENCHES", {})]
    out.append(["recording", "check"])
    return out


def problems(options: list[tuple[str, str]]) -> list[str]:
    """What is wrong with the (flags, help) of one command's options: a help over one line or longer
    than a summary, or a flag shown twice (a nested config printed again)."""
    out, seen = [], set()
    for flags, text in options:
        summary = re.sub(r"\s*\(default: .*\)$", "", text, flags=re.S)
        if "\n" in summary.strip():
            out.append(f"{flags}: help of {len(summary.splitlines())} lines")
        if len(summary) > MAX_SUMMARY_CHARS:
            out.append(f"{flags}: help of {len(summary)} characters")
        for flag in flags.split(", "):
            if flag in seen:
                out.append(f"{flag}: shown twice")
            seen.add(flag)
    return out


@pytest.fixture
def recorded(monkeypatch):
    """The (flags, help) of every option `--help` renders, as tyro built them."""
    options: list[tuple[str, str]] = []
    line = config._option_line

    def record(action):
        options.append((", ".join(action.option_strings), (action.help or "").strip()))
        return line(action)

    monkeypatch.setattr(config, "_option_line", record)
    return options


@pytest.mark.parametrize("argv", help_commands(), ids=" ".join)
def test_help_is_a_page_of_one_line_options(argv, capsys, monkeypatch, recorded):
    monkeypatch.setenv("COLUMNS", "80")  # argparse-based commands wrap at the terminal's width
    code, out, err = run_cli([*argv, "--help"], capsys)
    assert code == 0 and out.startswith("usage:"), (code, err)
    assert len(out.encode()) <= MAX_HELP_BYTES, f"mea {' '.join(argv)} --help: {len(out.encode())} bytes"
    assert max(map(len, out.splitlines())) <= MAX_LINE_CHARS
    assert problems(recorded) == []


@dataclasses.dataclass(frozen=True)
class Inner:
    """An inner group."""

    rate: float = 0.5
    """A rate whose docstring goes on
    over a second line."""


@dataclasses.dataclass(frozen=True)
class Planted:
    """A planted config: a two-line option help and a long default."""

    sizes: tuple[int, ...] = tuple(range(40))
    """Sizes."""
    inner: Inner = Inner()
    """An inner group."""


def test_the_checks_catch_a_long_help_and_a_flag_shown_twice(recorded):
    text = config.help_text(Planted, "mea planted", "A planted config.", Planted())
    assert "  --inner.rate FLOAT" in text and "A rate whose docstring goes on (default: 0.5)" in text
    assert "over a second line" not in text  # one line per option whatever the docstring
    default = re.search(r"--sizes .*\(default: (.*)\)", text)
    assert default and len(default.group(1)) == config.HELP_DEFAULT_CHARS and default.group(1).endswith("...")
    assert problems(recorded) == ["--inner.rate: help of 2 lines"]
    assert problems([("--x", "short"), ("--y, --x", "short")]) == ["--x: shown twice"]
    assert problems([("--z", "z" * (MAX_SUMMARY_CHARS + 1) + " (default: 1)")]) == [
        "--z: help of 101 characters"
    ]


def test_booleans_are_shown_as_one_flag_pair():
    assert config._paired(["--resume", "--no-resume"]) == ["--[no-]resume"]
    assert config._paired(["--sac.bc-filter", "--sac.no-bc-filter"]) == ["--sac.[no-]bc-filter"]
    assert config._paired(["--zenoh-config", "--service.zenoh.config-file"]) == [
        "--zenoh-config",
        "--service.zenoh.config-file",
    ]
