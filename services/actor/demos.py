"""`mea demos`: record scripted demonstrations of a task to an MCAP file.

Styles alternate (probe: touch the fixed object first; direct: go to the movable one), and only
successful episodes are kept, as in Equi-RSAC. The default expert decides from what it observes, so
a style is given by the layout: seeds are skipped until the nearest object is the fixed one (probe)
or the movable one (direct); docs/tasks.md. ``surgical_grasp_any`` has one style, its discrete
oracle (direct). The file has one channel per message type with its JSON Schema embedded, plus the
resolved config and the seeds as metadata.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from services.actor.config import ActorConfig, check_expert
from services.actor.rollout import RolloutActor
from services.common import config, logs
from services.common.mcap_io import McapRecorder
from services.tasks import EXPERT_STYLES, TASK_CLASSES

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class DemosConfig:
    """Record scripted demonstrations to MCAP."""

    task: str = "block_pull"
    """Task: block_pull, block_pick, drawer_open or surgical_grasp_any."""
    n: int = 2
    """Successful demonstrations to record."""
    out: Path = Path("demos.mcap")
    """Output file (written to OUT.tmp, renamed when complete)."""
    style: str = "alternate"
    """alternate, probe or direct (surgical_grasp_any has only direct: its oracle)."""
    expert: str = "observable"
    """Scripted expert: observable or privileged."""
    seed_base: int = 0
    """First seed."""
    max_attempts: int = 0
    """Give up after this many expert attempts (0: 4 per requested demo)."""
    depth_image: bool = False
    """Also record the baseline depth image."""
    overwrite: bool = False
    """Replace an existing output file."""

    def __post_init__(self) -> None:
        if self.task not in TASK_CLASSES:
            raise ValueError(f"--task must be one of {', '.join(sorted(TASK_CLASSES))}, not {self.task!r}")
        if self.style not in ("alternate", *EXPERT_STYLES):
            raise ValueError(f"--style must be alternate, probe or direct, not {self.style!r}")
        check_expert(self.expert)
        if self.n < 1:
            raise ValueError(f"--n must be >= 1 (demonstrations to record), not {self.n}")
        if self.seed_base < 0:
            raise ValueError(f"--seed-base must be >= 0, not {self.seed_base}")
        if self.max_attempts < 0:
            raise ValueError(f"--max-attempts must be >= 0 (0: 4 per demonstration), not {self.max_attempts}")
        if Path(self.out).parent.exists() and not Path(self.out).parent.is_dir():
            raise ValueError(f"--out: {str(Path(self.out).parent)!r} is a file, not a directory")
        if not Path(self.out).parent.is_dir():
            raise ValueError(f"--out: the directory {str(Path(self.out).parent)!r} does not exist")
        if Path(self.out).exists() and not self.overwrite:
            raise ValueError(f"--out: {str(self.out)!r} exists; pass --overwrite to replace it")


PRESETS = {"default": DemosConfig()}
CONFIG_NAME = "demos"
"""The resolved config is stored as metadata ``config/demos``."""
SEEDS_METADATA = "seeds"
"""Name of the metadata record listing the kept demonstrations' seeds."""


def run_metadata(cfg: DemosConfig) -> dict[str, str]:
    """The ``run`` metadata record of a demonstrations file (proto/README.md, section 5)."""
    return {"task": cfg.task, "kind": "demonstrations", "style": cfg.style}


def seeds_metadata(seeds: list[int], attempts: int) -> dict[str, str]:
    """The ``seeds`` metadata record: the kept seeds (comma-separated) and the expert attempts made."""
    return {"seeds": ",".join(map(str, seeds)), "attempts": str(attempts)}


def record(cfg: DemosConfig) -> dict:
    actor_cfg = ActorConfig(task=cfg.task, policy="expert", expert_style=cfg.style, expert=cfg.expert,
                            seed_base=cfg.seed_base, depth_image=cfg.depth_image)  # fmt: skip
    actor = RolloutActor(actor_cfg, "demos")
    attempts_cap = cfg.max_attempts or 4 * cfg.n
    kept, attempts, seeds = 0, 0, []
    with McapRecorder(cfg.out, metadata=run_metadata(cfg), overwrite=cfg.overwrite) as rec:
        rec.write_config(CONFIG_NAME, json.dumps(config.to_jsonable(cfg)))
        for b in actor.demonstrations(cfg.n, attempts_cap):
            attempts += 1
            if not b.success:
                log.info(
                    "expert failed; not kept", extra={"seed": b.meta["seed"], "kind": b.meta["policy_kind"]}
                )
                continue
            rec.write(b.finish(actor.episode_id(b)))
            seeds.append(b.meta["seed"])
            kept += 1
        rec.add_metadata(SEEDS_METADATA, seeds_metadata(seeds, attempts))
    actor.env.close()
    return {"kept": kept, "attempts": attempts, "out": str(cfg.out), "seeds": seeds}


def main(argv: Sequence[str]) -> int:
    cfg = config.parse(DemosConfig, PRESETS, argv, "mea demos", DemosConfig.__doc__ or "")
    logs.setup("demos", "demos", "text", "INFO")
    result = record(cfg)
    print(json.dumps(result))
    if result["kept"] < cfg.n:
        print(f"mea demos: only {result['kept']} of {cfg.n} demonstrations succeeded", file=sys.stderr)
        return 1
    return 0
