"""mea_tools.bench.stats on fixed inputs: IQM by hand, intervals that contain their estimate and shrink
with more runs, probability of improvement, the "within noise" verdict, reproducible bootstrap."""

from __future__ import annotations

import numpy as np
import pytest

from mea_tools.bench import stats
from mea_tools.bench.stats import Bootstrap, Interval

pytestmark = pytest.mark.unit

BOOT = Bootstrap(reps=2_000, seed=7)


def test_iqm_is_the_mean_of_the_middle_half():
    assert stats.iqm([8, 1, 7, 2, 6, 3, 5, 4]) == pytest.approx(4.5)  # (3 + 4 + 5 + 6) / 4
    # 8 runs: the 2 lowest and 2 highest are cut, so the outliers at 100 count once, not three times
    assert stats.iqm([0, 0, 1, 1, 1, 100, 100, 100]) == pytest.approx((1 + 1 + 1 + 100) / 4)


def test_arm_summary_mean_iqm_std_and_intervals_that_contain_them():
    values = [0.2, 0.4, 0.4, 0.5, 0.9]
    s = stats.summarize_arm(values, BOOT)
    assert s is not None and s.runs == 5
    assert s.mean.point == pytest.approx(0.48) and s.std == pytest.approx(np.std(values))
    assert s.iqm.point == pytest.approx(stats.iqm(values))
    for est in (s.mean, s.iqm):
        assert est.lo <= est.point <= est.hi and est.lo < est.hi
        assert est.lo >= 0.2 and est.hi <= 0.9  # a resampled mean stays within the runs' range
    assert stats.summarize_arm([], BOOT) is None


def test_intervals_shrink_with_more_runs():
    rng = np.random.default_rng(0)
    pool = rng.uniform(0.0, 1.0, size=48)
    few, many = stats.mean_interval(pool[:4], BOOT), stats.mean_interval(pool, BOOT)
    assert few is not None and many is not None
    assert (many.hi - many.lo) < 0.6 * (few.hi - few.lo)


def test_a_fixed_bootstrap_seed_reproduces_the_interval_and_another_seed_moves_it():
    values = np.linspace(0.0, 1.0, 9) ** 2
    a = stats.summarize_arm(values, BOOT)
    np.random.seed(123)  # the caller's global RNG must neither matter nor be disturbed
    before = np.random.get_state()[1].copy()
    b = stats.summarize_arm(values, BOOT)
    assert np.array_equal(np.random.get_state()[1], before)
    assert a == b
    c = stats.summarize_arm(values, Bootstrap(reps=BOOT.reps, seed=BOOT.seed + 1))
    assert c is not None and a is not None and (c.mean.lo, c.mean.hi) != (a.mean.lo, a.mean.hi)


def test_identical_arms_give_probability_of_improvement_one_half_and_are_within_noise():
    x = [0.1, 0.3, 0.5]
    c = stats.compare(x, list(x), BOOT)
    assert c is not None
    assert c.probability_of_improvement.point == pytest.approx(0.5)
    assert c.within_noise


@pytest.mark.slow
def test_separated_arms_are_not_within_noise_and_improvement_is_certain():
    low, high = [0.0, 0.02, 0.04], [0.9, 0.92, 0.94]
    up = stats.compare(high, low, BOOT)
    down = stats.compare(low, high, BOOT)
    assert up is not None and down is not None
    assert not up.within_noise and not down.within_noise
    assert up.probability_of_improvement == Interval(1.0, 1.0, 1.0)
    assert down.probability_of_improvement.point == pytest.approx(0.0)
    # overlapping arms: the verdict flips back
    near = stats.compare([0.3, 0.5, 0.7], [0.35, 0.55, 0.6], BOOT)
    assert near is not None and near.within_noise
    assert 0.0 < near.probability_of_improvement.point < 1.0
    assert stats.compare([], low, BOOT) is None


def test_within_noise_is_interval_overlap():
    assert stats.within_noise(Interval(0.5, 0.4, 0.6), Interval(0.65, 0.6, 0.7))  # touching counts
    assert not stats.within_noise(Interval(0.5, 0.4, 0.59), Interval(0.65, 0.6, 0.7))


def test_curve_band_keeps_points_every_run_covers_and_brackets_the_mean():
    steps = np.array([0.0, 1000.0, 2000.0, 3000.0])
    values = np.array([[0.0, 0.2, 0.4, np.nan], [0.0, 0.4, 0.6, 0.8], [0.0, 0.3, 0.8, 0.9]])
    band = stats.curve_band(steps, values, BOOT)
    assert band.runs == 3 and band.steps.tolist() == [0.0, 1000.0, 2000.0]  # run 0 stopped before 3000
    assert band.mean == pytest.approx([0.0, 0.3, 0.6])
    assert np.all(band.lo <= band.mean) and np.all(band.mean <= band.hi)
    assert band.lo[0] == band.hi[0] == 0.0 and band.hi[2] - band.lo[2] > band.hi[1] - band.lo[1]
    with pytest.raises(ValueError, match="steps"):
        stats.curve_band(steps[:2], values, BOOT)


def test_performance_profile_is_the_fraction_of_runs_above_each_threshold():
    taus = np.array([0.0, 0.25, 0.5, 0.75])
    p = stats.performance_profiles({"a": [0.1, 0.3, 0.6, 0.9], "b": [0.0, 0.0], "none": []}, taus, BOOT)
    assert set(p) == {"a", "b"}
    assert p["a"].fraction == pytest.approx([1.0, 0.75, 0.5, 0.25])
    assert p["b"].fraction == pytest.approx([0.0, 0.0, 0.0, 0.0])
    assert np.all(p["a"].lo <= p["a"].fraction) and np.all(p["a"].fraction <= p["a"].hi)
