"""`mea run`'s settings: one frozen RunConfig (saved as RUN_DIR/config.json) from which every
service's own config is derived (``services.plan``), and how ``--resume`` reads a run back."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

from proto.episode import DSA_TASKS
from services.variants import VARIANTS, check_task

SERVICE_ORDER = ("learner", "augmenter", "evaluator", "actor")
SERVICE_MODULES = {s: f"services.{s}.main" for s in SERVICE_ORDER}
"""Each service's shell: its ``run(config, bus_factory=None)`` runs the service."""


MEA_ON = ("", "demos", "successes", "all")
GASV2_PRESETS = {"paper": "gasv2", "cpu-small": "gasv2-cpu-small", "smoke": "gasv2-smoke"}
"""The GASv2 learner preset a run's ``learner_preset`` stands for with a GASv2 variant."""
RANDOM_PREFILL = {"paper": 9_000, "cpu-small": 1_000, "smoke": 0}
"""GASv2 runs' random prefill per learner preset: the reference's 9e3 random steps (`low_oracle3`,
beside 10 oracle demos) on the paper's 420K; 1,000 on the CPU budget of 16-20K env steps."""
CPU_LEARNER_PRESETS = ("cpu-small", "cpu-small-state")
"""Learner presets for two CPU cores: MEA on online successes too, 64 rotated copies of successes."""


