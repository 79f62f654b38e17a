"""`mea bench learning`: the paper's comparison trained here. EquiRSAC, EquiObs-EquiRSAC and
MEA-EquiObs-EquiRSAC (optionally MEA on every episode), each seed one whole `mea run` (one after
another, or ``--parallel`` at once): success at the budget, improvement timestep and area under the
success curve, with stratified-bootstrap intervals over seeds a reader can trust; ``--protocol``
calibrates against public numbers instead.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import tyro

from mea_tools.bench import best_policy, stats
from mea_tools.bench.harness import free_port
from mea_tools.bench.reference import PUBLIC_UPDATE_SECONDS
from mea_tools.bench.report import emit
from services.common import config
from services.evaluator.core.curves import align, common_grid, curve, improvement_timestep, success_auc
from services.evaluator.history import HISTORY, read_history
from services.evaluator.plot import PlotError, group_runs, load_run, summary_row
from services.variants import check_task

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
    "cpu-small": {"env_steps": 16_000, "seeds": 3, "eval_every": 2_000, "eval_episodes": 20,
                  "final_eval_episodes": 20, "demos": 10},
    "paper": {"env_steps": 420_000, "seeds": 3, "eval_every": 10_000, "eval_episodes": 20,
              "final_eval_episodes": 20, "demos": 10},
}  # fmt: skip
"""Surgical Grasp Any's settings per preset (the learner preset as ``PRESETS``). paper: the paper's
Sec. VI (10 demos, 420K env steps, 20 evaluation rollouts every 10K, 3 seeds). cpu-small: 16K env
steps took 40 minutes per run here, with seven evaluations of 20 episodes that mostly run to the
80-step limit (docs/benchmarks.md); 3 seeds per arm, the fewest that give an interval."""

PUBLIC_TRAINING_ENV_STEPS_PER_SECOND = (0.065, 1.0 / PUBLIC_UPDATE_SECONDS)
"""The public Equi-RSAC training loop on a 2-core CPU, env steps/s: one 11.1 s update per env step
is 0.09; with its env steps and evaluations about 0.065. Ratios are taken against the faster end."""

WALL_FILE = "bench-wall.json"
"""Inside a run directory: the wall seconds of every `mea run` session this benchmark ran there."""

PROFILE_TAUS = np.linspace(0.0, 1.0, 51)
"""Thresholds of the performance profile (success at budget; 50 held-out episodes move it by 0.02)."""


@dataclass(frozen=True)
class Protocol:
    """A calibration against published numbers: their data, arms, budget and seeds, and their curve."""

    variants: tuple[str, ...]
    env_steps: int
    seeds: int
    demos: int
    random_steps: int | None
    """``mea run --random-steps`` (None: not passed, the learner preset's prefill)."""
    eval_every: int
    reference_name: str
    reference: dict[str, dict[int, float]]
    """Per arm: env steps -> the reference's mean success there."""
    learner: str = "cpu-small"
    task: str = "block_pull"
    gripper_start: str = "random"
    """``mea run --gripper-start``: fixed where the reference ran the public environments' start."""


_PUBLIC15_STEPS = (5_000, 10_000, 15_000, 20_000, 25_000)
_PUBLIC15_BASELINE = dict(zip(_PUBLIC15_STEPS, (0.00, 0.27, 0.37, 0.53, 0.77), strict=True))
PROTOCOLS: dict[str, Protocol] = {
    # the public Equi-RSAC protocol's data: 80 expert demos and 20 random episodes (50 steps each)
    "public80": Protocol(
        variants=("equirsac", "equiobs"), env_steps=40_000, seeds=2, demos=80, random_steps=1_000,
        eval_every=2_500, reference_name="public Equi-RSAC (best Block Pull policies, 50 episodes)",
        reference={"equirsac": {40_000: 1.0}, "equiobs": {40_000: 1.0}},
    ),
    # the public reproduction linhongbin-ws/rgbd-sym: 15 demos, mean success of its baseline and MEA
    # arm. Both ran its fork of the public Equi-RSAC learner with `obs_type: occup`: the policy sees a
    # top-down image of occupancy voxels from the point cloud (the paper's kind of observation), not
    # the public code's depth render. So `equiobs` is its baseline here and `mea` its MEA arm;
    # `equirsac` (the depth render) is held to the same baseline curve. Its pool also held 20 random
    # episodes; this protocol has none, as every run measured with it so far.
    "public15": Protocol(
        variants=("equirsac", "equiobs", "mea"), env_steps=25_000, seeds=3, demos=15, random_steps=None,
        eval_every=2_500, reference_name="public reproduction (linhongbin-ws/rgbd-sym, occupancy-image baseline)",
        reference={"equirsac": _PUBLIC15_BASELINE, "equiobs": _PUBLIC15_BASELINE,
                   "mea": dict(zip(_PUBLIC15_STEPS, (0.00, 0.33, 0.17, 0.53, 0.67), strict=True))},
    ),
}  # fmt: skip
# The same data and references on the public environments' task: the gripper starts at the workspace
# centre with yaw 0 at every reset (this project's tasks draw its pose, MEA's premise), so the policy
# never has to turn to the blocks first.
PROTOCOLS |= {f"{name}-fixed": dataclasses.replace(p, gripper_start="fixed") for name, p in PROTOCOLS.items()}
"""``--protocol``: named calibrations on Block Pull with the cpu-small learner (20 held-out episodes
per evaluation, 50 at the budget)."""


@dataclass(frozen=True)
class LearningBenchConfig:
    """Train the paper's variants and print success at budget, improvement timestep, AUC and wall time."""

    preset: str = "cpu-small"
    """cpu-small (20K steps, 3 seeds, CPU) or paper (40K, 4 seeds, GPU)."""
    task: str = "block_pull"
    """Task: block_pull, block_pick, drawer_open or surgical_grasp_any."""
    variants: tuple[str, ...] = ()
    """Variants to train; empty: the paper's comparison for the task."""
    protocol: str = ""
    """A calibration against public numbers: public80 or public15 (-fixed: the public start)."""
    seeds: int = 0
    """Seeds per variant, the same seeds 0..n-1 for every variant (0: the preset's)."""
    env_steps: int = 0
    """Env-step budget per run (0: the preset's)."""
    demos: int = 0
    """Demonstrations per run (0: the paper's, 2 and `make run`'s; 10 on surgical_grasp_any)."""
    actors: int = 1
    """Actor processes per run."""
    envs_per_actor: int = 1
    """Envs each actor steps in lockstep (`mea run --envs-per-actor`)."""
    learner_preset: str = ""
    """Every run's `mea run --learner-preset` (empty: the preset's or the protocol's)."""
    learner_threads: int = 1
    """Every run's `mea run --learner-threads` (given again on resume)."""
    learner_device: str = "cpu"
    """Every run's learner device: cpu, cuda or cuda:N (given again on resume: it is this machine's)."""
    parallel: int = 1
    """Runs trained at once, each with its own router port and run dir (1: one after another)."""
    eval_every: int = 0
    """Evaluate every this many env steps (0: the preset's)."""
    eval_episodes: int = 0
    """Held-out episodes per evaluation (0: the preset's)."""
    final_eval_episodes: int = 0
    """Held-out episodes of the evaluation at the budget (0: the preset's)."""
    best_episodes: int = 0
    """Also play each run's best evaluated weights on this many fresh held-out seeds (0: off)."""
    out: Path = Path("runs/bench-learning")
    """Directory holding one run directory per (variant, seed), the curves PNG and the result."""
    timeout_minutes: float = 0.0
    """Give up a single run after this long (0: no limit); rerunning the benchmark resumes it."""
    json: bool = False
    """Print exactly one JSON object instead of tables."""
    extra: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """One more `mea run` argument for new runs; repeat for more (--extra=--track)."""
    bootstrap_reps: int = 10_000
    """Stratified-bootstrap resamples per interval."""
    bootstrap_seed: int = 0
    """Seed of the bootstrap (the same seed and runs give the same intervals)."""


# Presets: ``cpu-small`` (20K env steps, 3 seeds, the cpu-small learner `mea run` defaults to;
# evaluation every 1,000 env steps on 20 held-out seeds, 50 at the budget) and ``paper`` (40K env
# steps, 4 seeds, the paper learner preset, evaluation every 250 env steps; meant for a GPU
# workstation).

PRESETS: dict[str, dict[str, Any]] = {
    "cpu-small": {"env_steps": 20_000, "seeds": 3, "learner": None, "eval_every": 2_000, "eval_episodes": 20,
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
    random_steps: int | None = None
    protocol: Protocol | None = None

    @property
    def gripper_start(self) -> str:
        """``mea run --gripper-start`` of every run: the protocol's, else each task's random start."""
        return self.protocol.gripper_start if self.protocol else "random"

    @property
    def seed_list(self) -> tuple[int, ...]:
        """Every arm runs these seeds: arms are paired by seed."""
        return tuple(range(self.seeds))


def _refuse(msg: str) -> SystemExit:
    return SystemExit(f"mea bench learning: {msg}")


def _check_options(cfg: LearningBenchConfig) -> None:
    if cfg.preset not in PRESETS:
        raise _refuse(f"unknown preset {cfg.preset!r} (choose from {sorted(PRESETS)})")
    if cfg.protocol and cfg.protocol not in PROTOCOLS:
        raise _refuse(f"unknown --protocol {cfg.protocol!r} (choose from {sorted(PROTOCOLS)})")
    negative = [n for n in ("seeds", "env_steps", "demos", "eval_every", "eval_episodes", "final_eval_episodes")
                if getattr(cfg, n) < 0]  # fmt: skip
    if negative:
        raise _refuse(f"--{negative[0].replace('_', '-')} must be >= 0 (0: the preset's)")
    if cfg.parallel < 1:
        raise _refuse(f"--parallel must be >= 1, not {cfg.parallel}")
    if cfg.best_episodes < 0:
        raise _refuse(f"--best-episodes must be >= 0 (0: off), not {cfg.best_episodes}")
    if cfg.envs_per_actor < 1:
        raise _refuse(f"--envs-per-actor must be >= 1, not {cfg.envs_per_actor}")
    if cfg.learner_device != "cpu":
        from services.learner.config import check_device  # deferred: torch, for a CUDA device only

        try:
            check_device(cfg.learner_device, "--learner-device")
        except ValueError as exc:
            raise _refuse(str(exc)) from None
    if cfg.learner_threads < 0:
        raise _refuse(f"--learner-threads must be >= 0 (0: torch's default), not {cfg.learner_threads}")
    if cfg.bootstrap_reps < 1:
        raise _refuse(f"--bootstrap-reps must be >= 1, not {cfg.bootstrap_reps}")
    unknown = set(cfg.variants) - set(VARIANTS)
    if unknown:
        raise _refuse(f"unknown variants {sorted(unknown)} (choose from {sorted(VARIANTS)})")
    if cfg.protocol:
        proto = PROTOCOLS[cfg.protocol]
        if cfg.task != proto.task:
            raise _refuse(f"--protocol {cfg.protocol} is a {proto.task} protocol, not --task {cfg.task}")
        if cfg.preset != "cpu-small":
            raise _refuse(f"--protocol {cfg.protocol} sets its own learner ({proto.learner}); "
                          "leave --preset at cpu-small")  # fmt: skip


def _check_learner_preset(name: str, variant: str) -> None:
    """Refuse before training a ``--learner-preset`` that the variant's algorithm has no row for."""
    from services.learner.config import learner_presets  # deferred: torch
    from services.variants import variant as run_variant

    choices = learner_presets(run_variant(variant).algorithm)
    if name not in choices:
        raise _refuse(
            f"--learner-preset {name!r} has no {variant} learner; choose one of {', '.join(choices)}"
        )


def settings(cfg: LearningBenchConfig) -> Settings:
    _check_options(cfg)
    proto = PROTOCOLS.get(cfg.protocol)
    default_variants = proto.variants if proto else ("equirsac", "equiobs", "mea")
    variants = cfg.variants or TASK_VARIANTS.get(cfg.task, default_variants)

    for v in variants:
        try:
            check_task(VARIANTS[v][1], cfg.task)
        except ValueError as exc:
            raise SystemExit(f"mea bench learning: {exc}") from None
        if cfg.learner_preset:
            _check_learner_preset(cfg.learner_preset, VARIANTS[v][1])
    p = dict(PRESETS[cfg.preset])
    if cfg.task in TASK_VARIANTS:
        p.update(SURGICAL_PRESETS[cfg.preset])
    if proto is not None:
        p.update(env_steps=proto.env_steps, seeds=proto.seeds, demos=proto.demos, learner=proto.learner,
                 eval_every=proto.eval_every, random_steps=proto.random_steps)  # fmt: skip
    return Settings(
        budget=cfg.env_steps or p["env_steps"],
        seeds=cfg.seeds or p["seeds"],
        variants=tuple(variants),
        demos=cfg.demos or p.get("demos", 2),
        learner=cfg.learner_preset or p["learner"],
        eval_every=cfg.eval_every or p["eval_every"],
        eval_episodes=cfg.eval_episodes or p["eval_episodes"],
        final_eval_episodes=cfg.final_eval_episodes or p["final_eval_episodes"],
        random_steps=p.get("random_steps"),
        protocol=proto,
    )


def _log(msg: str) -> None:
    print(f"[bench learning] {msg}", file=sys.stderr, flush=True)


def out_dir(cfg: LearningBenchConfig) -> Path:
    """Where runs and results go: --out, or --out/<protocol> for a protocol."""
    return cfg.out / cfg.protocol if cfg.protocol else cfg.out


def run_dir_of(cfg: LearningBenchConfig, variant: str, seed: int) -> Path:
    return out_dir(cfg) / f"{cfg.task}-{variant}-s{seed}"


def _history(run_dir: Path) -> list[dict]:
    path = run_dir / HISTORY
    return read_history(path) if path.exists() else []


def budget_record(records: list[dict], budget: int) -> dict | None:
    """The run's evaluation at the budget (or any env-step point): the first (in file order) with
    env_steps >= budget."""
    return next((r for r in records if isinstance(r.get("env_steps"), (int, float)) and r["env_steps"] >= budget),
                None)  # fmt: skip


def finished(run_dir: Path, budget: int) -> bool:
    return budget_record(_history(run_dir), budget) is not None


def machine_args(cfg: LearningBenchConfig) -> list[str]:
    """This machine's `mea run` settings, given to a new run and again to a resumed one (a resume takes
    them from its command line, not from the run's saved config)."""
    return ["--learner-device", cfg.learner_device, "--learner-threads", str(cfg.learner_threads)]


# Each (variant, seed) is one whole `mea run` (its own processes and Zenoh router on a free 127.0.0.1
# port, its own run directory ``OUT/<task>-<variant>-s<seed>``), one after another, so every run gets
# the machine to itself; ``--parallel P`` trains up to P at once (``train_all``). Every arm runs the same seeds 0..n-1 (paired by seed). A run gets exactly
# `make run`'s recipe (``mea run --task T --demos 2`` and `mea run`'s defaults) plus the variant, seed,
# env-step budget and evaluation settings of the preset; only the ``paper`` preset (``--learner-preset
# paper``) or the benchmark's own ``--learner-preset`` changes the learner. ``--protocol`` names a calibration against public numbers instead
# (``PROTOCOLS``: its data, arms, budget and seeds; its runs under ``OUT/<protocol>``).
def run_args(cfg: LearningBenchConfig, variant: str, seed: int, s: Settings) -> list[str]:
    """`mea run` arguments of a new run: `make run`'s recipe plus this run's variant, seed, budget and
    evaluation settings; the learner preset only where the benchmark's preset or --learner-preset
    names one."""
    args = ["--task", cfg.task, "--demos", str(s.demos), *VARIANTS[variant], "--seed", str(seed),
            "--actors", str(cfg.actors), "--envs-per-actor", str(cfg.envs_per_actor), *machine_args(cfg),
            "--env-steps", str(s.budget), "--eval-every", str(s.eval_every),
            "--eval-episodes", str(s.eval_episodes), "--final-eval-episodes", str(s.final_eval_episodes)]  # fmt: skip
    if s.random_steps is not None:
        args += ["--random-steps", str(s.random_steps)]
    if s.learner is not None:
        args += ["--learner-preset", s.learner]
    if s.gripper_start != "random":
        args += ["--gripper-start", s.gripper_start]
    args += ["--run-dir", str(run_dir_of(cfg, variant, seed))]
    # an --extra flag replaces the bench's own (mea run refuses a flag given twice)
    given = {a.split("=", 1)[0] for a in cfg.extra if a.startswith("--")}
    pairs = [args[i : i + 2] for i in range(0, len(args), 2)]  # every argument above is a flag and a value
    return [a for flag, value in pairs if flag not in given for a in (flag, value)] + list(cfg.extra)


def _mea_run():
    """`mea run`'s config class and presets. Imported here: they pull in torch and pybullet, which this
    process never needs otherwise (the runs are subprocesses)."""
    from services.launcher import PRESETS, RunConfig  # deferred: torch and pybullet

    return RunConfig, PRESETS


CHECKED = ("task", "variant", "seed", "env_steps", "demos", "random_steps", "learner_preset", "gripper_start")
"""What a reused or resumed run directory must have been made with (demos and random steps as
resolved: None stands for the default it resolved to)."""


def _checked(values: dict[str, Any]) -> dict[str, Any]:
    """The ``CHECKED`` settings of a `mea run` config (as saved in config.json), defaults resolved."""
    RunConfig, _ = _mea_run()
    known = {
        k: values[k] for k in ("task", "variant", "learner_preset", "demos", "random_steps") if k in values
    }
    try:
        rc = RunConfig(**known)
    except (TypeError, ValueError):  # not a config this code can read: compare what was saved
        return {k: values[k] for k in CHECKED if k in values}
    resolved = {"demos": rc.resolved_demos(), "random_steps": rc.resolved_random_steps()}
    return {k: resolved.get(k, values[k]) for k in CHECKED if k in values}


# Resumable: a run whose history has an evaluation at the budget is reused (delete it to rerun); a run
# directory without one is continued with ``mea run --resume``. A run directory made with other
# settings (task, variant, seed, budget, demos, random steps, learner preset) is refused rather than
# mixed in.
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
    if not isinstance(saved, dict):
        return
    RunConfig, RUN_PRESETS = _mea_run()
    # what `mea run` would save for this run now, --extra included
    wanted_cfg = config.parse(RunConfig, RUN_PRESETS, run_args(cfg, variant, seed, s), "mea run", "")
    want = _checked(config.to_jsonable(wanted_cfg))
    have = _checked(saved)
    made = {k: have[k] for k, v in want.items() if k in have and have[k] != v}
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


class ListenPorts:
    """Free 127.0.0.1 ports for the runs in flight, never one that another run of this benchmark was
    given and may not have bound yet (its router starts seconds after the port is chosen)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._held: set[int] = set()

    @contextlib.contextmanager
    def hold(self) -> Iterator[int]:
        with self._lock:
            port = free_port()
            while port in self._held:
                port = free_port()
            self._held.add(port)
        try:
            yield port
        finally:
            with self._lock:
                self._held.discard(port)


_PORTS = ListenPorts()

STOP_WAIT_SECONDS = 180.0
"""How long a `mea run` told to stop may take to write its last checkpoint before it is killed."""

_LIVE: set[subprocess.Popen] = set()
_LIVE_LOCK = threading.Lock()


def stop_live_runs() -> None:
    """SIGTERM every `mea run` this bench started that has not ended: the launcher's own graceful
    stop (services stopped, last checkpoint and summary written), so that a rerun resumes them and
    no run goes on writing its directory unattended."""
    with _LIVE_LOCK:
        procs = list(_LIVE)
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()


def run_child(cmd: list[str], logf: Any, timeout_s: float | None, name: str) -> int:
    """Run one `mea run` to its end and return its exit code. Past ``timeout_s`` it is stopped;
    if this bench is interrupted while waiting (Ctrl-C, SIGTERM), it is stopped before the
    interruption goes on, so that none outlives the bench."""
    proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, env=dict(os.environ))
    with _LIVE_LOCK:
        _LIVE.add(proc)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        _stop(proc)
        _log(f"{name}: stopped after {timeout_s / 60:.0f} min")
    except BaseException:
        _stop(proc)
        _log(f"{name}: stopped (the same command resumes it)")
        raise
    finally:
        with _LIVE_LOCK:
            _LIVE.discard(proc)
    return proc.returncode


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(STOP_WAIT_SECONDS)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def train(cfg: LearningBenchConfig, variant: str, seed: int, s: Settings) -> Path:
    run_dir = run_dir_of(cfg, variant, seed)
    if finished(run_dir, s.budget):
        _log(f"{run_dir.name}: finished earlier, reused")
        return run_dir
    if (run_dir / "config.json").exists():  # an interrupted run: continue it with its saved settings
        args = ["--resume", str(run_dir), *machine_args(cfg)]  # and this machine's
    else:
        args = run_args(cfg, variant, seed, s)
    with _PORTS.hold() as port:
        cmd = [sys.executable, "-m", "services.cli", "run", *args, "--listen", f"tcp/127.0.0.1:{port}",
               "--metrics-port", "0", "--log-format", "json"]  # fmt: skip
        _log(f"{run_dir.name}: training ({s.budget:,} env steps) ...")
        t0 = time.monotonic()
        run_dir.mkdir(parents=True, exist_ok=True)
        with open(run_dir / "launcher.log", "a") as logf:
            try:
                code = run_child(cmd, logf, cfg.timeout_minutes * 60 or None, run_dir.name)
            finally:  # an interrupted run's time counts too
                elapsed = time.monotonic() - t0
                _add_wall(run_dir, elapsed)
    _log(f"{run_dir.name}: exit {code} after {elapsed / 60:.1f} min")
    return run_dir


def train_all(cfg: LearningBenchConfig, s: Settings) -> dict[str, list[Path]]:
    """Every (variant, seed) run, by variant: one after another, or up to ``--parallel`` at once,
    seed by seed across the arms (an interrupted comparison then has every arm on the same seeds).
    Each run keeps its own run directory, router port and wall time, reused or resumed as alone."""
    if cfg.parallel == 1:
        return {variant: [train(cfg, variant, seed, s) for seed in s.seed_list] for variant in s.variants}
    jobs = [(variant, seed) for seed in s.seed_list for variant in s.variants]
    workers = min(cfg.parallel, len(jobs))
    _note_cores(cfg, workers)
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="bench-run")
    try:
        futures = {job: pool.submit(train, cfg, *job, s) for job in jobs}
        return {
            variant: [futures[(variant, seed)].result() for seed in s.seed_list] for variant in s.variants
        }
    except BaseException:  # Ctrl-C, SIGTERM or a failure: the runs in flight stop too (resumable)
        stop_live_runs()
        raise
    finally:  # no new run starts
        pool.shutdown(wait=True, cancel_futures=True)


def _note_cores(cfg: LearningBenchConfig, runs: int) -> None:
    """Say when ``runs`` runs at once ask for more cores than this machine lends: they still run, slower."""
    from services.run_config import AUTO_RESERVED_CORES, usable_cores  # deferred: torch and pybullet

    processes, cores = runs * (cfg.actors + AUTO_RESERVED_CORES), usable_cores()
    share = "; they share the cores, each run slower than alone" if processes > cores else ""
    _log(f"{runs} runs at once: {processes} busy processes (actors, learner, augmenter, evaluator, "
         f"launcher) on {cores} cores{share}")  # fmt: skip


def _mean_std(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    a = np.asarray(values, np.float64)
    return float(a.mean()), float(a.std())


def _ci(i: stats.Interval | None) -> list[float] | None:
    return None if i is None else [i.lo, i.hi]


def run_row(variant: str, run_dir: Path, budget: int) -> dict[str, Any]:
    """One run's numbers from its history and wall-time file."""
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


def arm_band(dirs: list[Path], boot: stats.Bootstrap) -> stats.CurveBand | None:
    """An arm's runs on their union env-step grid (step-wise hold), reduced to mean and interval."""
    curves = [c for c in (curve(_history(d)) for d in dirs) if c[0].size]
    if not curves:
        return None
    grid = common_grid(curves)
    return stats.curve_band(grid, align(curves, grid, "hold"), boot)


def _pyplot():
    import matplotlib  # deferred: matplotlib, only where a figure is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: after the backend is chosen

    return plt


def render_curves(bands: dict[str, stats.CurveBand], reference: dict[str, dict[int, float]], ref_name: str,
                  png: Path, title: str) -> None:  # fmt: skip
    """Mean success vs env steps per arm with its interval band, and the reference's points."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    try:
        for arm, band in bands.items():
            (line,) = ax.plot(band.steps, band.mean, drawstyle="steps-post",
                              marker="o" if band.steps.size == 1 else "", label=f"{arm} (n={band.runs})")  # fmt: skip
            ax.fill_between(band.steps, band.lo, band.hi, color=line.get_color(), alpha=0.2, linewidth=0,
                            step="post")  # fmt: skip
            ref = reference.get(arm)
            if ref:
                ax.plot(list(ref), list(ref.values()), linestyle="--", marker="x", color=line.get_color(),
                        label=f"{arm}: {ref_name}")  # fmt: skip
        ax.set_xlabel("env steps")
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize="small")
        ax.set_title(title, fontsize="medium")
        fig.tight_layout()
        fig.savefig(png, format="png")
    finally:
        plt.close(fig)


def render_profile(profiles: dict[str, stats.Profile], png: Path, title: str) -> None:
    """rliable's performance-profile plot: fraction of runs with success at the budget > tau."""
    plt = _pyplot()
    from rliable import plot_utils  # deferred: matplotlib, only where a figure is drawn

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    try:
        taus = next(iter(profiles.values())).taus
        plot_utils.plot_performance_profiles(
            {k: p.fraction for k, p in profiles.items()}, taus,
            performance_profile_cis={k: (p.lo, p.hi) for k, p in profiles.items()}, ax=ax,
            xlabel=r"success at budget ($\tau$)", ylabel=r"fraction of runs with success $> \tau$",
            labelsize="medium", ticklabelsize="medium",
        )  # fmt: skip
        ax.legend(loc="upper right")
        ax.set_title(title, fontsize="medium")
        fig.tight_layout()
        fig.savefig(png, format="png")
    finally:
        plt.close(fig)


def reference_rows(
    proto: Protocol, runs: dict[str, list[Path]], boot: stats.Bootstrap
) -> list[dict[str, Any]]:
    """Ours (mean and interval over seeds of each run's first evaluation at or after the reference's
    env steps) beside the reference, point by point."""
    rows = []
    for arm, points in proto.reference.items():
        if arm not in runs:
            continue
        histories = [_history(d) for d in runs[arm]]
        for steps, ref in points.items():
            at = [budget_record(h, steps) for h in histories]
            values = [float(r["success_rate"]) for r in at if r is not None]
            iv = stats.mean_interval(values, boot)
            if iv is None:
                verdict = "not reached"
            elif iv.point >= ref:
                verdict = "at/above"
            else:
                verdict = "below (reference inside the CI)" if iv.hi >= ref else "below"
            rows.append({
                "variant": arm, "env steps": steps, "seeds": len(values),
                "ours (mean)": None if iv is None else iv.point, "ours (95% CI)": _ci(iv),
                "reference": ref, "verdict": verdict,
            })  # fmt: skip
    return rows


# Per variant, from the runs' evaluation histories (``RUN_DIR/eval/history.jsonl``), with 95%
# stratified-bootstrap intervals over seeds from rliable (``mea_tools.bench.stats``):
#
# * success at budget: each run's evaluation at the budget (the first with ``env_steps >= budget``:
#   ``--final-eval-episodes`` held-out seeds); mean, IQM and std over seeds;
# * improvement timestep (the paper's: the first env-step count from which success stays > 0), mean
#   over the seeds that have one, and of the mean-over-seeds curve;
# * AUC: the area under each run's success curve, normalised by its evaluated env-step range
#   (``services.evaluator.core.curves.success_auc``, in [0, 1]), mean over seeds;
# * against the first arm: rliable's probability of improvement, and "within noise" where the two
#   arms' intervals of the mean success at the budget overlap;
# * with a protocol: ours (mean and interval) beside the public reference at its env-step points;
# * wall time: the minutes the runs took (every `mea run` session of a run, resumed ones included,
#   is added up in ``RUN_DIR/bench-wall.json``), and the whole stack's training env steps per second
#   against the public Equi-RSAC training loop (one 11.1 s update per env step plus its env: about
#   0.065-0.09 env steps/s on a 2-core CPU);
# * ``curves-<task>.png`` (mean success vs env steps with its interval band per arm, and the
#   protocol's reference), ``profile-<task>.png`` (rliable performance profile of success at the
#   budget) and ``result-<task>.json``, all in the output directory.
def summarize(
    task: str,
    runs: dict[str, list[Path]],
    budget: int,
    out: Path | None,
    learner: str,
    boot: stats.Bootstrap,
    protocol: Protocol | None = None,
    best: dict[str, dict[str, Any] | None] | None = None,
) -> dict[str, list[dict[str, Any]]]:
    """The benchmark's sections from finished (or partly finished) run directories, and its PNGs in
    ``out`` (None: none).

    ``comparison``: success at the budget per variant; ``learning speed``: AUC, improvement timestep
    and wall time; ``against the first arm``: probability of improvement and the noise verdict;
    ``against the public reference`` with a protocol; ``runs``: one row per run; and the training
    loop (whole-stack env steps/s) against the public Equi-RSAC code. ``best`` (run name -> its
    ``best_policy.measure``) adds each run's best weights on fresh seeds, and their mean per arm."""
    loaded = []
    for variant, dirs in runs.items():
        for d in dirs:
            try:
                loaded.append(dataclasses.replace(load_run(d, "variant"), label=variant))
            except PlotError as exc:
                _log(f"{d.name}: {exc}")
    groups = {g.label: g for g in group_runs(loaded)}
    per_run = {v: [run_row(v, d, budget) for d in dirs] for v, dirs in runs.items()}
    if best is not None:
        for row in (r for rows in per_run.values() for r in rows):
            b = best.get(row["run"])
            row["best weights (env steps)"] = None if b is None else b["env steps"]
            row["best weights on fresh seeds"] = None if b is None else b["success"]
    at_budget = {v: [r["success at budget"] for r in rows if r["success at budget"] is not None]
                 for v, rows in per_run.items()}  # fmt: skip
    comparison, speed, loop = [], [], []
    lo, hi = PUBLIC_TRAINING_ENV_STEPS_PER_SECOND
    for variant, rows in per_run.items():
        scores = [r["grasp score at budget"] for r in rows if r["grasp score at budget"] is not None]
        aucs = [r["AUC"] for r in rows if r["AUC"] is not None]
        improved = [r["improvement timestep"] for r in rows if r["improvement timestep"] is not None]
        walls = [r["wall (min)"] for r in rows if r["wall (min)"] is not None]
        timed = [r for r in rows if r["env steps/s"] is not None]
        arm = stats.summarize_arm(at_budget[variant], boot)
        auc, improvement = stats.mean_interval(aucs, boot), stats.mean_interval(improved, boot)
        g = groups.get(variant)
        comparison.append({
            "variant": variant, "seeds": len(rows), "seeds at budget": len(at_budget[variant]),
            "success at budget (mean)": None if arm is None else arm.mean.point,
            "success at budget (95% CI)": None if arm is None else _ci(arm.mean),
            "success at budget (IQM)": None if arm is None else arm.iqm.point,
            "success at budget (IQM 95% CI)": None if arm is None else _ci(arm.iqm),
            "success at budget (std)": None if arm is None else arm.std,
            "grasp score at budget (mean)": _mean_std(scores)[0],
        })  # fmt: skip
        if best is not None:
            fresh = stats.mean_interval([r["best weights on fresh seeds"] for r in rows
                                         if r["best weights on fresh seeds"] is not None], boot)  # fmt: skip
            comparison[-1]["best weights on fresh seeds (mean)"] = None if fresh is None else fresh.point
            comparison[-1]["best weights on fresh seeds (95% CI)"] = _ci(fresh)
        speed.append({
            "variant": variant, "AUC (mean)": None if auc is None else auc.point, "AUC (95% CI)": _ci(auc),
            "AUC (std)": _mean_std(aucs)[1],
            "improvement timestep (mean over seeds)": None if improvement is None else improvement.point,
            "improvement timestep (95% CI)": _ci(improvement), "seeds improved": len(improved),
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
    first = next(iter(runs), None)
    against = []
    for variant in list(runs)[1:]:
        c = stats.compare(at_budget[variant], at_budget[first], boot) if first is not None else None
        verdict = None
        if c is not None and min(len(at_budget[variant]), len(at_budget[first])) < 2:
            verdict = "one seed: no interval to compare"  # a one-run interval is a point
        elif c is not None:
            verdict = ("within noise (the 95% CIs of the mean overlap)" if c.within_noise
                       else "separated (the 95% CIs of the mean do not overlap)")  # fmt: skip
        against.append({
            "variant": variant, "against": first,
            "P(improvement)": None if c is None else c.probability_of_improvement.point,
            "P(improvement) 95% CI": None if c is None else _ci(c.probability_of_improvement),
            "success at budget": verdict,
        })  # fmt: skip
    out_sections: dict[str, list[dict[str, Any]]] = {
        "comparison": comparison, "learning speed": speed, "against the first arm": against,
    }  # fmt: skip
    if protocol is not None:
        out_sections["against the public reference"] = reference_rows(protocol, runs, boot)
    out_sections["runs"] = [r for rows in per_run.values() for r in rows]
    if task not in TASK_VARIANTS:  # the public anchor is Equi-RSAC's training loop
        out_sections["training loop against the public Equi-RSAC code"] = loop
    if out is not None:
        _write_pngs(task, runs, at_budget, out, boot, protocol)
    return out_sections


def _write_pngs(task: str, runs: dict[str, list[Path]], at_budget: dict[str, list[float]], out: Path,
                boot: stats.Bootstrap, protocol: Protocol | None) -> None:  # fmt: skip
    bands = {v: b for v in runs if (b := arm_band(runs[v], boot)) is not None and b.steps.size}
    if bands:
        render_curves(bands, protocol.reference if protocol else {}, protocol.reference_name if protocol else "",
                      out / f"curves-{task}.png",
                      f"{task}: success rate vs env steps (mean, 95% bootstrap CI over seeds)")  # fmt: skip
    profiles = stats.performance_profiles(at_budget, PROFILE_TAUS, boot)
    if profiles:
        render_profile(profiles, out / f"profile-{task}.png",
                       f"{task}: performance profile of success at the budget (95% CI)")  # fmt: skip


def run(cfg: LearningBenchConfig) -> dict:
    s = settings(cfg)
    for variant in s.variants:  # before training anything: no run directory with other settings
        for seed in s.seed_list:
            check_existing(cfg, variant, seed, s)
    started = time.monotonic()
    out = out_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    runs = train_all(cfg, s)
    RunConfig, _ = _mea_run()
    learner = s.learner or f"{RunConfig().learner_preset} (mea run's default)"
    boot = stats.Bootstrap(reps=cfg.bootstrap_reps, seed=cfg.bootstrap_seed)
    best = None
    if cfg.best_episodes:
        best = {d.name: best_policy.measure(d, cfg.best_episodes) for dirs in runs.values() for d in dirs}
    sections = summarize(cfg.task, runs, s.budget, out, learner, boot, s.protocol, best)
    meta = {"preset": cfg.preset, "protocol": cfg.protocol or None, "task": cfg.task, "budget": s.budget,
            "seeds": s.seeds, "seed list (every arm)": list(s.seed_list), "demos": s.demos,
            "random_steps": s.random_steps, "learner": learner, "eval_every": s.eval_every,
            "eval_episodes": s.eval_episodes, "final_eval_episodes": s.final_eval_episodes,
            "best_episodes": cfg.best_episodes,
            "parallel": cfg.parallel, "bootstrap": {"reps": boot.reps, "confidence": boot.confidence, "seed": boot.seed,
                          "method": "rliable stratified bootstrap, percentile"},
            "reference": None if s.protocol is None else s.protocol.reference_name,
            "curves_png": str(out / f"curves-{cfg.task}.png"), "profile_png": str(out / f"profile-{cfg.task}.png"),
            "out": str(out), "minutes": round((time.monotonic() - started) / 60, 1)}  # fmt: skip
    result = emit("learning", sections, measured={}, as_json=cfg.json, meta=meta)
    (out / f"result-{cfg.task}.json").write_text(json.dumps(result, indent=2, default=float) + "\n")
    return result
