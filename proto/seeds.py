"""Seed layout of a run: which seeds train, which evaluate, and how augmentation draws its copies.

Every stream below is disjoint from the others, so no training episode ever shares a seed with an
evaluation episode, no resume repeats a seed, and any augmented copy can be regenerated from its
provenance (``Augmentation.seed`` and ``copy_index``).
"""

from __future__ import annotations

EVAL_SEED_BASE = 1_000_000_000
"""First held-out evaluation seed; training seeds stay below it."""
RUN_SEED_STRIDE = 10**8
"""Actors' training seeds of run seed s start at s * RUN_SEED_STRIDE (+ the resume offset)."""
RESUME_SEED_STRIDE = 10**5
"""Each resume moves the actors' seed streams on by this much."""
RESTART_SEED_STRIDE = 10**4
"""Each restart of an actor within a run moves its seed stream on by this much (a run's actor takes
far fewer than 1e4 episodes between restarts; up to 9 restarts per resume stay apart from the next
resume's stream)."""
ACTOR_SEED_STRIDE = 1_000_000
"""Actor i's episode seeds start at its seed base + i * ACTOR_SEED_STRIDE."""
SHARED_ROTATION_STREAM = 1_000_000
"""``default_rng([seed, SHARED_ROTATION_STREAM])`` draws the rotation all MEA copies of an episode
share; isometric copy k's angle comes from ``[seed, k]`` (k < SHARED_ROTATION_STREAM)."""
MEA_COPY_SEED_OFFSET = SHARED_ROTATION_STREAM + 1
"""MEA copy k of a source episode draws from ``default_rng([seed, MEA_COPY_SEED_OFFSET + k])``."""


def actor_seed_base(run_seed: int, resumes: int) -> int:
    """First training seed of a run's actors after ``resumes`` resumes."""
    return run_seed * RUN_SEED_STRIDE + resumes * RESUME_SEED_STRIDE