@dataclass(frozen=True)
class RunConfig:
    """Run the full training stack locally."""

    task: str = "block_pull"
    """Task: block_pull, block_pick, drawer_open or surgical_grasp_any."""
    variant: str = "mea"
    """What the paper compares. General manipulation (Equi-RSAC learner): equirsac (rendered depth
    image, isometric x4), equiobs (voxel projection, isometric x4), mea (voxel projection, isometric x4
    + MEA x6 on the demos, and with the cpu-small learner on online successes too: see mea_on).
    surgical_grasp_any (GASv2 learner): gasv2 (DSA image) or mea-gasv2 (+ MEA x200, as mea_on says)."""
    mea_on: str = ""
    """mea and mea-gasv2 variants only: which episodes get MEA (demos: the paper; successes: the demos and every online
    success; all). Empty: successes with the cpu-small learner preset, demos with the others."""
    env_steps: int = 40_000
    """Env-step budget (the paper: 40K, demos included); the run stops after the evaluation at the
    budget. 0: run until Ctrl-C."""
    learner_preset: str = "cpu-small"
    """Learner preset: cpu-small (two CPU cores), cpu-small-state (the same with a critic on the
    simulator's state), paper (a GPU workstation), smoke (tests)."""
    learner_device: str = "cpu"
    """torch device of the learner (cuda on a GPU workstation; the GASv2 learner only, for now)."""
    seed: int = 0
    """Run seed: actors' training seeds, augmentation, networks (evaluation seeds are fixed)."""
    eval_every: int = 1000
    """Evaluate the newest weights every this many env steps (Equi-RSAC: 250-500; raise it on CPU)."""
    eval_episodes: int = 20
    """Evaluation episodes per evaluation (held-out seeds from 1e9, the same every time; deterministic
    policy)."""
    final_eval_episodes: int = 50
    """Episodes of the evaluation at the env-step budget (the same held-out seed sequence, its first
    final_eval_episodes seeds)."""
    record: bool = True
    """Record every raw episode to RUN_DIR/episodes/raw-<n>-<k>.mcap (n: resume count; k: segment,
    each a complete MCAP file)."""
    recording_segment_bytes: int = 256 * 2**20
    """Start the next recording segment once the open one holds this many bytes (0: no size limit)."""
    recording_segment_seconds: float = 3600.0
    """Start the next recording segment once the open one has been open this long (0: no age limit)."""
    recording_max_bytes: int = 0
    """Delete the oldest finished recording segments (every resume's) while they take more than this
    many bytes; the newest finished one and the open one always stay. 0: keep everything."""
    follow_gate: bool = True
    """Actors wait for the learner's replay gate (off: actors run flat out; for benchmarks)."""
    resume: Path | None = None
    """Continue the run in this directory (its saved config; learner checkpoint; no new demos)."""
    resumes: int = 0
    """How many times the run was resumed (set by --resume; moves the actors' seed streams on)."""
    actors: int = 1
    """Number of actor processes."""
    random_steps: int | None = None
    """Env steps of uniformly random episodes after the demonstrations (the replay's random prefill);
    None: the learner preset's for the variant (GASv2: 9,000 with paper as the reference, 1,000
    with cpu-small, 0 with smoke; the Equi-RSAC variants: 0)."""
    demos: int | None = None
    """Scripted demonstrations pre-filled before training; None: the paper's setting for the task
    (2 for the general manipulation tasks, 10 for surgical_grasp_any)."""
    run_dir: Path | None = None
    """Run directory (config, checkpoints, eval history, recordings); default runs/<time>-<task>-<variant>."""
    listen: str = "tcp/127.0.0.1:7447"
    """Endpoint of the embedded Zenoh router; services connect to it."""
    connect: tuple[str, ...] = ()
    """Routers on other hosts the embedded router meshes with (e.g. `tcp/10.0.0.5:7447`; one run across
    hosts: deploy/multihost.md). With it, actors follow the learned policy even without a learner here."""
    namespace: str = "default"
    """Key namespace of this run (separates runs sharing a Zenoh network)."""
    authenticate: bool = True
    """Seal every message with the run's key (RUN_DIR/run.key, created at run start, owner-only):
    services accept only what the run's own services sealed, each on the topics it may write
    (proto/seal.py). Services joining from another host need a copy of the key file."""
    metrics_port: int = 9100
    """Port base of the run's /metrics: the launcher serves it (router traffic, services alive), each
    service the base plus its offset (learner +1, augmenter +2, evaluator +3, actor i +10+i; README).
    A second run on one host takes another base (e.g. 9200). 0 disables every /metrics."""
    metrics_addr: str = "127.0.0.1"
    """Address every /metrics of the run binds to (0.0.0.0: reachable by a Prometheus on another host)."""
    duration_seconds: float = 0.0
    """Stop after this many seconds (0: run until Ctrl-C / SIGTERM)."""
    stop_grace_seconds: float = 30.0
    """How long children get to exit after SIGTERM before SIGKILL (the learner writes its final
    checkpoint then; others exit within a second or two)."""
    stop_on_failure: bool = True
    """If a service keeps exiting (more than restart_limit restarts within restart_window_seconds),
    stop the whole stack (otherwise keep running without it)."""
    restart_limit: int = 3
    """Restarts of a service instance that exited on its own, with backoff (1, 2, 4 ... 30 s), within
    restart_window_seconds before the launcher gives up on it (0: never restart). A restarted actor
    records no demos again and takes fresh seeds; a restarted learner resumes from its checkpoint."""
    restart_window_seconds: float = 600.0
    """Window over which restarts count against restart_limit."""
    services: tuple[str, ...] = SERVICE_ORDER
    """Services to start (those not in this build are skipped, and listed)."""
    extra_services: tuple[str, ...] = ()
    """Additional `module:function` entries to start as services (plugins; used by tests)."""
    log_format: str = "text"
    """Log format of the launcher and its services: json or text."""
    final_eval_seconds: float = 900.0
    """At the budget, how long to wait for the evaluation of the last weights (final_eval_episodes
    episodes) before stopping."""

    in_process: bool = False
    """Run every service in this one process over the in-process bus (debugging, fast tests) instead
    of separate processes over the embedded Zenoh router; same services, same configs."""

    success_rotations: int | None = None
    """Rotated copies of each demonstration and online success (every variant; other episodes get
    4). None: the learner preset's default (cpu-small: 64, the paper: 4 like every episode)."""

    def resolved_success_rotations(self) -> int:
        """``success_rotations``, else the learner preset's default: the CPU recipe clones its few
        successes, and BC of 2 Block Pull demos reached 0.23-0.33 with 64 rotated copies against
        0.05-0.10 with 4 (30 held-out seeds, 3000 updates)."""
        if self.success_rotations is not None:
            return self.success_rotations
        return 64 if self.learner_preset in CPU_LEARNER_PRESETS else 0

    def resolved_demos(self) -> int:
        """``demos``, else the paper's: 10 on surgical_grasp_any (Sec. VI), 2 on the general tasks."""
        if self.demos is not None:
            return self.demos
        return 10 if self.task in DSA_TASKS else 2

    def resolved_random_steps(self) -> int:
        """``random_steps``, else the learner preset's prefill for the variant (``RANDOM_PREFILL``)."""
        if self.random_steps is not None:
            return self.random_steps
        if VARIANTS[self.variant].algorithm != "gasv2":
            return 0
        return RANDOM_PREFILL.get(self.learner_preset, 0)

    def resolved_mea_on(self) -> str:
        """What the mea variant runs MEA on: ``mea_on``, else the learner preset's default (the CPU
        recipe adds online successes: beyond the two demos, they are the only other layouts)."""
        return self.mea_on or ("successes" if self.learner_preset in CPU_LEARNER_PRESETS else "demos")

    def __post_init__(self) -> None:
        if self.actors < 0:
            raise ValueError("actors must be >= 0")
        if self.restart_limit < 0 or self.restart_window_seconds <= 0:
            raise ValueError("restart_limit must be >= 0 and restart_window_seconds > 0")
        if min(self.recording_segment_bytes, self.recording_segment_seconds, self.recording_max_bytes) < 0:
            raise ValueError("recording_segment_bytes, _seconds and recording_max_bytes must be >= 0")
        if self.success_rotations is not None and self.success_rotations < 0:
            raise ValueError("success_rotations must be >= 0")
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {tuple(VARIANTS)}, not {self.variant!r}")
        if self.mea_on not in MEA_ON:
            raise ValueError(f"mea_on must be one of {MEA_ON[1:]}, not {self.mea_on!r}")
        if self.mea_on and not VARIANTS[self.variant].mea:
            raise ValueError("--mea-on applies to --variant mea and mea-gasv2 only")
        check_task(self.variant, self.task)
        if self.learner_device != "cpu" and VARIANTS[self.variant].algorithm != "gasv2":
            raise ValueError(
                f"learner_device {self.learner_device!r}: only the gasv2 learner runs off the CPU"
            )
        if VARIANTS[self.variant].algorithm == "gasv2" and self.learner_preset not in GASV2_PRESETS:
            raise ValueError(f"learner preset {self.learner_preset!r} has no gasv2 learner; choose one of "
                             f"{sorted(GASV2_PRESETS)}")  # fmt: skip
        if (self.demos is not None and self.demos < 0) or (
            self.random_steps is not None and self.random_steps < 0
        ):
            raise ValueError("demos and random_steps must be >= 0")
        if self.env_steps < 0 or min(self.eval_every, self.eval_episodes, self.final_eval_episodes) < 1:
            raise ValueError("env_steps must be >= 0, eval_every, eval_episodes and final_eval_episodes >= 1")
        unknown = set(self.services) - set(SERVICE_ORDER)
        if unknown:
            raise ValueError(f"unknown services {sorted(unknown)}; choose from {SERVICE_ORDER}")


