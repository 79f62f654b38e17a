"""The learner's settings: `LearnerConfig` (the algorithm's own config inside it), one preset table
per algorithm, the run id a fresh run gets, and the trainer a config describes (``build_trainer``).

No transport, so that the benchmarks, the tests and the shell (``services.learner.main``) share one
definition.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import time
from collections.abc import Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro

from services.algorithms.gasv2.algorithm import GasV2Config
from services.algorithms.gasv2.config import PRESETS as DREAMER_PRESETS
from services.algorithms.networks import PRESETS as NET_PRESETS
from services.algorithms.rate_limiter import SampleToInsertRatio
from services.algorithms.registry import lookup
from services.algorithms.sac.algorithm import SacConfig
from services.algorithms.sac.config import SacSettings
from services.algorithms.trainer import Trainer
from services.common.config import ServiceConfig

DEVICES = re.compile(r"cpu|cuda(:\d+)?")
"""Learner devices: the CPU or a CUDA GPU (``cuda`` is the current one, ``cuda:N`` the N-th)."""

AlgorithmSettings = Annotated[
    SacConfig | GasV2Config, tyro.conf.arg(name="", prefix_name=False), tyro.conf.AvoidSubcommands
]
"""The algorithm's own config, its fields flags of their own (``--algorithm``, ``--net.*``, ``--sac.*``,
``--dreamer.*``, ``--observation``): a preset picks the algorithm, the flags change its fields."""


def check_device(device: str, option: str) -> None:
    """ValueError in one line naming ``option`` unless ``device`` is cpu, cuda or cuda:N and, for
    CUDA, such a GPU is visible to this process."""
    if not DEVICES.fullmatch(device):
        raise ValueError(f"{option} must be cpu, cuda or cuda:N, not {device!r}")
    if device == "cpu":
        return
    if not torch.cuda.is_available():
        why = "torch is built without CUDA" if torch.version.cuda is None else "no GPU is visible"
        raise ValueError(f"{option} {device!r}: CUDA is unavailable here ({why}, torch {torch.__version__}); "
                         "use cpu")  # fmt: skip
    count, index = torch.cuda.device_count(), torch.device(device).index
    if index is not None and index >= count:
        raise ValueError(
            f"{option} {device!r}: this machine has {count} CUDA device(s), cuda:0..cuda:{count - 1}"
        )


def prepare_device(device: str) -> torch.device:
    """``device`` as a torch device; on CUDA, allow TF32 (10-bit mantissa) for the process's fp32
    matmuls (oneDNN's on the CPU too, where it has TF32: a CUDA learner's are on the GPU) and cuDNN
    convolutions and LSTMs. Set through the long-standing switches, which keep torch's old and new
    views of the setting in step (mixing the two APIs makes torch raise when it reads them)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.set_float32_matmul_precision("high")
        torch.backends.cudnn.allow_tf32 = True  # torch's default, stated
    return dev


