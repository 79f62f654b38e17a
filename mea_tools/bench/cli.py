"""`mea bench NAME`: benchmarks that print a table, or exactly one JSON object with --json."""

from __future__ import annotations

import importlib
import signal
import sys
from collections.abc import Sequence

from services.common import config

# name -> (module, config class, help); each module has run(cfg) -> dict
BENCHES: dict[str, tuple[str, str, str]] = {
    "transport": (
        "mea_tools.bench.transport",
        "TransportBenchConfig",
        "wire codec and Zenoh transport speeds",
    ),
    "augment": (
        "mea_tools.bench.augment",
        "AugmentBenchConfig",
        "augmented transitions/s per core including re-projection, and raw-in to augmented-out latency",
    ),
    "learner": (
        "mea_tools.bench.learner",
        "LearnerBenchConfig",
        "gradient updates/s per preset, replay memory, weights publish -> loaded latency",
    ),
    "learning": (
        "mea_tools.bench.learning",
        "LearningBenchConfig",
        "train EquiRSAC / EquiObs / MEA variants: success at budget, improvement timestep, AUC, wall time, curves",
    ),
    "critic": (
        "mea_tools.bench.critic",
        "CriticBenchConfig",
        "a run's critic along its replay: Q of the recorded, turned, reversed, random and policy actions per step",
    ),
    "compare": (
        "mea_tools.bench.compare",
        "CompareBenchConfig",
        "arms of training runs from different benches side by side: success at budget, AUC, P(improvement)",
    ),
    "reach": (
        "mea_tools.bench.reach",
        "ReachBenchConfig",
        "the RL core against a known answer: recurrent SAC on a sparse-reward 2D reach, by state or pixels",
    ),
    "imitation": (
        "mea_tools.bench.imitation",
        "ImitationBenchConfig",
        "behaviour cloning of N scripted demos into the run's actor: held-out success per N and training seed",
    ),
    "system": (
        "mea_tools.bench.system",
        "SystemBenchConfig",
        "raw vs full-stack env steps/s, augmenter and learner rates, weights publish -> loaded",
    ),
    "soak": (
        "mea_tools.bench.soak",
        "SoakBenchConfig",
        "an hour of `mea run`: RSS of every service after warm-up and at the end (growth < 5%)",
    ),
    "tasks": (
        "mea_tools.bench.tasks",
        "TasksBenchConfig",
        "scripted-expert success, env steps/s and the transition prior per task",
    ),
    "serve": (
        "mea_tools.bench.serve",
        "ServeBenchConfig",
        "inference server act() round trip and server time per actor preset, weights swap -> first action",
    ),
}


def main(argv: Sequence[str]) -> int:
    args = list(argv)
    if not args or args[0] in ("-h", "--help"):
        print("usage: mea bench NAME [OPTIONS] [--json]\n\nbenchmarks:")
        for name, (_, _, text) in BENCHES.items():
            print(f"  {name:<10} {text}")
        return 0
    name = args[0]
    if name not in BENCHES:
        print(f"mea bench: unknown benchmark {name!r} (choose from {', '.join(BENCHES)})", file=sys.stderr)
        return 2
    module_name, cls_name, text = BENCHES[name]
    module = importlib.import_module(module_name)
    cfg = config.cli(getattr(module, cls_name), args[1:], f"mea bench {name}", text)
    previous = signal.signal(signal.SIGTERM, _interrupt)  # a kill stops the bench's children as Ctrl-C does
    try:
        module.run(cfg)
    except KeyboardInterrupt:  # Ctrl-C: one line, not a traceback (runs it started resume on a rerun)
        print(f"mea bench {name}: interrupted", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0


def _interrupt(signum: int, _frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")
