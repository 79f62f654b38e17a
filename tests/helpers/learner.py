"""Tiny learner settings and episodes with policy images, shared by learner tests (and spawned children)."""

from __future__ import annotations

import dataclasses
import threading
from contextlib import AbstractContextManager
from pathlib import Path

import numpy as np

from proto.episode import Augmentation, Episode
from services.algorithms.networks import NetConfig
from services.algorithms.sac.algorithm import SacConfig
from services.algorithms.sac.config import SacSettings
from services.algorithms.trainer import Trainer
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig
from services.learner.config import LearnerConfig, build_trainer
from tests.helpers import build_episode

SIZE = 12
TINY_NET = NetConfig(
    group="c4",
    image_size=SIZE,
    encoder=((2, 3, 3),),
    final_kernel=4,
    image_embed=8,
    action_embed=4,
    q_action_embed=4,
    lstm_hidden=8,
    mlp_hidden=(16,),
)


def policy_images(rng: np.random.Generator, T: int, size: int = SIZE) -> np.ndarray:
    """(T+1, 2, size, size) uint8: random depth codes, a jaw code constant over each image."""
    images = rng.integers(0, 256, (T + 1, 2, size, size), dtype=np.uint8)
    images[:, 1] = rng.integers(0, 256, (T + 1, 1, 1), dtype=np.uint8)
    return images


def learner_episode(
    seed: int, T: int = 10, *, actor_id: str = "actor-0", demo: bool = False, copy_of: str | None = None
) -> Episode:
    """A raw episode (or, with ``copy_of``, an isometric copy of that episode id) with policy images."""
    rng = np.random.default_rng(seed)
    ep = build_episode(T=T, seed=seed, actor_id=actor_id)
    ep = dataclasses.replace(
        ep,
        images=policy_images(rng, T),
        is_demo=demo,
        policy_kind="expert_direct" if demo else "random",
        rewards=(rng.random(T) < 0.2).astype(np.float32),
    )
    if copy_of is not None:
        aug = Augmentation(
            source_episode_id=copy_of,
            kind="isometric",
            seed=seed,
            copy_index=0,
            phase_split=0,
            params={"rotation": np.array([0.5])},
        )
        ep = dataclasses.replace(ep, episode_id=f"{copy_of}.iso{seed}", augmentation=aug)
    return ep


def tiny_learner_config(
    run_dir: Path, service: ServiceConfig, *, net: NetConfig = TINY_NET, sac: SacSettings | None = None, **kw
) -> LearnerConfig:
    """A recurrent SAC learner of ``net`` with ``sac`` settings; ``kw`` overrides its other fields."""
    defaults = dict(
        algorithm=SacConfig(net=net, sac=sac or SacSettings()),
        batch_size=4,
        seq_len=20,
        replay_capacity=2_000,
        samples_per_insert=1.0,
        min_steps=20,
        error_buffer=30.0,
        publish_every=2,
        checkpoint_minutes=0.0,
        run_dir=run_dir,
        threads=1,
        gate_seconds=0.1,
        service=service,
    )
    defaults.update(kw)
    return LearnerConfig(**defaults)


def tiny_trainer(*, guard: AbstractContextManager[object] | None = None, **kw) -> Trainer:
    """The trainer of ``tiny_learner_config`` (``kw`` overrides its fields), built as the service builds
    its own."""
    return build_trainer(tiny_learner_config(Path("unused"), ServiceConfig(), **kw), guard)


def learner_child(endpoint: str, run_dir: str, resume: bool, instance: str) -> None:
    """Child entry (spawned): a tiny learner over Zenoh (client of the router at ``endpoint``)."""
    import sys

    from services.common.runtime import die_with_parent
    from services.learner.main import run
    from tests.helpers.zenoh_peer import peer_config

    die_with_parent()
    service = ServiceConfig(instance_id=instance, zenoh=peer_config(endpoint, "client"), metrics_port=0,
                            log_format="text", heartbeat_seconds=0.2)  # fmt: skip
    cfg = tiny_learner_config(Path(run_dir), service, resume=resume, checkpoint_every=5, error_buffer=40.0)
    sys.exit(run(cfg))


def start_learner(
    cfg: LearnerConfig, hub: Hub, observer: InProcBus, timeout: float = 60.0
) -> tuple[threading.Thread, dict]:
    """Run the learner service on ``hub`` in a thread; return once ``observer`` sees it alive. The
    thread's exit code lands in the dict under "rc"."""
    from services.learner.main import run

    watch = observer.watch_alive("learner")
    result: dict = {}
    thread = threading.Thread(
        target=lambda: result.setdefault("rc", run(cfg, bus_factory=lambda _c: InProcBus(hub))), daemon=True
    )
    thread.start()
    instance = cfg.service.instance_id
    assert watch.wait_for(lambda alive: ("learner", instance) in alive, timeout=timeout)
    return thread, result