@dataclass(frozen=True)
class LearnerConfig:
    """Train a learner (recurrent SAC or GASv2) on replayed episodes; broadcast its weights."""

    algorithm: AlgorithmSettings = field(default_factory=SacConfig)
    """The algorithm and its settings (SacConfig or GasV2Config)."""
    replay_capacity: int = 100_000
    """Replay size in transitions."""
    batch_size: int = 32
    """Episodes (SAC) or windows (gasv2) per update."""
    demo_fraction: float = 0.0
    """Batch share from the demos (0: uniform)."""
    successes_as_demos: bool = False
    """Successes join the demo set."""
    seq_len: int = 50
    """Longest episode stored (the time limit)."""
    samples_per_insert: float = 1.0
    """Updates per raw env step (Equi-RSAC: 1)."""
    min_steps: int = 100
    """Raw env steps before the first update."""
    error_buffer: float = 200.0
    """The replay gate's slack in updates."""
    publish_every: int = 10
    """Updates between weights announcements."""
    checkpoint_minutes: float = 10.0
    """Checkpoint period, minutes (0: off)."""
    checkpoint_every: int = 0
    """Also checkpoint every N updates (0: off)."""
    keep_checkpoints: int = 3
    """Checkpoints kept, newest first (at least 1)."""
    checkpoint_max_bytes: int = 0
    """Checkpoint bytes kept at most (0: no budget)."""
    run_dir: Path = Path("runs/learner")
    """Run directory: config and checkpoints/."""
    run_id: str = ""
    """Version lineage id (empty: derived)."""
    resume: bool = False
    """Continue from run_dir/checkpoints if any."""
    init_actor: Path | None = None
    """Actor's starting weights (no checkpoint)."""
    max_updates: int = 0
    """Stop after N updates (0: never)."""
    max_env_steps: int = 0
    """Env-step budget of the run (0: none)."""
    tensorboard_dir: Path | None = None
    """TensorBoard directory; None: off."""
    tensorboard_every: int = 50
    """Updates per TensorBoard point."""
    threads: int = 0
    """torch intra-op threads (0: torch's default)."""
    device: str = "cpu"
    """torch device: cpu, cuda or cuda:N."""
    seed: int = 0
    """Seed of nets, sampling and exploration."""
    queue: int = 64
    """Incoming episodes buffered before ingest."""
    inbox_mb: int = 1024
    """Inbox MiB during checkpoints."""
    gate_seconds: float = 0.5
    """Period of the replay gate."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""

    def __post_init__(self) -> None:
        for name in ("batch_size", "seq_len", "publish_every", "queue", "inbox_mb"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
        if self.keep_checkpoints < 1 or self.checkpoint_max_bytes < 0:
            raise ValueError("keep_checkpoints must be >= 1 and checkpoint_max_bytes >= 0")
        if self.replay_capacity < self.seq_len:
            raise ValueError("replay_capacity must hold at least one episode (>= seq_len)")
        if not 0.0 <= self.demo_fraction <= 1.0:
            raise ValueError(f"demo_fraction must be in [0, 1], got {self.demo_fraction}")
        check_device(self.device, "--device")
        if getattr(self.algorithm, "cuda_graphs", False) and not self.device.startswith("cuda"):
            raise ValueError(
                f"--cuda-graphs needs a CUDA learner (--device cuda), not --device {self.device}"
            )
        if self.samples_per_insert <= 0 or self.min_steps < 0 or self.error_buffer < 0:
            raise ValueError("samples_per_insert must be > 0, min_steps and error_buffer >= 0")

    @property
    def metrics_every(self) -> int:
        """Updates per read of the update statistics: each one on the CPU, means over
        tensorboard_every on a GPU (``core.trainer.MetricsWindow``)."""
        return 1 if self.device == "cpu" else max(1, self.tensorboard_every)


# One preset table per algorithm. `mea learner --preset` takes Equi-RSAC's names as they are and
# GASv2's prefixed (``PRESETS``); `mea run --learner-preset` names a row of its variant's table.
_CPU_SMALL_SAC = SacConfig(
    net=dataclasses.replace(NET_PRESETS["cpu-small"], critic_layer_norm=True, actor_prev_action=False),
    sac=SacSettings(
        init_alpha=0.01, bc_weight=2.0, share_encoder=True, return_bound=True, alpha_loss="log_alpha"
    ),
)
SAC_PRESETS: dict[str, LearnerConfig] = {
    "paper": LearnerConfig(),
    # cpu-small: the recipe for two CPU cores and a 20K env-step budget (docs/learners.md, "Presets"). Cuts:
    # halved network widths, 8 episodes per batch instead of 32, 0.5 updates per env step instead of
    # 1 (the replay gate lets actors run 2 steps per update). Additions, each a field: half of every
    # batch from the demonstration set (demos, their copies, online successes), a BC term, alpha from
    # 0.01, LayerNorm in the Q MLPs, one encoder shared by actor and critic, critic targets bounded
    # below by the observed return; replay 200k holds a whole 20K-step run with its copies.
    "cpu-small": LearnerConfig(
        algorithm=_CPU_SMALL_SAC,
        demo_fraction=0.5,
        successes_as_demos=True,
        batch_size=8,
        samples_per_insert=0.5,
        replay_capacity=200_000,
        min_steps=100,
        error_buffer=100.0,
        publish_every=5,
        checkpoint_minutes=5.0,
    ),
    # smoke: the cpu-small networks at the smallest useful batch, for end-to-end tests of the stack
    # (weights versions every 2 updates); it does not learn anything in the time it runs.
    "smoke": LearnerConfig(
        algorithm=SacConfig(net=NET_PRESETS["cpu-small"]),
        batch_size=2,
        samples_per_insert=0.5,
        replay_capacity=5_000,
        min_steps=50,
        error_buffer=50.0,
        publish_every=2,
        checkpoint_minutes=1.0,
    ),
}
# cpu-small-state: cpu-small with a critic on the simulator's privileged state instead of images (an
# asymmetric actor-critic: ``privileged.py``; the policy still reads images, and the critic is used
# in simulation only). Same demo share, BC, temperature and return bound; no shared encoder (the
# critic has none) and no critic LayerNorm (the state critic's MLPs have their own). Its updates are
# cheaper, so it affords the paper's 1.0 update per env step in about 35 minutes for 20K env steps
# (Block Pull at 20K: 0.48 and 0.28 for seeds 0 and 1, against 0.28 with 0.5 for seed 0; docs/results.md).
SAC_PRESETS["cpu-small-state"] = dataclasses.replace(
    SAC_PRESETS["cpu-small"],
    algorithm=dataclasses.replace(
        _CPU_SMALL_SAC,
        net=dataclasses.replace(_CPU_SMALL_SAC.net, critic_input="state", critic_layer_norm=False),
        sac=dataclasses.replace(_CPU_SMALL_SAC.sac, share_encoder=False),
    ),
    samples_per_insert=1.0,
)

# GASv2 on Surgical Grasp Any (the reference's training settings, tasks-and-baselines.md section 5):
# windows of 6 observations, 100 per update, one update per 2 env steps (`train_every` 2), replay
# 5e5 transitions, episodes of at most 80 steps; demos and their MEA copies are pinned in replay.
# The reference's 9e3 random prefill steps are the actors' (`mea run --random-steps`); training
# starts once min_steps env steps are in.
_gasv2 = LearnerConfig(
    algorithm=GasV2Config(dreamer=DREAMER_PRESETS["paper"], chunk_length=6),
    batch_size=100,
    seq_len=80,
    replay_capacity=500_000,
    samples_per_insert=0.5,
    min_steps=10_000,
    error_buffer=200.0,
    publish_every=10,
)
GASV2_PRESETS: dict[str, LearnerConfig] = {
    "paper": _gasv2,
    # cpu-small: two CPU cores (16K env steps in about 40 minutes; docs/learners.md, "GASv2"): the
    # world model's cpu-small widths (gasv2/config.py), 16 windows per update instead of 100, training
    # from 500 env steps, and the demo-aware sampling of the cpu-small SAC recipe (half of every batch
    # from the demos, their copies and online successes); everything else as paper.
    "cpu-small": dataclasses.replace(
        _gasv2,
        algorithm=GasV2Config(dreamer=DREAMER_PRESETS["cpu-small"]),
        batch_size=16,
        replay_capacity=200_000,
        min_steps=500,
        error_buffer=100.0,
        demo_fraction=0.5,
        successes_as_demos=True,
        publish_every=5,
        checkpoint_minutes=5.0,
    ),
    # smoke: tiny networks and batches for end-to-end tests of the stack; learns nothing.
    "smoke": dataclasses.replace(
        _gasv2,
        algorithm=GasV2Config(dreamer=DREAMER_PRESETS["smoke"]),
        batch_size=2,
        replay_capacity=20_000,
        min_steps=50,
        error_buffer=50.0,
        publish_every=2,
        checkpoint_minutes=1.0,
    ),
}

PRESET_TABLES: dict[type, tuple[str, dict[str, LearnerConfig]]] = {
    SacConfig: ("", SAC_PRESETS),
    GasV2Config: ("gasv2", GASV2_PRESETS),
}
"""Each algorithm config type's preset table and the prefix of its names in ``PRESETS``."""


