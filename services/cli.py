"""`mea`: one subcommand per service, the local launcher, and tools (benchmarks, audits, demos)."""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Sequence

# command -> (module with main(argv) -> int | None, one-line help)
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
        "services.bench.audit",
        "replay augmented episodes through physics and report their validity",
    ),
    "demos": ("services.actor.demos", "record scripted demonstrations of a task to an MCAP file"),
    "bench": ("services.bench.cli", "benchmarks that print tables (or one JSON object with --json)"),
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


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    command = args[0]
    if command not in COMMANDS:
        print(f"mea: unknown command {command!r}\n\n{usage()}", file=sys.stderr)
        return 2
    if not available(command):
        print(f"mea: `{command}` is not part of this build yet", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[command][0])
    code = module.main(args[1:])
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
