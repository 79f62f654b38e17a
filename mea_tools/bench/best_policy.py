"""Each run's best evaluated weights, measured again on held-out seeds that did not select them.

The public Equi-RSAC code reports its best policies on 50 episodes (its Table 2); `mea bench
learning` reports each run's last weights at the budget. Picking the best of a run's evaluations on
the same seeds that scored them flatters it, so the chosen weights play fresh seeds, past the
evaluator's. The result is kept in the run directory (``CACHE``) and reused while the run's best
version, the episodes and the seeds stay the same.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from proto.seeds import EVAL_SEED_BASE
from services.evaluator.history import HISTORY, read_history

CACHE = "bench-best.json"
"""Inside a run directory: its best weights' version and their success on fresh seeds."""
FRESH_SEED_OFFSET = 1_000_000
"""Fresh seeds start this far past the evaluator's first held-out seed (its evaluations use far fewer)."""

Evaluate = Callable[[Path, int, int, int], float]
"""(run dir, weights version, first seed, episodes) -> success rate of the deterministic policy."""


def best_record(records: list[dict]) -> dict | None:
    """The evaluation with the highest success rate (the latest of equals), None without one."""
    scored = [r for r in records if isinstance(r.get("version"), int) and isinstance(r.get("env_steps"), int | float)
              and r["env_steps"] >= 0 and isinstance(r.get("success_rate"), int | float)]  # fmt: skip
    return max(scored, key=lambda r: (r["success_rate"], r["env_steps"]), default=None)


def measure(run_dir: Path, episodes: int, evaluate: Evaluate | None = None) -> dict[str, Any] | None:
    """The run's best evaluated weights on ``episodes`` fresh seeds (None: no evaluation yet)."""
    path = run_dir / HISTORY
    best = best_record(read_history(path) if path.exists() else [])
    if best is None:
        return None
    first_seed = EVAL_SEED_BASE + FRESH_SEED_OFFSET
    key = {"version": best["version"], "episodes": episodes, "first seed": first_seed}
    cache = run_dir / CACHE
    try:
        kept = json.loads(cache.read_text())
    except (OSError, ValueError):
        kept = None
    if (
        isinstance(kept, dict)
        and {k: kept.get(k) for k in key} == key
        and isinstance(kept.get("success"), float)
    ):
        return kept
    success = (evaluate or play_fresh_seeds)(run_dir, best["version"], first_seed, episodes)
    result = {
        **key,
        "env steps": best["env_steps"],
        "selected by": best["success_rate"],
        "success": float(success),
    }
    cache.write_text(json.dumps(result) + "\n")
    return result


def play_fresh_seeds(run_dir: Path, version: int, first_seed: int, episodes: int) -> float:
    """Version ``version`` of the run's weights (checked against its run's key where sealed), on the
    run's task and start, through the evaluator's ``EpisodeRunner``."""
    # deferred: torch and pybullet (seconds to import), only where a policy plays
    from mea_tools.bench.imitation import evaluate
    from services.algorithms.policy import blob_observation
    from services.learner import init_actor

    _, blob = init_actor.read(run_dir, version)
    saved = json.loads((run_dir / "config.json").read_text())
    result = evaluate(blob, saved["task"], blob_observation(blob) == "depth", episodes,
                      saved.get("gripper_start", "random"), seed_base=first_seed)  # fmt: skip
    return float(result["success"])
