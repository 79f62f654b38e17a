"""`mea run`'s settings: one frozen RunConfig (saved as RUN_DIR/config.json) from which every
service's own config is derived (``services.plan``), and how ``--resume`` reads a run back."""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import typeguard

from proto.episode import DSA_TASKS
from services.actor.config import MAX_ENVS, check_expert
from services.common.bus.zenoh_derive import check_run_file
from services.learner import init_actor
from services.learner.config import check_device, learner_presets, preset_name
from services.tasks import DEPTH_IMAGE_REVISION, TASK_CLASSES, EnvSettings
from services.variants import VARIANTS, check_task

SERVICE_ORDER = ("learner", "augmenter", "evaluator", "actor")
SERVICE_MODULES = {s: f"services.{s}.main" for s in SERVICE_ORDER}
"""Each service's shell: its ``run(config, bus_factory=None)`` runs the service."""


MEA_ON = ("", "demos", "successes", "all")
RANDOM_PREFILL = {"gasv2": 9_000, "gasv2-cpu-small": 1_000, "gasv2-smoke": 0}
"""Random prefill per learner preset (``learner.config.PRESETS`` names; none for the others): the
GASv2 reference's 9e3 random steps (`low_oracle3`, beside 10 oracle demos) on the paper's 420K; 1,000
on the CPU budget of 16-20K env steps."""
CPU_LEARNER_PRESETS = ("cpu-small", "cpu-small-state")
WANDB_MODES = ("offline", "online")
"""Learner presets for two CPU cores: MEA on online successes too, 64 rotated copies of successes."""

AUTO_RESERVED_CORES = 4
"""Cores ``--actors auto`` leaves to the rest of the run: the learner, the augmenter, the evaluator and
the launcher (the Zenoh router and the episode recorder)."""
AUTO_MAX_ACTORS = 12
"""``--actors auto`` never starts more: a 16-core workstation (the ``paper`` preset's machine) gets 12,
and larger machines no more. Actors wait at the learner's replay gate (updates per env step), so past
what the learner consumes more actors add host memory (three runs of 7 processes peaked at 14.3 GiB,
docs/gpu.md) and older policies in the replay, not env steps."""