def _flat_name(prefix: str, name: str) -> str:
    return name if not prefix else prefix if name == "paper" else f"{prefix}-{name}"


PRESETS: dict[str, LearnerConfig] = {
    _flat_name(prefix, name): cfg for prefix, table in PRESET_TABLES.values() for name, cfg in table.items()
}
"""`mea learner --preset NAME`: every table's presets (paper, cpu-small, ..., gasv2, gasv2-cpu-small, ...)."""


def learner_presets(algorithm: str) -> tuple[str, ...]:
    """The preset names of ``algorithm``'s table (a run's ``--learner-preset`` choices)."""
    return tuple(PRESET_TABLES[lookup(algorithm).config][1])


def preset_name(algorithm: str, name: str) -> str:
    """The ``PRESETS`` name of ``algorithm``'s preset ``name``; ValueError naming its presets otherwise."""
    prefix, table = PRESET_TABLES[lookup(algorithm).config]
    if name not in table:
        raise ValueError(
            f"learner preset {name!r} has no {algorithm} learner; choose one of {', '.join(table)}"
        )
    return _flat_name(prefix, name)


class _Peek(argparse.ArgumentParser):
    """A look at one option before the real parse: never prints, never exits."""

    def error(self, message: str):  # type: ignore[override]
        raise ValueError(message)


