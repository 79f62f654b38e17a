"""`mea bench learning`: the paper's comparison, trained here: success at the budget, improvement
timestep and area under the success curve of EquiRSAC, EquiObs-EquiRSAC and MEA-EquiObs-EquiRSAC
(optionally MEA on every episode).

Each (variant, seed) is one whole `mea run` (its own processes and Zenoh router on a free 127.0.0.1
port, its own run directory ``OUT/<task>-<variant>-s<seed>``), one after another, so every run gets
the machine to itself. A run gets exactly `make run`'s recipe (``mea run --task T --demos 2`` and
`mea run`'s defaults) plus the variant, seed, env-step budget and evaluation settings of the preset;
only the ``paper`` preset changes the learner (``--learner-preset paper``).

Per variant, from the runs' evaluation histories (``RUN_DIR/eval/history.jsonl``):

* success at budget: the success rate of each run's evaluation at the budget (the first with
  ``env_steps >= budget``: ``--final-eval-episodes`` held-out seeds), mean ± std over seeds;
* improvement timestep (the paper's: the first env-step count from which success stays > 0), mean
  over the seeds that have one, and of the mean-over-seeds curve;
* AUC: the area under each run's success curve, normalised by its evaluated env-step range
  (trapezoid rule on env steps, in [0, 1]: ``services.evaluator.core.metrics.success_auc``), mean ±
  std over seeds;
* wall time: the minutes the runs took (every `mea run` session of a run, resumed ones included,
  is added up in ``RUN_DIR/bench-wall.json``), and the whole stack's training env steps per second
  against the public Equi-RSAC training loop (one 11.1 s update per env step plus its env: about
  0.065-0.09 env steps/s on a 2-core CPU);
* the learning curves (``mea plot``) as ``OUT/curves-<task>.png``, and the result as
  ``OUT/result-<task>.json``.

Resumable: a run whose history has an evaluation at the budget is reused (delete it to rerun); a run
directory without one is continued with ``mea run --resume``. A run directory made with other
settings (task, variant, seed, budget) is refused rather than mixed in.

Presets: ``cpu-small`` (20K env steps, 1 seed, the cpu-small learner `mea run` defaults to; evaluation
every 1,000 env steps on 20 held-out seeds, 50 at the budget) and ``paper`` (40K env steps, 4 seeds,
the paper learner preset, evaluation every 250 env steps; meant for a GPU workstation).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.bench.harness import free_port
from services.bench.reference import PUBLIC_UPDATE_SECONDS
from services.bench.report import emit

VARIANTS = {
    "equirsac": ["--variant", "equirsac"],
    "equiobs": ["--variant", "equiobs"],
    "mea": ["--variant", "mea"],
    "mea-all": ["--variant", "mea", "--mea-on", "all"],
    "gasv2": ["--variant", "gasv2"],
    "mea-gasv2": ["--variant", "mea-gasv2"],
}
TASK_VARIANTS = {"surgical_grasp_any": ("gasv2", "mea-gasv2")}
"""The comparison run on a task where it is not the general manipulation one (``VARIANTS``' first three)."""
SURGICAL_PRESETS: dict[str, dict[str, Any]] = {
    "cpu-small": {"env_steps": 16_000, "seeds": 1, "eval_every": 2_000, "eval_episodes": 20,
                  "final_eval_episodes": 20, "demos": 10},
    "paper": {"env_steps": 420_000, "seeds": 3, "eval_every": 10_000, "eval_episodes": 20,
              "final_eval_episodes": 20, "demos": 10},
}  # fmt: skip
"""Surgical Grasp Any's settings per preset (the learner preset as ``PRESETS``). paper: the paper's
Sec. VI (10 demos, 420K env steps, 20 evaluation rollouts every 10K, 3 seeds). cpu-small: what two
runs fit in under two hours on two CPU cores (16K env steps took 40 minutes per run here, with
seven evaluations of 20 episodes that mostly run to the 80-step limit; README, "Benchmarks")."""

PUBLIC_TRAINING_ENV_STEPS_PER_SECOND = (0.065, 1.0 / PUBLIC_UPDATE_SECONDS)
"""The public Equi-RSAC training loop on a 2-core CPU, env steps/s: one 11.1 s update per env step
is 0.09; with its env steps and evaluations about 0.065. Ratios are taken against the faster end."""

WALL_FILE = "bench-wall.json"
"""Inside a run directory: the wall seconds of every `mea run` session this benchmark ran there."""


@dataclass(frozen=True)
class LearningBenchConfig:
    """Train the paper's variants and print success at budget, improvement timestep, AUC and wall time."""

    preset: str = "cpu-small"
    """cpu-small (20K steps, 1 seed, `mea run`'s learner; 2 CPU cores) or paper (40K steps, 4 seeds,
    paper learner; GPU)."""
    task: str = "block_pull"
    """Task: block_pull, block_pick, drawer_open or surgical_grasp_any."""
    variants: tuple[str, ...] = ()
    """Variants to train; empty: the paper's comparison for the task (equirsac, equiobs, mea; on
    surgical_grasp_any gasv2, mea-gasv2). Add mea-all for MEA on every episode, beyond the paper."""
    seeds: int = 0
    """Seeds per variant (0: the preset's)."""
    env_steps: int = 0
    """Env-step budget per run (0: the preset's)."""
    demos: int = 0
    """Demonstrations per run (0: the paper's, 2 and `make run`'s; 10 on surgical_grasp_any)."""
    actors: int = 1
    """Actor processes per run."""
    eval_every: int = 0
    """Evaluate every this many env steps (0: the preset's)."""
    eval_episodes: int = 0
    """Held-out episodes per evaluation (0: the preset's)."""
    final_eval_episodes: int = 0
    """Held-out episodes of the evaluation at the budget (0: the preset's)."""
    out: Path = Path("runs/bench-learning")
    """Directory holding one run directory per (variant, seed), the curves PNG and the result."""
    timeout_minutes: float = 0.0
    """Give up a single run after this long (0: no limit); rerunning the benchmark resumes it."""
    json: bool = False
    """Print exactly one JSON object instead of tables."""
    extra: tuple[str, ...] = field(default_factory=tuple)
    """Extra `mea run` arguments for every new run."""


PRESETS: dict[str, dict[str, Any]] = {
    "cpu-small": {"env_steps": 20_000, "seeds": 1, "learner": None, "eval_every": 1_000, "eval_episodes": 20,
                  "final_eval_episodes": 50},
    "paper": {"env_steps": 40_000, "seeds": 4, "learner": "paper", "eval_every": 250, "eval_episodes": 20,
              "final_eval_episodes": 50},
}  # fmt: skip
"""learner None: `mea run`'s default learner preset (what `make run` trains with)."""


@dataclass(frozen=True)
class Settings:
    """The benchmark's resolved per-run settings."""

    budget: int
    seeds: int
    variants: tuple[str, ...]
    demos: int
    learner: str | None
    eval_every: int
    eval_episodes: int
    final_eval_episodes: int


def settings(cfg: LearningBenchConfig) -> Settings:
    if cfg.preset not in PRESETS:
        raise SystemExit(f"mea bench learning: unknown preset {cfg.preset!r} (choose from {sorted(PRESETS)})")
    unknown = set(cfg.variants) - set(VARIANTS)
    if unknown:
        raise SystemExit(
            f"mea bench learning: unknown variants {sorted(unknown)} (choose from {sorted(VARIANTS)})"
        )
    variants = cfg.variants or TASK_VARIANTS.get(cfg.task, ("equirsac", "equiobs", "mea"))
    from services.variants import check_task

    for v in variants:
        try:
            check_task(VARIANTS[v][1], cfg.task)
        except ValueError as exc:
            raise SystemExit(f"mea bench learning: {exc}") from None
    p = dict(PRESETS[cfg.preset])
    if cfg.task in TASK_VARIANTS:
        p.update(SURGICAL_PRESETS[cfg.preset])
    return Settings(
        budget=cfg.env_steps or p["env_steps"],
        seeds=cfg.seeds or p["seeds"],
        variants=tuple(variants),
        demos=cfg.demos or p.get("demos", 2),
        learner=p["learner"],
        eval_every=cfg.eval_every or p["eval_every"],
        eval_episodes=cfg.eval_episodes or p["eval_episodes"],
        final_eval_episodes=cfg.final_eval_episodes or p["final_eval_episodes"],
    )


def _log(msg: str) -> None:
    print(f"[bench learning] {msg}", file=sys.stderr, flush=True)


def run_dir_of(cfg: LearningBenchConfig, variant: str, seed: int) -> Path:
    return cfg.out / f"{cfg.task}-{variant}-s{seed}"


def _history(run_dir: Path) -> list[dict]:
    from services.evaluator.history import HISTORY, read_history

    path = run_dir / HISTORY
    return read_history(path) if path.exists() else []


def budget_record(records: list[dict], budget: int) -> dict | None:
    """The run's evaluation at the budget: the first (in file order) with env_steps >= budget."""
    return next((r for r in records if isinstance(r.get("env_steps"), (int, float)) and r["env_steps"] >= budget),
                None)  # fmt: skip


def finished(run_dir: Path, budget: int) -> bool:
    return budget_record(_history(run_dir), budget) is not None


def run_args(cfg: LearningBenchConfig, variant: str, seed: int, s: Settings) -> list[str]:
    """`mea run` arguments of a new run: `make run`'s recipe plus this run's variant, seed, budget and
    evaluation settings; the learner preset only where the benchmark's preset names one."""
    args = ["--task", cfg.task, "--demos", str(s.demos), *VARIANTS[variant], "--seed", str(seed),
            "--actors", str(cfg.actors), "--env-steps", str(s.budget), "--eval-every", str(s.eval_every),
            "--eval-episodes", str(s.eval_episodes), "--final-eval-episodes", str(s.final_eval_episodes)]  # fmt: skip
    if s.learner is not None:
        args += ["--learner-preset", s.learner]
    return [*args, "--run-dir", str(run_dir_of(cfg, variant, seed)), *cfg.extra]


def check_existing(cfg: LearningBenchConfig, variant: str, seed: int, s: Settings) -> None:
    """Refuse a run directory that an earlier benchmark made with other settings (it would be reused
    or resumed with its own): a clear message instead of a mixed comparison."""
    path = run_dir_of(cfg, variant, seed) / "config.json"
    if not path.exists():
        return
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    want = {"task": cfg.task, "variant": VARIANTS[variant][1], "seed": seed, "env_steps": s.budget}
    made = {k: saved[k] for k, v in want.items() if k in saved and saved[k] != v}
    if made:
        wanted = {k: want[k] for k in made}
        raise SystemExit(
            f"mea bench learning: {path.parent} was made with {made}, not {wanted}; "
            "delete it or choose another --out"
        )


def wall_seconds(run_dir: Path) -> float | None:
    """Wall seconds of the `mea run` sessions this benchmark ran in ``run_dir`` (None: unknown)."""
    try:
        return float(json.loads((run_dir / WALL_FILE).read_text())["seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _add_wall(run_dir: Path, seconds: float) -> None:
    prev = wall_seconds(run_dir) or 0.0
    try:
        sessions = int(json.loads((run_dir / WALL_FILE).read_text()).get("sessions", 0))
    except (OSError, ValueError, AttributeError, TypeError):
        sessions = 0
    tmp = run_dir / (WALL_FILE + ".tmp")
    tmp.write_text(json.dumps({"seconds": round(prev + seconds, 3), "sessions": sessions + 1}) + "\n")
    tmp.replace(run_dir / WALL_FILE)


def train(cfg: LearningBenchConfig, variant: str, seed: int, s: Settings) -> Path:
    run_dir = run_dir_of(cfg, variant, seed)
    if finished(run_dir, s.budget):
        _log(f"{run_dir.name}: finished earlier, reused")
        return run_dir
    if (run_dir / "config.json").exists():  # an interrupted run: continue it with its saved settings
        args = ["--resume", str(run_dir)]
    else:
        args = run_args(cfg, variant, seed, s)
    cmd = [sys.executable, "-m", "services.cli", "run", *args, "--listen", f"tcp/127.0.0.1:{free_port()}",
           "--metrics-port", "0", "--log-format", "json"]  # fmt: skip
    _log(f"{run_dir.name}: training ({s.budget:,} env steps) ...")
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
    _add_wall(run_dir, elapsed)
    _log(f"{run_dir.name}: exit {proc.returncode} after {elapsed / 60:.1f} min")
    return run_dir


def _mean_std(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    a = np.asarray(values, np.float64)
    return float(a.mean()), float(a.std())


def run_row(variant: str, run_dir: Path, budget: int) -> dict[str, Any]:
    """One run's numbers from its history and wall-time file."""
    from services.evaluator.core.metrics import curve, improvement_timestep, success_auc

    records = _history(run_dir)
    steps, success = curve(records)
    at = budget_record(records, budget)
    wall = wall_seconds(run_dir)
    last = int(steps[-1]) if steps.size else None
    return {
        "run": run_dir.name, "variant": variant, "evaluations": int(steps.size),
        "success at budget": None if at is None else float(at["success_rate"]),
        "grasp score at budget": None if at is None or at.get("grasp_score") is None else float(at["grasp_score"]),
        "episodes at budget": None if at is None else at.get("episodes"),
        "AUC": success_auc(steps, success), "improvement timestep": improvement_timestep(steps, success),
        "last eval at (env steps)": last, "wall (min)": None if wall is None else wall / 60,
        "env steps/s": None if wall is None or not last else last / wall,
    }  # fmt: skip


def summarize(
    task: str, runs: dict[str, list[Path]], budget: int, png: Path | None, learner: str
) -> dict[str, list[dict[str, Any]]]:
    """The benchmark's sections from finished (or partly finished) run directories, and the curves PNG.

    ``comparison``: one row per variant; ``runs``: one per run; and the training loop (whole-stack env
    steps/s) against the public Equi-RSAC code."""
    import dataclasses

    from services.evaluator.plot import PlotError, group_runs, load_run, render, summary_row

    loaded = []
    for variant, dirs in runs.items():
        for d in dirs:
            try:
                loaded.append(dataclasses.replace(load_run(d, "variant"), label=variant))
            except PlotError as exc:
                _log(f"{d.name}: {exc}")
    groups = {g.label: g for g in group_runs(loaded)}
    if groups and png is not None:
        render(list(groups.values()), png, title=f"{task}: success rate vs env steps (mean ± std over seeds)")
    per_run = {v: [run_row(v, d, budget) for d in dirs] for v, dirs in runs.items()}
    comparison, loop = [], []
    lo, hi = PUBLIC_TRAINING_ENV_STEPS_PER_SECOND
    for variant, rows in per_run.items():
        at_budget = [r["success at budget"] for r in rows if r["success at budget"] is not None]
        scores = [r["grasp score at budget"] for r in rows if r["grasp score at budget"] is not None]
        aucs = [r["AUC"] for r in rows if r["AUC"] is not None]
        improved = [r["improvement timestep"] for r in rows if r["improvement timestep"] is not None]
        walls = [r["wall (min)"] for r in rows if r["wall (min)"] is not None]
        timed = [r for r in rows if r["env steps/s"] is not None]
        success_mean, success_std = _mean_std(at_budget)
        auc_mean, auc_std = _mean_std(aucs)
        g = groups.get(variant)
        comparison.append({
            "variant": variant, "seeds": len(rows), "seeds at budget": len(at_budget),
            "success at budget (mean)": success_mean, "success at budget (std)": success_std,
            "grasp score at budget (mean)": _mean_std(scores)[0],
            "AUC (mean)": auc_mean, "AUC (std)": auc_std,
            "improvement timestep (mean over seeds)": float(np.mean(improved)) if improved else None,
            "seeds improved": len(improved),
            "improvement timestep of the mean curve": None if g is None else summary_row(g)["improvement_of_mean"],
            "wall (min, all seeds)": sum(walls) if walls else None,
        })  # fmt: skip
        rate = None
        if timed:
            steps = sum(r["last eval at (env steps)"] for r in timed)
            rate = steps / sum(r["wall (min)"] * 60 for r in timed)
        loop.append({
            "variant": variant, "learner preset": learner, "runs timed": len(timed),
            "env steps/s (whole stack, wall)": rate, "public training loop (env steps/s)": f"{lo:g}-{hi:.2g}",
            "ratio (vs the faster public end)": None if rate is None else rate / hi,
        })  # fmt: skip
    out = {"comparison": comparison, "runs": [r for rows in per_run.values() for r in rows]}
    if task not in TASK_VARIANTS:  # the public anchor is Equi-RSAC's training loop
        out["training loop against the public Equi-RSAC code"] = loop
    return out


def run(cfg: LearningBenchConfig) -> dict:
    s = settings(cfg)
    for variant in s.variants:  # before training anything: no run directory with other settings
        for seed in range(s.seeds):
            check_existing(cfg, variant, seed, s)
    started = time.monotonic()
    cfg.out.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list[Path]] = {}
    for variant in s.variants:
        for seed in range(s.seeds):
            runs.setdefault(variant, []).append(train(cfg, variant, seed, s))
    png = cfg.out / f"curves-{cfg.task}.png"
    from services.launcher import RunConfig

    learner = s.learner or f"{RunConfig().learner_preset} (mea run's default)"
    sections = summarize(cfg.task, runs, s.budget, png, learner)
    meta = {"preset": cfg.preset, "task": cfg.task, "budget": s.budget, "seeds": s.seeds, "demos": s.demos,
            "learner": learner, "eval_every": s.eval_every, "eval_episodes": s.eval_episodes,
            "final_eval_episodes": s.final_eval_episodes, "curves_png": str(png), "out": str(cfg.out),
            "minutes": round((time.monotonic() - started) / 60, 1)}  # fmt: skip
    result = emit("learning", sections, measured={}, as_json=cfg.json, meta=meta)
    (cfg.out / f"result-{cfg.task}.json").write_text(json.dumps(result, indent=2, default=float) + "\n")
    return result