def usable_cores() -> int:
    """Cores this process may run on: its CPU affinity (what a container or ``taskset`` allows), else
    the machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # no affinity on this platform
        return os.cpu_count() or 1


def auto_actors(cores: int) -> int:
    """``--actors auto`` on ``cores`` cores: one actor per core beyond ``AUTO_RESERVED_CORES``, at least
    1 and at most ``AUTO_MAX_ACTORS`` (2 cores: 1; 16 cores: 12)."""
    return max(1, min(AUTO_MAX_ACTORS, cores - AUTO_RESERVED_CORES))


@dataclass(frozen=True)
class RunConfig:
    """Run the full training stack locally."""

    task: str = "block_pull"
    """Task: block_pull, block_pick, drawer_open or surgical_grasp_any."""
    variant: str = "mea"
    """What the paper compares: equirsac, equiobs, mea, gasv2 or mea-gasv2."""
    mea_on: str = ""
    """mea variants: which episodes get MEA (demos, successes, all); empty: by preset."""
    env_steps: int = 40_000
    """Env-step budget, demos included (the paper: 40K); 0: until Ctrl-C."""
    learner_preset: str = "cpu-small"
    """Learner preset: cpu-small, cpu-small-state, paper or smoke."""
    learner_device: str = "cpu"
    """torch device of the learner: cpu, cuda or cuda:N."""
    learner_threads: int = 1
    """torch threads of the learner (1: it shares the cores with actors and augmenter; 0: torch's default)."""
    seed: int = 0
    """Run seed: actors' training seeds, augmentation, networks (evaluation seeds are fixed)."""
    eval_every: int = 1000
    """Evaluate the newest weights every this many env steps."""
    eval_episodes: int = 20
    """Episodes per evaluation (held-out seeds, deterministic policy)."""
    final_eval_episodes: int = 50
    """Episodes of the evaluation at the env-step budget."""
    eval_videos: int = 2
    """Episodes filmed per filmed evaluation (MP4 and TensorBoard); 0: none."""
    record: bool = True
    """Record every raw episode to RUN_DIR/episodes/*.mcap."""
    recording_segment_bytes: int = 256 * 2**20
    """Bytes per recording segment (0: no size limit)."""
    recording_segment_seconds: float = 3600.0
    """Seconds per recording segment (0: no age limit)."""
    recording_max_bytes: int = 0
    """Delete the oldest finished segments beyond this many bytes (0: keep all)."""
    follow_gate: bool = True
    """Actors wait for the learner's replay gate (off: actors run flat out; for benchmarks)."""
    resume: Path | None = None
    """Continue the run in this directory (docs/cli.md: what may change)."""
    resumes: int = 0
    """How many times the run was resumed (set by --resume; moves the actors' seed streams on)."""
    init_actor: Path | None = None
    """Start the learner's actor from these weights (a fresh run only)."""
    actors: int | Literal["auto"] = 1
    """Actor processes; auto: one per core beyond 4, 1 to 12 (saved as the number)."""
    envs_per_actor: int = 1
    """Envs each actor steps in lockstep, one batched policy step per tick (as that many actors)."""
    random_steps: int | None = None
    """Env steps of random episodes after the demos; None: the preset's."""
    demos: int | None = None
    """Scripted demonstrations pre-filled; None: the paper's for the task."""
    run_dir: Path | None = None
    """Run directory; default runs/<time>-<task>-<variant>."""
    listen: str = "tcp/127.0.0.1:7447"
    """Endpoint of the embedded Zenoh router; services connect to it."""
    connect: tuple[str, ...] = ()
    """Routers on other hosts the embedded router meshes with."""
    namespace: str = "default"
    """Key namespace of this run (separates runs sharing a Zenoh network)."""
    zenoh_config: str = ""
    """Zenoh's own config file (JSON5) for the embedded router (TLS, auth)."""
    authenticate: bool = True
    """Seal every message with the run's key (RUN_DIR/run.key)."""
    metrics_port: int = 9100
    """Port base of the run's /metrics (services add offsets); 0: off."""
    metrics_addr: str = "127.0.0.1"
    """Address every /metrics of the run binds to."""
    duration_seconds: float = 0.0
    """Stop after this many seconds (0: run until Ctrl-C / SIGTERM)."""
    stop_grace_seconds: float = 30.0
    """Seconds between SIGTERM and SIGKILL when stopping children."""
    stop_on_failure: bool = True
    """Stop the whole stack when a service keeps failing."""
    restart_limit: int = 3
    """Restarts of a failed service within the window (0: never restart)."""
    restart_window_seconds: float = 600.0
    """Window over which restarts count against restart_limit."""
    services: tuple[str, ...] = SERVICE_ORDER
    """Services to start (those not in this build are skipped, and listed)."""
    extra_services: tuple[str, ...] = ()
    """Additional `module:function` entries to start as services (plugins; used by tests)."""
    log_format: str = "text"
    """Log format of the launcher and its services: json or text."""
    track: bool = False
    """Also send RUN_DIR/tb to Weights & Biases (mea-rl[track])."""
    wandb_mode: str = "offline"
    """With --track: offline (files under RUN_DIR/wandb, `wandb sync` uploads them) or online."""
    final_eval_seconds: float = 900.0
    """Wait at the budget for the last weights' evaluation, in seconds."""

    in_process: bool = False
    """Run every service in this process over the in-process bus."""

    learner_args: str = ""
    """Flags of `mea learner` applied to the learner preset (one string)."""

    success_rotations: int | None = None
    """Rotated copies of each demo and success; None: the preset's."""

    gripper_start: str = "random"
    """Gripper at reset: random (MEA's premise) or fixed (public Equi-RSAC: centre, yaw 0)."""

    jump_start: float = 0.0
    """Share of learned episodes that replay one of the run's demos up to a drawn step, then act (JSRL)."""

    expert: str = "observable"
    """Demos' expert: observable, or privileged (the first object by its hidden fixedness)."""

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
        return RANDOM_PREFILL.get(self.learner_preset_name(), 0)

    def learner_preset_name(self) -> str:
        """The learner preset (``learner.config.PRESETS``) that ``learner_preset`` names in the table of
        the variant's algorithm."""
        return preset_name(VARIANTS[self.variant].algorithm, self.learner_preset)

    def resolved_mea_on(self) -> str:
        """What the mea variant runs MEA on: ``mea_on``, else the learner preset's default (the CPU
        recipe adds online successes: beyond the two demos, they are the only other layouts)."""
        return self.mea_on or ("successes" if self.learner_preset in CPU_LEARNER_PRESETS else "demos")

    def __post_init__(self) -> None:
        self._check_actors()
        if self.restart_limit < 0 or self.restart_window_seconds <= 0:
            raise ValueError("restart_limit must be >= 0 and restart_window_seconds > 0")
        if min(self.recording_segment_bytes, self.recording_segment_seconds, self.recording_max_bytes) < 0:
            raise ValueError("recording_segment_bytes, _seconds and recording_max_bytes must be >= 0")
        if self.success_rotations is not None and self.success_rotations < 0:
            raise ValueError("success_rotations must be >= 0")
        EnvSettings(gripper_start=self.gripper_start)  # its check of the start pose
        if self.gripper_start != "random" and self.task in DSA_TASKS:
            raise ValueError(
                f"gripper_start {self.gripper_start!r} is for the manipulation tasks, not {self.task}"
            )
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {tuple(VARIANTS)}, not {self.variant!r}")
        self._check_demos()
        self._check_jump_start()
        if self.mea_on not in MEA_ON:
            raise ValueError(f"mea_on must be one of {MEA_ON[1:]}, not {self.mea_on!r}")
        if self.mea_on and not VARIANTS[self.variant].mea:
            raise ValueError("--mea-on applies to --variant mea and mea-gasv2 only")
        if self.task not in TASK_CLASSES:
            raise ValueError(f"--task must be one of {', '.join(TASK_CLASSES)}, not {self.task!r}")
        check_task(self.variant, self.task)
        self._check_learner_preset()
        check_device(self.learner_device, "--learner-device")
        if self.learner_threads < 0:
            raise ValueError(
                f"--learner-threads must be >= 0 (0: torch's default), not {self.learner_threads}"
            )
        if self.eval_videos < 0:
            raise ValueError("--eval-videos must be >= 0 (0: no evaluation videos)")
        if self.wandb_mode not in WANDB_MODES:
            raise ValueError(f"--wandb-mode must be one of {', '.join(WANDB_MODES)}, not {self.wandb_mode!r}")
        if self.env_steps < 0 or min(self.eval_every, self.eval_episodes, self.final_eval_episodes) < 1:
            raise ValueError("env_steps must be >= 0, eval_every, eval_episodes and final_eval_episodes >= 1")
        unknown = set(self.services) - set(SERVICE_ORDER)
        if unknown:
            raise ValueError(f"unknown services {sorted(unknown)}; choose from {SERVICE_ORDER}")
        self._check_init_actor()
        # a file the router or the run's services cannot use: refused before anything starts
        check_run_file(self.zenoh_config, self.listen, self.connect, self.namespace, self.in_process)

    def _check_actors(self) -> None:
        if self.actors == "auto":  # resolved here once: config.json and every service see the number
            object.__setattr__(self, "actors", auto_actors(usable_cores()))
        if not isinstance(self.actors, int) or self.actors < 0:
            raise ValueError(f"--actors must be >= 0 or auto, not {self.actors!r}")
        if not isinstance(self.envs_per_actor, int) or not 1 <= self.envs_per_actor <= MAX_ENVS:
            raise ValueError(f"--envs-per-actor must be in 1..{MAX_ENVS}, not {self.envs_per_actor!r}")

    def _check_demos(self) -> None:
        if (self.demos is not None and self.demos < 0) or (
            self.random_steps is not None and self.random_steps < 0
        ):
            raise ValueError("demos and random_steps must be >= 0")
        check_expert(self.expert)

    def _check_jump_start(self) -> None:
        if not 0.0 <= self.jump_start <= 1.0:
            raise ValueError(f"--jump-start must be in [0, 1], not {self.jump_start}")
        if self.jump_start == 0:
            return
        if self.task in DSA_TASKS:  # its episodes draw conditions besides the seed: no replay by seed
            raise ValueError(f"--jump-start is for the manipulation tasks, not {self.task}")
        if self.resolved_demos() < 1:
            raise ValueError("--jump-start replays the run's demonstrations: give --demos >= 1")

    def _check_learner_preset(self) -> None:
        """The preset must be one of the variant's algorithm's (``learner.config.learner_presets``)."""
        choices = learner_presets(VARIANTS[self.variant].algorithm)
        if self.learner_preset not in choices:
            raise ValueError(f"--learner-preset must be one of {', '.join(choices)} with --variant "
                             f"{self.variant}, not {self.learner_preset!r}")  # fmt: skip

    def _check_init_actor(self) -> None:
        if self.init_actor is None:
            return
        if self.resume is not None:
            raise ValueError("--init-actor starts a fresh run; a resumed run (--resume) continues from its "
                             "learner's checkpoint")  # fmt: skip
        if not init_actor.supports(VARIANTS[self.variant].algorithm):
            raise ValueError(f"--init-actor applies to the Equi-RSAC variants, not {self.variant!r}")


PRESETS = {"default": RunConfig()}


def recording_metadata(cfg: RunConfig) -> dict[str, str]:
    """The ``run`` metadata record of that recording (proto/README.md, section 5)."""
    return {"task": cfg.task, "variant": cfg.variant, "seed": str(cfg.seed), "resumes": str(cfg.resumes)}


_MACHINE_FIELDS = ("listen", "connect", "metrics_port", "metrics_addr", "duration_seconds", "stop_grace_seconds",
                   "log_format", "final_eval_seconds", "in_process", "zenoh_config", "learner_device", "learner_threads",
                   "track", "wandb_mode")  # fmt: skip
"""Fields a resumed run takes from the command line rather than from the run's saved config."""


RESUMABLE = ("env_steps", "eval_every", "actors", "envs_per_actor", "final_eval_episodes")
"""Run settings a resume may change (each change is recorded in config.json's ``history``): the
budget, the evaluation cadence, the actor count and the size of the evaluation at the budget. Any
other run setting given with --resume is refused by name; this machine's (``_MACHINE_FIELDS``) are
always the command line's."""


def flag(field: str) -> str:
    """The command-line spelling of a RunConfig field."""
    return "--" + field.replace("_", "-")


@dataclass(frozen=True)
class Resumed:
    """What ``--resume RUN_DIR`` continues: the saved settings with this sitting's, and config.json's
    history of resumes with this one last (``{"resume": n, "changed": {field: [old, new]}}``)."""

    config: RunConfig
    history: tuple[dict, ...]


def _saved_value(name: str, value: object, hint: object) -> object:
    """A config.json value as the field's type (JSON has lists for tuples, strings for paths);
    ValueError naming the field when it is not of that type."""
    options = typing.get_args(hint) or (hint,)
    if isinstance(value, str) and Path in options:
        value = Path(value)
    elif isinstance(value, list) and typing.get_origin(hint) is tuple:
        value = tuple(value)
    try:
        typeguard.check_type(value, hint)
    except typeguard.TypeCheckError as exc:
        raise ValueError(f"its {name} is {value!r} ({exc})") from None
    return value


def read_resume(cfg: RunConfig, given: Collection[str] = ()) -> Resumed:
    """``--resume RUN_DIR``: the run's saved config with this machine's settings, the ``RESUMABLE``
    ones ``given`` on the command line, resumes + 1. ValueError (one line, naming the option) for any
    other run setting ``given`` (field names), or a run directory whose config.json does not make a
    run; nothing is written here."""
    run_dir = Path(cfg.resume)  # type: ignore[arg-type]
    refused = [flag(f) for f in sorted(given) if f not in (*RESUMABLE, *_MACHINE_FIELDS, "resume")]
    if refused:
        raise ValueError(f"{', '.join(refused)} cannot change on --resume (the run keeps the settings in its "
                         f"config.json); a resume may change {', '.join(map(flag, RESUMABLE))} and this "
                         f"machine's {', '.join(map(flag, _MACHINE_FIELDS))}")  # fmt: skip
    path = run_dir / "config.json"
    if not run_dir.is_dir():
        raise ValueError(f"--resume {run_dir}: no such run directory")
    try:
        saved = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"--resume {run_dir}: no config.json there (not a directory of `mea run`)") from None
    except OSError as exc:
        raise ValueError(f"--resume {run_dir}: cannot read config.json ({exc.strerror})") from None
    except ValueError as exc:
        raise ValueError(f"--resume {run_dir}: config.json is not JSON ({exc})") from None
    if not isinstance(saved, dict):
        raise ValueError(
            f"--resume {run_dir}: config.json holds a {type(saved).__name__}, not a run's settings"
        )
    name = saved.get("variant", RunConfig.variant)
    variant = VARIANTS.get(name) if isinstance(name, str) else None  # a damaged name: refused below
    revision = saved.get("depth_image_revision", 1)
    if variant is not None and variant.depth_image and revision != DEPTH_IMAGE_REVISION:
        raise ValueError(
            f"--resume {run_dir}: its depth images are of revision {revision!r}, this version renders "
            f"revision {DEPTH_IMAGE_REVISION} (the floor drawn): its replay would mix two observations; "
            "start a new run"
        )
    hints = typing.get_type_hints(RunConfig)
    known = {f.name for f in dataclasses.fields(RunConfig)}
    try:
        values = {
            k: _saved_value(k, v, hints[k])
            for k, v in saved.items()
            if k in known and k not in _MACHINE_FIELDS
        }
    except ValueError as exc:
        raise ValueError(f"--resume {run_dir}: config.json is damaged: {exc}") from None
    values.pop("init_actor", None)  # a fresh run's start: the resumed learner continues its checkpoint
    resumes = values.get("resumes", 0) + 1
    changed = {}
    for k in RESUMABLE:
        old = values.get(k, getattr(RunConfig, k))
        if k in given and getattr(cfg, k) != old:
            changed[k] = [old, getattr(cfg, k)]
            values[k] = getattr(cfg, k)
    values.update(run_dir=run_dir, resume=run_dir, resumes=resumes)
    values.update({k: getattr(cfg, k) for k in _MACHINE_FIELDS})
    try:
        resumed = RunConfig(**values)
    except ValueError as exc:
        raise ValueError(f"--resume {run_dir}: config.json does not make a run: {exc}") from None
    history = saved.get("history")
    history = tuple(h for h in history if isinstance(h, dict)) if isinstance(history, list) else ()
    return Resumed(resumed, (*history, {"resume": resumes, "changed": changed}))


def resumed_config(cfg: RunConfig, given: Collection[str] = ()) -> RunConfig:
    """``read_resume``'s config."""
    return read_resume(cfg, given).config
