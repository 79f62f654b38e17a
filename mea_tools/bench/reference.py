"""The public Equi-RSAC speed anchor on a 2-core CPU machine, and the targets this project must beat.

Figures from the project's platform notes (public Equi-RSAC code, Block Pulling, torch CPU, 2 threads):
11.1 s per gradient update (batch 32 episodes x 50 steps), about 10.3 env steps/s with the scripted
expert, and about 10.5 GB reserved for 1e5 transitions of replay.
Every benchmark prints these rows, filled in where it measures the quantity.
"""

from __future__ import annotations

from dataclasses import dataclass

PUBLIC_UPDATE_SECONDS = 11.1
PUBLIC_UPDATE_SECONDS_BY_THREADS = {1: 15.4, 2: PUBLIC_UPDATE_SECONDS}
"""The public code's update by torch thread count (its training entry point forces 1 thread)."""
PUBLIC_ENV_STEPS_PER_SECOND = 10.3
PUBLIC_REPLAY_BYTES_PER_1E5 = 10.5e9


@dataclass(frozen=True)
class Target:
    key: str
    label: str
    reference: float
    unit: str
    required_ratio: float
    higher_is_better: bool


TARGETS = (
    Target("update_seconds", "gradient update (paper preset)", PUBLIC_UPDATE_SECONDS, "s", 3.0, False),
    Target(
        "env_steps_per_second", "env steps per process", PUBLIC_ENV_STEPS_PER_SECOND, "steps/s", 2.5, True
    ),
    Target(
        "replay_bytes_per_1e5", "replay for 1e5 transitions", PUBLIC_REPLAY_BYTES_PER_1E5, "B", 10.0, False
    ),
)


def ratios(measured: dict[str, float | None]) -> list[dict]:
    """One row per target: measured value (or None when this benchmark does not measure it),
    speed-up ratio against the public code, the required ratio, and whether it is met."""
    rows = []
    for t in TARGETS:
        value = measured.get(t.key)
        ratio = None
        if value is not None and value > 0:
            ratio = value / t.reference if t.higher_is_better else t.reference / value
        rows.append(
            {
                "target": t.key,
                "label": t.label,
                "public": t.reference,
                "unit": t.unit,
                "measured": value,
                "ratio": ratio,
                "required_ratio": t.required_ratio,
                "met": None if ratio is None else ratio >= t.required_ratio,
            }
        )
    return rows
