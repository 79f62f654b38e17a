"""`mea bench compare`: two or more arms of finished (or partly finished) training runs side by side,
with the learning bench's statistics, where the arms came from different benches or commands (a
recipe change against the runs it changes, e.g. ``--arms box=runs/bench-d2-mea
disc=runs/bench-d2-mea-disc``).

Each arm is a label and directories: a run directory (``mea run``'s, with its ``config.json``) or a
directory of them (a ``mea bench learning --out``). The arms must share what decides the numbers
being compared (task, budget, demos, random steps, gripper start, evaluation episodes); what differs
between them is printed first, so a table never hides which change it measures. Nothing is written
unless ``--out`` is given."""

from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mea_tools.bench import stats
from mea_tools.bench.learning import summarize
from mea_tools.bench.report import emit

SAME = ("task", "env_steps", "demos", "random_steps", "gripper_start", "eval_episodes", "final_eval_episodes")
"""Run settings every run of every arm must share: the budget and what each evaluation measures."""
RECIPE = ("variant", "mea_on", "learner_preset", "learner_args", "success_rotations", "init_actor", "actors",
          "envs_per_actor", "eval_every", "follow_gate")  # fmt: skip
"""Run settings an arm is defined by: one value per arm, shown where the arms differ."""
CONFIG = "config.json"


@dataclass(frozen=True)
class CompareBenchConfig:
    """Compare arms of training runs: success at the budget, AUC, P(improvement) against the first arm."""

    arms: tuple[str, ...] = ()
    """LABEL=DIR[,DIR...] per arm, the first the baseline; DIR a run directory or a directory of them."""
    at_env_steps: int = 0
    """Compare success at the first evaluation at or past this many env steps (0: the runs' budget)."""
    out: Path | None = None
    """Directory for the curves PNG and the result JSON; None: print only."""
    json: bool = False
    """Print exactly one JSON object instead of tables."""
    bootstrap_reps: int = 10_000
    """Stratified-bootstrap resamples per interval."""
    bootstrap_seed: int = 0
    """Seed of the bootstrap (the same seed and runs give the same intervals)."""


def _refuse(msg: str) -> SystemExit:
    return SystemExit(f"mea bench compare: {msg}")


def _run_dirs(path: Path) -> list[Path]:
    """``path`` if it is a run directory, else the run directories directly inside it, by name."""
    if (path / CONFIG).is_file():
        return [path]
    return sorted(p for p in path.iterdir() if (p / CONFIG).is_file()) if path.is_dir() else []


@functools.cache
def _defaults() -> dict[str, Any]:
    """`mea run`'s defaults, for settings a run saved before they existed."""
    from services.run_config import RunConfig  # deferred: it pulls in torch and pybullet

    return json.loads(json.dumps(dataclasses.asdict(RunConfig()), default=str))


def _config(run_dir: Path) -> dict[str, Any]:
    """The run's saved settings, each missing one at `mea run`'s default."""
    try:
        cfg = json.loads((run_dir / CONFIG).read_text())
    except (OSError, ValueError) as exc:
        raise _refuse(f"{run_dir / CONFIG}: not a run's config ({exc})") from None
    if not isinstance(cfg, dict) or "task" not in cfg or "env_steps" not in cfg:
        raise _refuse(f"{run_dir / CONFIG}: not a run's config (no task or env_steps)")
    return _defaults() | cfg


def parse_arms(specs: tuple[str, ...]) -> dict[str, list[Path]]:
    """{label: run directories} from LABEL=DIR[,DIR...] specs; SystemExit naming the bad one."""
    if len(specs) < 2:
        raise _refuse("give at least two --arms, each LABEL=DIR[,DIR...] (the first is the baseline)")
    arms: dict[str, list[Path]] = {}
    for spec in specs:
        label, sep, dirs = spec.partition("=")
        if not sep or not label or not dirs:
            raise _refuse(f"--arms takes LABEL=DIR[,DIR...], got {spec!r}")
        if label in arms:
            raise _refuse(f"arm {label!r} given twice")
        found: list[Path] = []
        for d in dirs.split(","):
            runs = _run_dirs(Path(d))
            if not runs:
                raise _refuse(f"arm {label!r}: {d} is neither a run directory nor a directory of them")
            found += runs
        if len({p.resolve() for p in found}) != len(found):
            raise _refuse(f"arm {label!r} lists a run directory twice")
        arms[label] = found
    every = [p.resolve() for runs in arms.values() for p in runs]
    if len(set(every)) != len(every):
        raise _refuse("a run directory is in two arms")
    return arms