def without_foreign_group(argv: Sequence[str]) -> list[str]:
    """`mea learner`'s ``argv`` less ``--net.group G`` where its preset's algorithm has no networks
    config (GASv2): deploy/docker-compose.yml passes the task's group to every learner."""
    pre = _Peek(add_help=False)
    pre.add_argument("--preset", default=next(iter(PRESETS)))
    try:
        known, _ = pre.parse_known_args(list(argv))
    except ValueError:  # a malformed --preset: the command's own parser refuses it in one line
        return list(argv)
    algo = PRESETS[known.preset].algorithm if known.preset in PRESETS else None
    if algo is None or "net" in {f.name for f in dataclasses.fields(algo)}:
        return list(argv)
    out, args = [], list(argv)
    while args:
        arg = args.pop(0)
        if arg == "--net.group" and args:
            args.pop(0)
        elif not arg.startswith("--net.group="):
            out.append(arg)
    return out


def default_run_id(run_dir: Path) -> str:
    """A version lineage id for a fresh run: the run directory's name (made label-safe) and the start time."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "-", run_dir.resolve().name)[:60] or "run"
    return f"{stem}-{int(time.time())}"


def build_trainer(cfg: LearnerConfig, guard: AbstractContextManager[object] | None = None) -> Trainer:
    """The trainer ``cfg`` describes: networks from torch's generator seeded with ``cfg.seed``, batches
    and the replay's own generator from ``cfg.seed``."""
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    limiter = SampleToInsertRatio(cfg.samples_per_insert, cfg.min_steps, cfg.error_buffer)
    agent = cfg.algorithm.build(cfg.seed, prepare_device(cfg.device))
    replay = cfg.algorithm.replay(cfg.replay_capacity, cfg.seq_len, cfg.seed)
    return Trainer(cfg.algorithm, agent, replay, limiter, rng, cfg, guard)


__all__ = [
    "DEVICES",
    "GASV2_PRESETS",
    "PRESETS",
    "SAC_PRESETS",
    "LearnerConfig",
    "build_trainer",
    "check_device",
    "default_run_id",
    "learner_presets",
    "without_foreign_group",
    "preset_name",
    "prepare_device",
]
