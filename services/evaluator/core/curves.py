"""Learning curves across seeds (numpy and stdlib only): the improvement timestep, the area under
the success curve, and curves put on a common env-step grid. Pure, so that the evaluator service and
``mea plot`` (and their tests) use exactly the same definitions; the history file they read is
``services.evaluator.history``, the scores of one episode and one evaluation ``services.episodes.scores``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

INTERPOLATIONS = ("hold", "linear")

# --------------------------------------------------------------------------------------------
# improvement timestep and area under the success curve
# --------------------------------------------------------------------------------------------

# Improvement timestep (MEA paper, EquiObs ablation):
# "the first step after which the mean success stays > 0". Defined here exactly as: order a run's
# evaluations by ``env_steps``; the improvement timestep is the ``env_steps`` of the earliest
# evaluation from which *every* evaluation up to the end of the run has ``success_rate > 0``.
# It is ``None`` when the last evaluation has success 0 (including "never > 0") or there are no
# evaluations. A single evaluation with success > 0 gives its own ``env_steps``. Applied to a
# mean-over-seeds curve it is the paper's definition; :func:`improvement_timestep` takes any
# (steps, values) pair.
#
# Area under the success curve (AUC):
# :func:`success_auc`: the trapezoid-rule integral of the success rate over ``env_steps`` divided
# by the evaluated range (last minus first evaluation's ``env_steps``), i.e. the mean success over
# that range, in [0, 1] for success rates. Uneven spacing is weighted by the spacing; a single
# evaluation (zero-width range) gives its own value; no evaluation gives ``None``. Points whose
# value is NaN (a grid point no run covers) are left out. It summarises how early *and* how well a
# run learns in one number, where success at the budget and the improvement timestep each see
# one side.


def improvement_timestep(steps: Sequence[float], values: Sequence[float]) -> float | None:
    """The steps of the earliest evaluation from which every later one (by steps) has value > 0.

    ``None`` when there are no evaluations or the last one is not > 0. Evaluations are ordered by
    ``steps`` (stably, so equal steps keep their given order)."""
    s = np.asarray(steps, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if s.shape != v.shape or s.ndim != 1:
        raise ValueError(f"steps {s.shape} and values {v.shape} must be equal-length 1-D")
    order = np.argsort(s, kind="stable")
    s, v = s[order], v[order]
    i = len(v)
    while i > 0 and v[i - 1] > 0:  # NaN is not > 0: a gap breaks the streak
        i -= 1
    if i == len(v):
        return None
    out = s[i]
    return int(out) if float(out).is_integer() else float(out)


def success_auc(steps: Sequence[float], values: Sequence[float]) -> float | None:
    """Normalised area under a (steps, values) curve: the trapezoid rule on ``steps`` divided by the
    evaluated range, i.e. the mean value over it (see the comment above). ``None`` if empty."""
    s = np.asarray(steps, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if s.shape != v.shape or s.ndim != 1:
        raise ValueError(f"steps {s.shape} and values {v.shape} must be equal-length 1-D")
    keep = ~(np.isnan(s) | np.isnan(v))
    s, v = s[keep], v[keep]
    if s.size == 0:
        return None
    order = np.argsort(s, kind="stable")
    s, v = s[order], v[order]
    width = s[-1] - s[0]
    if width == 0:
        return float(v.mean())  # one evaluation (or several at the same steps): no range to average over
    return float(np.sum((v[1:] + v[:-1]) * np.diff(s)) / 2.0 / width)


def run_success_auc(records: Iterable[Mapping], key: str = "success_rate") -> float | None:
    """:func:`success_auc` of one run's history (as :func:`curve` reads it)."""
    return success_auc(*curve(records, key))


def run_improvement_timestep(records: Iterable[Mapping], key: str = "success_rate") -> int | None:
    """:func:`improvement_timestep` of one run's history (records with unknown env steps ignored)."""
    steps, values = curve(records, key)
    t = improvement_timestep(steps, values)
    return None if t is None else int(t)


# --------------------------------------------------------------------------------------------
# curves across runs
# --------------------------------------------------------------------------------------------

