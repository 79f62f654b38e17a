"""The learner's settings: `LearnerConfig`, its presets, the run id a fresh run gets, and the
trainer a config describes (``build_trainer``).

No transport, so that the benchmarks, the tests and the shell (``services.learner.main``) share one
definition.
"""

from __future__ import annotations

import dataclasses
import re
import time
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from services.common.config import ServiceConfig
from services.learner.core.gasv2.agent import GasV2Agent
from services.learner.core.gasv2.chunk_replay import ChunkReplay
from services.learner.core.gasv2.config import PRESETS as DREAMER_PRESETS
from services.learner.core.gasv2.config import DreamerConfig
from services.learner.core.gasv2.trainer import GasV2Trainer
from services.learner.core.networks import PRESETS as NET_PRESETS
from services.learner.core.networks import NetConfig, build_actor, build_critic
from services.learner.core.policy import OBSERVATIONS
from services.learner.core.privileged import STATE_DIM
from services.learner.core.rate_limiter import SampleToInsertRatio
from services.learner.core.replay import SequenceReplay
from services.learner.core.sac import RecurrentSAC, SacSettings
from services.learner.core.trainer import Trainer, TrainerSettings

ALGORITHMS = ("equi_rsac", "rsac", "gasv2")
DEVICES = re.compile(r"cpu|cuda(:\d+)?")
"""Learner devices: the CPU or a CUDA GPU (``cuda`` is the current one, ``cuda:N`` the N-th)."""


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
    """Train recurrent SAC from replayed episodes and broadcast the actor's weights."""

    algorithm: str = "equi_rsac"
    """equi_rsac (C4/D4-equivariant, `--net.group c4|d4`), rsac (the non-equivariant twin, same widths)
    or gasv2 (DreamerV2 world model + imagination actor; Surgical Grasp Any; `--preset gasv2...`)."""
    net: NetConfig = field(default_factory=lambda: NET_PRESETS["paper"])
    """Network widths and symmetry group (SAC)."""
    sac: SacSettings = SacSettings()
    """SAC hyperparameters."""
    dreamer: DreamerConfig = field(default_factory=lambda: DREAMER_PRESETS["paper"])
    """GASv2's world model, actor and critic (gasv2 only)."""
    chunk_length: int = 6
    """gasv2: observations per training window (GASv2: batch 100 x length 6)."""
    observation: str = "voxel"
    """What the policy sees: voxel (orthographic projection; EquiObs/MEA), depth (rendered; Equi-RSAC)
    or dsa (the surgical task's DSA image; gasv2)."""
    replay_capacity: int = 100_000
    """Replay capacity in transitions (raw and augmented copies alike; demonstrations are never evicted)."""
    batch_size: int = 32
    """Whole episodes per update (SAC); windows of chunk_length per update (gasv2)."""
    demo_fraction: float = 0.0
    """Share of every batch drawn from the demonstration set (demos and all their augmented copies),
    the rest from the other episodes (RLPD / SERL symmetric sampling); 0 samples uniformly (the paper)."""
    successes_as_demos: bool = False
    """Episodes that succeeded (``Episode.succeeded``: online successes and their copies) join the demonstration set
    for demo_fraction and the BC term: self-imitation of what already worked (off: demos only)."""
    trim_batches: bool = True
    """Pad each batch to its longest episode instead of seq_len (same losses, less work)."""
    seq_len: int = 50
    """Episodes are padded to this many steps (the task's time limit)."""
    samples_per_insert: float = 1.0
    """Updates per raw env step (Equi-RSAC: one update per env step)."""
    min_steps: int = 100
    """Raw env steps in replay before the first update."""
    error_buffer: float = 200.0
    """Slack (in updates) around samples_per_insert x env steps before either side waits."""
    publish_every: int = 10
    """Announce new weights every this many updates."""
    checkpoint_minutes: float = 10.0
    """Checkpoint period (and always on shutdown); 0 disables periodic checkpoints."""
    checkpoint_every: int = 0
    """Also checkpoint every this many updates (0: off)."""
    keep_checkpoints: int = 3
    """Checkpoints kept (the newest; at least 1): --resume falls back to an older one if the newest
    is unreadable. Each holds the replay's contents (hundreds of MB with the paper preset)."""
    checkpoint_max_bytes: int = 0
    """Also delete the oldest checkpoints while they take more than this many bytes in all; the
    newest always stays (0: no budget, keep_checkpoints alone)."""
    run_dir: Path = Path("runs/learner")
    """Directory for the resolved config and checkpoints/."""
    run_id: str = ""
    """Version lineage id; empty derives one from run_dir and the start time (kept on --resume)."""
    resume: bool = False
    """Continue from run_dir/checkpoints if there is a checkpoint there."""
    init_actor: Path | None = None
    """Start the actor from this weights file (or the newest in this run dir / weights folder: a clone
    from `mea bench imitation`, or weights a learner wrote) when there is no checkpoint to continue;
    with a shared encoder the critic's encoder too (``services.learner.init_actor``)."""
    max_updates: int = 0
    """Stop after this many updates (0: until stopped)."""
    max_env_steps: int = 0
    """Env-step budget of the run: the replay gate never allows more (actors stop there); 0: none."""
    tensorboard_dir: Path | None = None
    """Write the training scalars (means over tensorboard_every updates, against env steps) here as
    TensorBoard events; None: off (`mea run` sets RUN_DIR/tb)."""
    tensorboard_every: int = 50
    """Updates per TensorBoard point."""
    threads: int = 0
    """torch intra-op threads (0: torch's default)."""
    device: str = "cpu"
    """torch device of the networks, optimisers and batches: cpu, cuda or cuda:N (a GPU workstation).
    The replay stays in host memory; published weights and checkpoints are on the CPU, so a run
    resumes on another device. On CUDA: TF32 matmuls, and the update metrics are read from the
    device every tensorboard_every updates (means), not after each update."""
    seed: int = 0
    """Seed of networks, sampling and exploration noise."""
    queue: int = 64
    """Incoming episodes buffered between Zenoh and the ingest thread."""
    gate_seconds: float = 0.5
    """Period of the replay gate."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""

    def __post_init__(self) -> None:
        if self.algorithm not in ALGORITHMS:
            raise ValueError(f"algorithm must be one of {ALGORITHMS}, not {self.algorithm!r}")
        if self.algorithm == "rsac" and self.net.group != "none":  # the twin: same widths, plain layers
            object.__setattr__(self, "net", dataclasses.replace(self.net, group="none"))
        if self.algorithm == "gasv2" and self.observation != "dsa":
            raise ValueError("--algorithm gasv2 starts from a gasv2 preset (--preset gasv2, gasv2-cpu-small or "
                             "gasv2-smoke): it observes dsa, the surgical DSA image, in windows of its own")  # fmt: skip
        if self.observation == "dsa" and self.algorithm != "gasv2":
            raise ValueError("observation dsa (the surgical DSA image) is the gasv2 learner's only")
        if self.algorithm == "equi_rsac" and self.net.group == "none":
            raise ValueError("equi_rsac needs --net.group c4 or d4 (the plain twin is --algorithm rsac)")
        if self.observation not in OBSERVATIONS:
            raise ValueError(f"observation must be one of {OBSERVATIONS}, not {self.observation!r}")
        for name in ("batch_size", "seq_len", "publish_every", "queue", "chunk_length"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
        if self.keep_checkpoints < 1 or self.checkpoint_max_bytes < 0:
            raise ValueError("keep_checkpoints must be >= 1 and checkpoint_max_bytes >= 0")
        if self.replay_capacity < self.seq_len:
            raise ValueError("replay_capacity must hold at least one episode (>= seq_len)")
        if not 0.0 <= self.demo_fraction <= 1.0:
            raise ValueError(f"demo_fraction must be in [0, 1], got {self.demo_fraction}")
        if self.net.critic_input == "state" and self.sac.share_encoder:
            raise ValueError("sac.share_encoder needs the image critic (net.critic_input image)")
        check_device(self.device, "--device")
        if self.samples_per_insert <= 0 or self.min_steps < 0 or self.error_buffer < 0:
            raise ValueError("samples_per_insert must be > 0, min_steps and error_buffer >= 0")

    def trainer_settings(self) -> TrainerSettings:
        return TrainerSettings(
            batch_size=self.batch_size,
            trim_batches=self.trim_batches,
            publish_every=self.publish_every,
            demo_fraction=self.demo_fraction,
            successes_as_demos=self.successes_as_demos,
            max_env_steps=self.max_env_steps,
            max_updates=self.max_updates,
            metrics_every=1 if self.device == "cpu" else max(1, self.tensorboard_every),
        )


PRESETS = {
    "paper": LearnerConfig(),
    # cpu-small: the recipe for two CPU cores and a 20K env-step budget (README, "Presets"). Cuts:
    # halved network widths, 8 episodes per batch instead of 32, 0.5 updates per env step instead of
    # 1 (the replay gate lets actors run 2 steps per update). Additions, each a field: half of every
    # batch from the demonstration set (demos, their copies, online successes), a BC term, alpha from
    # 0.01, LayerNorm in the Q MLPs, one encoder shared by actor and critic, critic targets bounded
    # below by the observed return; replay 200k holds a whole 20K-step run with its copies.
    "cpu-small": LearnerConfig(
        net=dataclasses.replace(NET_PRESETS["cpu-small"], critic_layer_norm=True, actor_prev_action=False),
        sac=SacSettings(init_alpha=0.01, bc_weight=2.0, share_encoder=True, return_bound=True),
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
        net=NET_PRESETS["cpu-small"],
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
# (Block Pull at 20K: 0.48 and 0.28 for seeds 0 and 1, against 0.28 with 0.5 for seed 0; README).
PRESETS["cpu-small-state"] = dataclasses.replace(
    PRESETS["cpu-small"],
    net=dataclasses.replace(PRESETS["cpu-small"].net, critic_input="state", critic_layer_norm=False),
    sac=dataclasses.replace(PRESETS["cpu-small"].sac, share_encoder=False),
    samples_per_insert=1.0,
)


# GASv2 on Surgical Grasp Any (the reference's training settings, tasks-and-baselines.md section 5):
# windows of 6 observations, 100 per update, one update per 2 env steps (`train_every` 2), replay
# 5e5 transitions, episodes of at most 80 steps; demos and their MEA copies are pinned in replay.
# The reference's 9e3 random prefill steps are the actors' (`mea run --random-steps`); training
# starts once min_steps env steps are in.
PRESETS["gasv2"] = LearnerConfig(
    algorithm="gasv2",
    observation="dsa",
    dreamer=DREAMER_PRESETS["paper"],
    batch_size=100,
    chunk_length=6,
    seq_len=80,
    replay_capacity=500_000,
    samples_per_insert=0.5,
    min_steps=10_000,
    error_buffer=200.0,
    publish_every=10,
)
# gasv2-cpu-small: two CPU cores (16K env steps in about 40 minutes; README, "The learner (GASv2)"): the world model's
# cpu-small widths (gasv2/config.py), 16 windows per update instead of 100, training from 500 env
# steps, and the demo-aware sampling of the cpu-small SAC recipe (half of every batch from the demos,
# their copies and online successes); everything else as gasv2.
PRESETS["gasv2-cpu-small"] = dataclasses.replace(
    PRESETS["gasv2"],
    dreamer=DREAMER_PRESETS["cpu-small"],
    batch_size=16,
    replay_capacity=200_000,
    min_steps=500,
    error_buffer=100.0,
    demo_fraction=0.5,
    successes_as_demos=True,
    publish_every=5,
    checkpoint_minutes=5.0,
)
# gasv2-smoke: tiny networks and batches for end-to-end tests of the stack; learns nothing.
PRESETS["gasv2-smoke"] = dataclasses.replace(
    PRESETS["gasv2"],
    dreamer=DREAMER_PRESETS["smoke"],
    batch_size=2,
    replay_capacity=20_000,
    min_steps=50,
    error_buffer=50.0,
    publish_every=2,
    checkpoint_minutes=1.0,
)


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
    if cfg.algorithm == "gasv2":
        replay = ChunkReplay(cfg.replay_capacity, seq_len=cfg.seq_len, seed=cfg.seed)
        agent = GasV2Agent(cfg.dreamer, seed=cfg.seed, device=prepare_device(cfg.device))
        return GasV2Trainer(agent, replay, limiter, rng, cfg.trainer_settings(), cfg.chunk_length, guard)
    sac = RecurrentSAC(build_actor(cfg.net), build_critic(cfg.net), cfg.sac, prepare_device(cfg.device))
    replay = SequenceReplay(
        cfg.replay_capacity,
        image_size=cfg.net.image_size,
        seq_len=cfg.seq_len,
        channels=cfg.net.in_channels,
        seed=cfg.seed,
        state_dim=STATE_DIM if cfg.net.critic_input == "state" else 0,
    )
    return Trainer(sac, replay, limiter, rng, cfg.trainer_settings(), guard)


__all__ = [
    "ALGORITHMS",
    "DEVICES",
    "PRESETS",
    "LearnerConfig",
    "build_trainer",
    "check_device",
    "default_run_id",
    "prepare_device",
]