PRESETS = {"default": RunConfig()}


def recording_metadata(cfg: RunConfig) -> dict[str, str]:
    """The ``run`` metadata record of that recording (proto/README.md, section 5)."""
    return {"task": cfg.task, "variant": cfg.variant, "seed": str(cfg.seed), "resumes": str(cfg.resumes)}


_MACHINE_FIELDS = ("listen", "connect", "metrics_port", "metrics_addr", "duration_seconds", "stop_grace_seconds",
                   "log_format", "final_eval_seconds", "in_process")  # fmt: skip
"""Fields a resumed run takes from the command line rather than from the run's saved config."""


def resumed_config(cfg: RunConfig) -> RunConfig:
    """``--resume RUN_DIR``: the run's saved config, with this machine's settings, resumes + 1."""
    path = Path(cfg.resume) / "config.json"
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"mea run: cannot resume from {path}: {exc}") from None
    known = {f.name: f for f in dataclasses.fields(RunConfig)}
    values = {k: v for k, v in saved.items() if k in known and k not in _MACHINE_FIELDS}
    for k in ("services", "extra_services"):
        if k in values:
            values[k] = tuple(values[k])
    values.update(run_dir=Path(cfg.resume), resume=Path(cfg.resume), resumes=int(saved.get("resumes", 0)) + 1)
    values.update({k: getattr(cfg, k) for k in _MACHINE_FIELDS})
    return RunConfig(**values)
