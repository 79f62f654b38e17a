"""Statistics of `mea bench learning` over seeds, computed with rliable (Agarwal et al. 2021).

Pure: numpy arrays in, frozen dataclasses out, no files or processes. Per arm: mean and
interquartile mean (IQM) with 95% stratified-bootstrap confidence intervals; between two arms:
rliable's probability of improvement P(X > Y) with its CI, and whether the arms' CIs of the mean
overlap ("within noise"); learning curves as a pointwise bootstrap band; performance profiles.

One task, so every score array is (runs, 1) for rliable. rliable 1.2's stratified bootstrap draws
its indices from numpy's global RNG whatever ``random_state`` says, so each estimate seeds that RNG
from :attr:`Bootstrap.seed` and restores the caller's state afterwards: the same inputs and seed
give the same interval.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from rliable import library as rly
from rliable import metrics


@dataclass(frozen=True)
class Bootstrap:
    """How intervals are estimated."""

    reps: int = 10_000
    """Bootstrap resamples of the per-arm intervals (rliable's default is 50,000)."""
    confidence: float = 0.95
    seed: int = 0
    heavy_reps: int = 2_000
    """At most this many resamples where each resample is costly: the probability of improvement (a
    Mann-Whitney U test each), curve bands and performance profiles (rliable's own default for
    profiles, and its README's for the probability of improvement)."""

    def __post_init__(self) -> None:
        if min(self.reps, self.heavy_reps) < 1 or not 0.0 < self.confidence < 1.0:
            raise ValueError(
                f"reps and heavy_reps must be >= 1 and confidence in (0, 1), got {self.reps}, "
                f"{self.heavy_reps}, {self.confidence}"
            )

    @property
    def heavy(self) -> int:
        return min(self.reps, self.heavy_reps)


@dataclass(frozen=True)
class Interval:
    """A point estimate and its bootstrap confidence interval [lo, hi]."""

    point: float
    lo: float
    hi: float

    def overlaps(self, other: Interval) -> bool:
        return self.lo <= other.hi and other.lo <= self.hi


@dataclass(frozen=True)
class ArmSummary:
    """One arm's scores over seeds (e.g. success at the budget)."""

    runs: int
    mean: Interval
    iqm: Interval
    std: float
    """Population standard deviation over runs (what the benchmark printed before the intervals)."""


@dataclass(frozen=True)
class Comparison:
    """Arm X against arm Y."""

    probability_of_improvement: Interval
    """P(a run of X scores above a run of Y), ties counted half (Mann-Whitney U / (n_x n_y))."""
    within_noise: bool
    """The two arms' confidence intervals of the mean overlap."""


@dataclass(frozen=True)
class CurveBand:
    """Mean success over runs at each env-step point, with a pointwise bootstrap interval."""

    steps: np.ndarray
    mean: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    runs: int


@dataclass(frozen=True)
class Profile:
    """Performance profile: the fraction of runs scoring above each threshold tau, with its interval."""

    taus: np.ndarray
    fraction: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


@contextmanager
def _seeded(seed: int) -> Iterator[None]:
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def _runs(values: Sequence[float] | np.ndarray) -> np.ndarray:
    a = np.asarray(values, np.float64).reshape(-1, 1)
    if np.isnan(a).any():
        raise ValueError("scores must not contain NaN")
    return a


def iqm(values: Sequence[float] | np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50% (rliable's 25%-trimmed mean)."""
    return float(metrics.aggregate_iqm(_runs(values)))


def _estimates(scores, func, boot: Bootstrap, reps: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    with _seeded(boot.seed):
        points, cis = rly.get_interval_estimates(
            {"x": scores}, func, reps=reps or boot.reps, confidence_interval_size=boot.confidence
        )
    return np.asarray(points["x"], np.float64), np.asarray(cis["x"], np.float64)


def summarize_arm(values: Sequence[float] | np.ndarray, boot: Bootstrap) -> ArmSummary | None:
    """Mean and IQM of one arm's per-run scores with their intervals; None without runs."""
    a = _runs(values)
    if a.size == 0:
        return None
    points, cis = _estimates(
        a, lambda s: np.array([metrics.aggregate_mean(s), metrics.aggregate_iqm(s)]), boot
    )
    mean, iq = (Interval(float(points[i]), float(cis[0, i]), float(cis[1, i])) for i in range(2))
    return ArmSummary(runs=int(a.shape[0]), mean=mean, iqm=iq, std=float(a.std()))


def _mean_of(a: np.ndarray, boot: Bootstrap) -> Interval:
    points, cis = _estimates(a, lambda s: np.array([metrics.aggregate_mean(s)]), boot)
    return Interval(float(points[0]), float(cis[0, 0]), float(cis[1, 0]))


def mean_interval(values: Sequence[float] | np.ndarray, boot: Bootstrap) -> Interval | None:
    """The mean over runs with its interval; None without runs."""
    a = _runs(values)
    return None if a.size == 0 else _mean_of(a, boot)


def within_noise(a: Interval, b: Interval) -> bool:
    """Two arms are within noise of each other when their confidence intervals overlap."""
    return a.overlaps(b)


def compare(
    x: Sequence[float] | np.ndarray, y: Sequence[float] | np.ndarray, boot: Bootstrap
) -> Comparison | None:
    """X against Y: probability of improvement (runs of each resampled independently) and whether
    their intervals of the mean overlap (the same intervals as :func:`summarize_arm`'s); None if
    either has no runs."""
    ax, ay = _runs(x), _runs(y)
    if ax.size == 0 or ay.size == 0:
        return None
    with _seeded(boot.seed):
        points, cis = rly.get_interval_estimates(
            {"x": [ax, ay]},
            lambda a, b: np.array([metrics.probability_of_improvement(a, b)]),
            reps=boot.heavy,
            confidence_interval_size=boot.confidence,
        )
    p, ci = np.asarray(points["x"], np.float64), np.asarray(cis["x"], np.float64)
    noise = within_noise(*(_mean_of(a, boot) for a in (ax, ay)))
    return Comparison(Interval(float(p[0]), float(ci[0, 0]), float(ci[1, 0])), noise)


def curve_band(steps: np.ndarray, values: np.ndarray, boot: Bootstrap) -> CurveBand:
    """Pointwise mean and interval of (runs, points) curves on a common grid ``steps``.

    Only points every run covers are kept (a run that stopped early would otherwise make the mean
    jump where it drops out)."""
    v = np.atleast_2d(np.asarray(values, np.float64))
    s = np.asarray(steps, np.float64)
    if v.shape[1] != s.size:
        raise ValueError(f"{s.size} steps for curves of {v.shape[1]} points")
    keep = ~np.isnan(v).any(axis=0)
    s, v = s[keep], v[:, keep]
    if v.shape[1] == 0 or v.shape[0] == 0:
        empty = np.zeros(0)
        return CurveBand(empty, empty, empty, empty, int(v.shape[0]))
    points, cis = _estimates(v, lambda a: a.mean(axis=0), boot, boot.heavy)  # each point over runs
    return CurveBand(s, points, cis[0], cis[1], int(v.shape[0]))


def performance_profiles(
    scores: Mapping[str, Sequence[float] | np.ndarray], taus: np.ndarray, boot: Bootstrap
) -> dict[str, Profile]:
    """rliable's score-distribution profile per arm (fraction of runs with score > tau); arms without
    runs are left out."""
    t = np.asarray(taus, np.float64)
    arms = {k: _runs(v) for k, v in scores.items() if len(v)}
    if not arms:
        return {}
    with _seeded(boot.seed):
        profiles, cis = rly.create_performance_profile(
            arms, t, reps=boot.heavy, confidence_interval_size=boot.confidence
        )
    return {
        k: Profile(t, np.asarray(profiles[k], np.float64), np.asarray(cis[k][0]), np.asarray(cis[k][1]))
        for k in arms
    }


__all__ = [
    "ArmSummary",
    "Bootstrap",
    "Comparison",
    "CurveBand",
    "Interval",
    "Profile",
    "compare",
    "curve_band",
    "iqm",
    "mean_interval",
    "performance_profiles",
    "summarize_arm",
    "within_noise",
]