def check_arms(
    arms: dict[str, list[Path]], configs: dict[str, list[dict[str, Any]]]
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """(the settings all runs share, one row per recipe setting where the arms differ) from each
    arm's run directories and their ``configs``; SystemExit when runs differ in a ``SAME`` setting
    or an arm mixes recipes."""
    first = next(iter(configs.values()))[0]
    shared = {k: first.get(k) for k in SAME}
    for label, cfgs in configs.items():
        for d, cfg in zip(arms[label], cfgs, strict=True):
            for k in SAME:
                if cfg.get(k) != shared[k]:
                    raise _refuse(f"{d} has {k} {cfg.get(k)!r}, the other runs {shared[k]!r}: "
                                  "arms must share the budget and what an evaluation measures")  # fmt: skip
            for k in RECIPE:
                if cfg.get(k) != cfgs[0].get(k):
                    raise _refuse(
                        f"arm {label!r} mixes runs with {k} {cfgs[0].get(k)!r} and {cfg.get(k)!r} ({d})"
                    )
    differ = []
    for k in RECIPE:
        values = {label: cfgs[0].get(k) for label, cfgs in configs.items()}
        if len({json.dumps(v, sort_keys=True) for v in values.values()}) > 1:
            differ.append({"setting": k, **{label: v for label, v in values.items()}})
    return shared, differ


def _seed_rows(arms: dict[str, list[Path]], configs: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    return [{"arm": label, "runs": len(dirs), "seeds": sorted(c.get("seed") for c in configs[label]),
             "directories": ", ".join(str(d) for d in dirs)} for label, dirs in arms.items()]  # fmt: skip


def run(cfg: CompareBenchConfig) -> dict:
    if cfg.bootstrap_reps < 1:
        raise _refuse(f"--bootstrap-reps must be >= 1, not {cfg.bootstrap_reps}")
    if cfg.at_env_steps < 0:
        raise _refuse(f"--at-env-steps must be >= 0 (0: the runs' budget), not {cfg.at_env_steps}")
    if cfg.out is not None and cfg.out.exists() and not cfg.out.is_dir():
        raise _refuse(f"--out {cfg.out} is a file, not a directory")
    arms = parse_arms(cfg.arms)
    configs = {label: [_config(d) for d in dirs] for label, dirs in arms.items()}
    shared, differ = check_arms(arms, configs)
    if not differ:
        differ = [
            {
                "setting": "(none of the recipe settings)",
                "note": "the arms differ only in their seeds or code",
            }
        ]
    if cfg.out is not None:
        cfg.out.mkdir(parents=True, exist_ok=True)
    boot = stats.Bootstrap(reps=cfg.bootstrap_reps, seed=cfg.bootstrap_seed)
    sections = {"what differs between the arms": differ, "arms": _seed_rows(arms, configs)}
    learner = f"{next(iter(configs.values()))[0].get('learner_preset')} (per arm: see what differs)"
    # "at budget" below means at this point (the evaluations of runs still training are 20-seed ones)
    at = cfg.at_env_steps or int(shared["env_steps"])
    sections |= summarize(str(shared["task"]), arms, at, cfg.out, learner, boot)
    sections.pop("training loop against the public Equi-RSAC code", None)  # wall times of other loads
    meta = {"shared settings": shared, "arms": list(arms), "baseline": next(iter(arms)), "success at env steps": at,
            "bootstrap": {"reps": boot.reps, "confidence": boot.confidence, "seed": boot.seed,
                          "method": "rliable stratified bootstrap, percentile"},
            "out": None if cfg.out is None else str(cfg.out)}  # fmt: skip
    result = emit("compare", sections, measured={}, as_json=cfg.json, meta=meta)
    if cfg.out is not None:
        (cfg.out / f"result-{shared['task']}.json").write_text(
            json.dumps(result, indent=2, default=float) + "\n"
        )
    return result
