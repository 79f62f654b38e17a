"""`mea bench learning`: the paper's comparison, trained here: success at the budget and improvement
timestep of EquiRSAC, EquiObs-EquiRSAC and MEA-EquiObs-EquiRSAC (optionally MEA on every episode).

Each (variant, seed) is one whole `mea run` (its own processes and Zenoh router on a free 127.0.0.1
port, its own run directory), one after another, so every run gets the machine to itself. The
runs' evaluation histories give, per variant: success rate of the last evaluation at the budget
(mean ± std over seeds), the improvement timestep (first env-step count from which success stays
above 0), and the learning curves (``mea plot``) as a PNG. Runs already finished in the output
directory are reused (delete them to rerun), so an interrupted benchmark continues where it
stopped.

Presets: ``paper`` (40K env steps, 2 demos, 4 seeds, the paper learner preset: meant for a GPU
workstation) and ``cpu-small`` (8K env steps, 2 demos, 1 seed, the cpu-small learner: about an
hour for the three variants on 2 CPU cores).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.bench.report import emit

VARIANTS = {
    "equirsac": ["--variant", "equirsac"],
    "equiobs": ["--variant", "equiobs"],
    "mea": ["--variant", "mea"],
    "mea-all": ["--variant", "mea", "--mea-on", "all"],
}


@dataclass(frozen=True)
class LearningBenchConfig:
    """Train the paper's variants with several seeds and print success at budget and improvement timestep."""

    preset: str = "cpu-small"
    """paper (40K steps, 4 seeds, paper learner; GPU) or cpu-small (8K steps, 1 seed; ~1 h on 2 cores)."""
    task: str = "block_pull"
    """Task: block_pull, block_pick or drawer_open."""
    variants: tuple[str, ...] = ("equirsac", "equiobs", "mea")
    """Variants to train (add mea-all for MEA on every episode, beyond the paper)."""
    seeds: int = 0
    """Seeds per variant (0: the preset's)."""
    env_steps: int = 0
    """Env-step budget per run (0: the preset's)."""
    demos: int = 2
    """Demonstrations per run (the paper: 2)."""
    actors: int = 1
    """Actor processes per run."""
    eval_every: int = 0
    """Evaluate every this many env steps (0: the preset's)."""
    out: Path = Path("runs/bench-learning")
    """Directory holding one run directory per (variant, seed), the curves PNG and the result."""
    timeout_minutes: float = 0.0
    """Give up a single run after this long (0: no limit)."""
    json: bool = False
    """Print exactly one JSON object instead of tables."""
    extra: tuple[str, ...] = field(default_factory=tuple)
    """Extra `mea run` arguments for every run."""


PRESETS = {
    "paper": {"env_steps": 40_000, "seeds": 4, "learner": "paper", "eval_every": 250},
    "cpu-small": {"env_steps": 8_000, "seeds": 1, "learner": "cpu-small", "eval_every": 1_000},
}


def _log(msg: str) -> None:
    print(f"[bench learning] {msg}", file=sys.stderr, flush=True)


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _finished(run_dir: Path, budget: int) -> bool:
    from services.evaluator.core.metrics import read_history

    history = run_dir / "eval" / "history.jsonl"
    return history.exists() and any(r.get("env_steps", -1) >= budget for r in read_history(history))


