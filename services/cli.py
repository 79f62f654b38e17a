"""`mea`: one subcommand per service, the local launcher, and tools (benchmarks, audits, demos)."""

from __future__ import annotations

import contextlib
import importlib
import importlib.metadata
import importlib.util
import os
import sys
from collections.abc import Sequence

DISTRIBUTION = "mea-rl"
"""The package `mea --version` reports (pyproject.toml's name)."""

# command -> (module with main(argv) -> int | None, one-line help)
# Modules are named, imported only when their command runs: the CLI stays below the tools (mea_tools).
COMMANDS: dict[str, tuple[str, str]] = {
    "run": (
        "services.launcher",
        "run the whole stack on this machine (router + services as separate processes)",
    ),
    "router": ("services.router", "run a Zenoh router for services on other processes or hosts"),
    "actor": ("services.actor.main", "run one actor: simulate a task and publish whole episodes"),
    "augmenter": ("services.augmenter.main", "run the MEA augmenter on raw episodes"),
    "learner": ("services.learner.main", "train Equi-RSAC / GASv2 and broadcast weights"),
    "evaluator": ("services.evaluator.main", "evaluate broadcast weights on held-out seeds"),
    "serve": ("services.inference.main", "serve the newest policy to robots, behind a safety envelope"),
    "robot": ("services.inference.robot", "drive an arm (--sim: a simulated task) through `mea serve`"),
    "operator": ("services.inference.operator", "hold the operator's e-stop (robots hold when it goes away)"),
    "plot": (
        "services.evaluator.plot",
        "render learning curves (success vs env steps, mean ± std over seeds) to PNG",
    ),
    "audit": (
        "mea_tools.audit.cli",
        "replay augmented episodes through physics and report their validity",
    ),
    "play": ("services.play", "render a trained policy or recorded episodes to an MP4 or GIF"),
    "demos": ("services.actor.demos", "record scripted demonstrations of a task to an MCAP file"),
    "recording": (
        "services.recording_check",
        "`mea recording check PATH...`: messages, channels, time range, whole or damaged",
    ),
    "bench": ("mea_tools.bench.cli", "benchmarks that print tables (or one JSON object with --json)"),
}


def available(command: str) -> bool:
    module = COMMANDS[command][0]
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


def usage() -> str:
    lines = [
        "usage: mea COMMAND [--preset NAME] [OPTIONS]   (mea COMMAND --help for options)",
        "",
        "commands:",
    ]
    for name, (_, text) in COMMANDS.items():
        mark = "" if available(name) else "   [not in this build yet]"
        lines.append(f"  {name:<10} {text}{mark}")
    return "\n".join(lines)


def version() -> str:
    """The installed package's version (its metadata), else "unknown" (a source tree not installed)."""
    try:
        return importlib.metadata.version(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def os_error(exc: OSError) -> str:
    """An OS error as one line: what failed, on which path (no traceback)."""
    what = exc.strerror or str(exc) or type(exc).__name__
    paths = [str(p) for p in (exc.filename, exc.filename2) if p is not None]
    return f"{what}: {' -> '.join(paths)}" if paths else what


def main(argv: Sequence[str] | None = None) -> int:
    """Exit codes (docs/cli.md): 0 done, 1 failed while running (an OS error, a service that kept
    failing), 2 refused (bad input; nothing written)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:  # a bare `mea` did nothing it was asked to
        print(usage(), file=sys.stderr)
        return 2
    if args[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    if args[0] in ("-V", "--version"):
        print(f"mea {version()}")
        return 0
    command = args[0]
    if command not in COMMANDS:
        print(
            f"mea: unknown command {command!r}; choose from {', '.join(COMMANDS)} (mea --help)",
            file=sys.stderr,
        )
        return 2
    if not available(command):
        print(f"mea: `{command}` is not part of this build yet", file=sys.stderr)
        return 2
    try:
        module = importlib.import_module(COMMANDS[command][0])
        code = module.main(args[1:])
    except BrokenPipeError:  # stdout closed early (`mea run --help | head`): nothing left to say
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as exc:
        print(f"mea {command}: {os_error(exc)}", file=sys.stderr)
        return 1
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
