"""`mea run`'s experiment tracking: the resolved settings into RUN_DIR/tb (TensorBoard's hparams
records and a Markdown table), and with ``--track`` the run's TensorBoard directories into Weights &
Biases.

W&B gets nothing of its own: wandb learns a TensorBoard directory when a ``SummaryWriter`` opens one
in a process where ``wandb.tensorboard.patch`` is on, and then reads the event files there as they
grow. The launcher opens an empty writer in RUN_DIR/tb and in each service's RUN_DIR/tb/<instance>
(the services, in this process or others, write their own files there), each patched with its own
directory as the root, so the W&B keys are TensorBoard's tags, unprefixed (``global_step``: the env
steps). The W&B run id is kept in RUN_DIR/wandb-run-id, so a resumed run continues the same W&B run
(offline runs too: `wandb sync` uploads each sitting into it).
"""

from __future__ import annotations

import importlib.util
import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from services.common import config
from services.common.scalars import ScalarLog
from services.run_config import RunConfig

log = logging.getLogger(__name__)

RUN_ID_FILE = "wandb-run-id"
METRICS = (("evaluator-0", "eval/success_rate"), ("evaluator-0", "eval/return"),
           ("actor-0", "charts/episodic_return"), ("actor-0", "charts/success"))  # fmt: skip
"""The (run, tag) scalars the hparams view puts beside the settings."""


def check(cfg: RunConfig) -> None:
    """ValueError naming --track unless W&B tracking can start (the wandb package is installed)."""
    if cfg.track and importlib.util.find_spec("wandb") is None:
        raise ValueError("--track needs the wandb package: pip install 'mea-rl[track]'")


def settings(cfg: RunConfig) -> dict[str, Any]:
    """The run's settings as flat name -> value (nested values as JSON-like text)."""
    return {
        k: v if isinstance(v, (bool, int, float, str)) else str(v) for k, v in config.to_jsonable(cfg).items()
    }


def table(cfg: RunConfig) -> str:
    """The run's settings as a Markdown table (TensorBoard's text plugin renders it)."""
    rows = [f"| {k} | `{str(v).replace('|', '/')}` |" for k, v in settings(cfg).items()]
    return "\n".join(["| setting | value |", "| --- | --- |", *rows])


class Tracking:
    """Opened when the run starts (after RUN_DIR exists, before any service), closed after they stop;
    ``instances``: the run's service instances (each writes into RUN_DIR/tb/<instance>)."""

    def __init__(self, cfg: RunConfig, run_dir: Path, instances: Sequence[str] = ()) -> None:
        self.tb = run_dir / "tb"
        self.wandb: Any = None
        if cfg.track:
            self.wandb = _start_wandb(cfg, run_dir)
            if self.wandb is not None:
                _follow(self.tb, instances)
        self.scalars = ScalarLog(self.tb, 1, "")  # the settings: in the run's root directory
        self.scalars.add_hparams(settings(cfg), METRICS)
        self.scalars.add_text("config/run", table(cfg), cfg.resumes)

    def close(self) -> None:
        self.scalars.close()
        if self.wandb is not None:
            self.wandb.finish()


def _follow(tb: Path, instances: Sequence[str]) -> None:
    """Point the W&B run at RUN_DIR/tb and at each instance's directory in it, each its own root (so
    no key gets a directory's name as a prefix): an empty writer opened there with the patch on.
    wandb reads a directory's files in name order and leaves a file once a later one exists, so the
    services' files (named by the second they open) must come after these: wait into the next second."""
    import wandb  # deferred: wandb is an optional extra (mea-rl[track]), needed only with --track
    from torch.utils.tensorboard import SummaryWriter  # deferred: a slow import, needed only with --track

    for d in (tb, *(tb / i for i in instances)):
        d.mkdir(parents=True, exist_ok=True)
        wandb.tensorboard.patch(root_logdir=str(d))
        try:
            SummaryWriter(str(d), filename_suffix=".wandb").close()
        finally:
            wandb.tensorboard.unpatch()  # a service's writer in this process must not add it again
    time.sleep(1.01 - time.time() % 1.0)


def _start_wandb(cfg: RunConfig, run_dir: Path) -> Any:
    """A W&B run (the id in RUN_DIR/wandb-run-id, kept from the first sitting); None, logged, if W&B
    cannot start (no login for online mode): training goes on with TensorBoard."""
    import wandb  # deferred: wandb is an optional extra (mea-rl[track]), needed only with --track

    id_file = run_dir / RUN_ID_FILE
    run_id = id_file.read_text().strip() if id_file.is_file() else None  # None: W&B makes one
    if wandb.patched["tensorboard"]:  # patched by someone else in this process: leave it to them
        log.warning("W&B tracking not started: tensorboard is patched for W&B already")
        return None
    try:
        run = wandb.init(id=run_id, resume="allow", mode=cfg.wandb_mode, name=run_dir.name,
                         project=os.environ.get("WANDB_PROJECT", "mea"), config=settings(cfg),
                         dir=os.environ.get("WANDB_DIR") or str(run_dir),
                         settings=wandb.Settings(console="off", silent=True))  # fmt: skip
    except Exception as exc:  # noqa: BLE001 - W&B is an extra: the run goes on without it
        log.warning("W&B tracking not started", extra={"error": str(exc)[:300]})
        return None
    id_file.write_text(run.id + "\n")
    log.info("tracking with W&B", extra={"mode": cfg.wandb_mode, "run_id": run.id, "dir": str(run.dir)})
    return run


__all__ = ["RUN_ID_FILE", "Tracking", "check", "settings", "table"]