def train(cfg: LearningBenchConfig, variant: str, seed: int, budget: int, p: dict) -> tuple[Path, float]:
    run_dir = cfg.out / f"{cfg.task}-{variant}-s{seed}"
    if _finished(run_dir, budget):
        _log(f"{run_dir.name}: finished earlier, reused")
        return run_dir, 0.0
    if run_dir.exists():  # an interrupted run: continue it
        args = ["--resume", str(run_dir)]
    else:
        args = ["--task", cfg.task, *VARIANTS[variant], "--seed", str(seed), "--demos", str(cfg.demos),
                "--actors", str(cfg.actors), "--env-steps", str(budget), "--learner-preset", p["learner"],
                "--eval-every", str(cfg.eval_every or p["eval_every"]), "--run-dir", str(run_dir), *cfg.extra]  # fmt: skip
    cmd = [sys.executable, "-m", "services.cli", "run", *args, "--listen", f"tcp/127.0.0.1:{_port()}",
           "--metrics-port", "0", "--log-format", "json"]  # fmt: skip
    _log(f"{run_dir.name}: training ({budget:,} env steps) ...")
    t0 = time.monotonic()
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / "launcher.log", "a") as logf:
        proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, env=dict(os.environ))
        try:
            proc.wait(timeout=cfg.timeout_minutes * 60 or None)
        except subprocess.TimeoutExpired:
            proc.terminate()
            proc.wait(60)
            _log(f"{run_dir.name}: stopped after {cfg.timeout_minutes} min")
    elapsed = time.monotonic() - t0
    _log(f"{run_dir.name}: exit {proc.returncode} after {elapsed / 60:.1f} min")
    return run_dir, elapsed


def compare(
    cfg: LearningBenchConfig, runs: dict[str, list[Path]], budget: int, png: Path
) -> list[dict[str, Any]]:
    """One row per variant (success at budget mean ± std over seeds, improvement timestep), and the PNG."""
    import dataclasses

    from services.evaluator.plot import PlotError, group_runs, load_run, render, summary_row

    loaded, rows = [], []
    for variant, dirs in runs.items():
        for d in dirs:
            try:
                loaded.append(dataclasses.replace(load_run(d, "variant"), label=variant))
            except PlotError as exc:
                _log(f"{d.name}: {exc}")
    groups = group_runs(loaded)
    if groups:
        render(groups, png, title=f"{cfg.task}: success rate vs env steps (mean ± std over seeds)")
    for g in groups:
        r = summary_row(g)
        rows.append({
            "variant": g.label, "seeds": r["runs"], "evaluations": r["evaluations"],
            "last eval at (env steps)": int(max(run.steps[-1] for run in g.runs)),
            "success at budget (mean)": r["final_mean"], "success at budget (std)": r["final_std"],
            "improvement timestep (mean over seeds)": r["improvement_mean"],
            "seeds that improved": r["improvement_runs"], "improvement timestep of the mean curve": r["improvement_of_mean"],
            "budget (env steps)": budget,
        })  # fmt: skip
    return rows


def run(cfg: LearningBenchConfig) -> dict:
    if cfg.preset not in PRESETS:
        raise SystemExit(f"mea bench learning: unknown preset {cfg.preset!r} (choose from {sorted(PRESETS)})")
    unknown = set(cfg.variants) - set(VARIANTS)
    if unknown:
        raise SystemExit(
            f"mea bench learning: unknown variants {sorted(unknown)} (choose from {sorted(VARIANTS)})"
        )
    p = PRESETS[cfg.preset]
    budget, seeds = cfg.env_steps or p["env_steps"], cfg.seeds or p["seeds"]
    started = time.monotonic()
    cfg.out.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list[Path]] = {}
    minutes: dict[str, float] = {}
    for variant in cfg.variants:
        for seed in range(seeds):
            run_dir, elapsed = train(cfg, variant, seed, budget, p)
            runs.setdefault(variant, []).append(run_dir)
            minutes[run_dir.name] = elapsed / 60
    png = cfg.out / f"curves-{cfg.task}.png"
    rows = compare(cfg, runs, budget, png)
    result_rows = [{"run": name, "minutes": m} for name, m in minutes.items()]
    meta = {"preset": cfg.preset, "task": cfg.task, "budget": budget, "seeds": seeds, "demos": cfg.demos,
            "curves_png": str(png), "out": str(cfg.out), "minutes": round((time.monotonic() - started) / 60, 1)}  # fmt: skip
    result = emit(
        "learning", {"comparison": rows, "runs": result_rows}, measured={}, as_json=cfg.json, meta=meta
    )
    (cfg.out / f"result-{cfg.task}.json").write_text(json.dumps(result, indent=2, default=float) + "\n")
    return result