# Curves across runs (seeds):
# :func:`curve` turns a history into (env_steps, value) sorted by env_steps, dropping records with
# unknown steps (< 0) and keeping only the last record of repeated env_steps. :func:`align` puts
# several curves on a common grid (default: the union of all evaluation steps) either by *step-wise
# hold* (the value of the last evaluation at or before the grid point: what the policy was known to
# achieve) or by *linear interpolation* between evaluations; a grid point before a run's first or
# after its last evaluation is NaN for that run, so no run is extrapolated. :func:`mean_std` then
# reduces across runs, ignoring NaNs, with the number of runs contributing to each point.


def curve(records: Iterable[Mapping], key: str = "success_rate") -> tuple[np.ndarray, np.ndarray]:
    """(env_steps, values) of one run, sorted by env_steps.

    Records whose ``env_steps`` is missing or negative (unknown) or whose value is missing are
    dropped; of several records at the same env_steps the last one (in file order) is kept."""
    by_step: dict[int, float] = {}
    for r in records:
        steps, value = r.get("env_steps"), r.get(key)
        if not isinstance(steps, (int, float)) or steps < 0 or not isinstance(value, (int, float)):
            continue
        by_step[int(steps)] = float(value)
    xs = np.array(sorted(by_step), dtype=np.float64)
    return xs, np.array([by_step[int(x)] for x in xs], dtype=np.float64)


def common_grid(curves: Sequence[tuple[np.ndarray, np.ndarray]], points: int | None = None) -> np.ndarray:
    """Grid for :func:`align`: the sorted union of all evaluation steps, or ``points`` evenly spaced
    steps from the earliest to the latest evaluation."""
    xs = [np.asarray(c[0], np.float64) for c in curves if len(c[0])]
    if not xs:
        return np.zeros(0)
    if points is None:
        return np.unique(np.concatenate(xs))
    if points < 1:
        raise ValueError(f"points must be >= 1, got {points}")
    lo, hi = min(x[0] for x in xs), max(x[-1] for x in xs)
    return np.linspace(lo, hi, points)


def align(
    curves: Sequence[tuple[np.ndarray, np.ndarray]], grid: np.ndarray, method: str = "hold"
) -> np.ndarray:
    """(runs, len(grid)) values of each curve at the grid points; NaN outside a run's evaluated span.

    ``hold``: the value of the last evaluation at or before the point. ``linear``: linear
    interpolation between the evaluations around the point. Curves must be sorted by steps (as
    :func:`curve` returns them)."""
    if method not in INTERPOLATIONS:
        raise ValueError(f"method must be one of {INTERPOLATIONS}, not {method!r}")
    g = np.asarray(grid, np.float64)
    out = np.full((len(curves), len(g)), np.nan)
    for k, (xs, ys) in enumerate(curves):
        xs, ys = np.asarray(xs, np.float64), np.asarray(ys, np.float64)
        if xs.size == 0:
            continue
        if np.any(np.diff(xs) < 0):
            raise ValueError("curve steps must be sorted")
        inside = (g >= xs[0]) & (g <= xs[-1])
        if method == "hold":
            idx = np.searchsorted(xs, g, side="right") - 1
            out[k] = np.where(inside, ys[np.clip(idx, 0, len(ys) - 1)], np.nan)
        else:
            out[k] = np.where(inside, np.interp(g, xs, ys), np.nan)
    return out


def mean_std(values: np.ndarray, ddof: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, standard deviation and count over runs (axis 0), ignoring NaN.

    A point no run covers is NaN in mean and std. ``ddof=0`` (population std, the default) gives
    std 0 for a single run; with ``ddof=1`` a single run's std is NaN."""
    v = np.atleast_2d(np.asarray(values, np.float64))
    ok = ~np.isnan(v)
    n = ok.sum(axis=0)
    total = np.where(ok, v, 0.0).sum(axis=0)
    mean = np.divide(total, n, out=np.full(v.shape[1], np.nan), where=n > 0)
    sq = np.where(ok, (v - mean) ** 2, 0.0).sum(axis=0)
    std = np.sqrt(np.divide(sq, n - ddof, out=np.full(v.shape[1], np.nan), where=n - ddof > 0))
    return mean, std, n


__all__ = [
    "INTERPOLATIONS",
    "align",
    "common_grid",
    "curve",
    "improvement_timestep",
    "mean_std",
    "run_improvement_timestep",
    "run_success_auc",
    "success_auc",
]
