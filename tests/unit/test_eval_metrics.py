"""Evaluation math: grasp score, improvement timestep, AUC, curves across seeds."""

from __future__ import annotations

import numpy as np
import pytest

from services.episodes.scores import H_MAX, EpisodeResult, episode_result, grasp_score, summarize
from services.evaluator.core.curves import (
    align,
    common_grid,
    curve,
    improvement_timestep,
    mean_std,
    run_improvement_timestep,
    run_success_auc,
    success_auc,
)

pytestmark = pytest.mark.unit


# ---------------------------------------------------------------------------- grasp score, summary


def test_grasp_score_is_time_left_over_horizon_on_success_and_zero_on_failure():
    assert H_MAX == 50
    assert grasp_score(True, 10) == pytest.approx(0.8)  # (50 - 10) / 50
    assert grasp_score(True, 50) == 0.0  # success on the very last step
    assert grasp_score(True, 1) == pytest.approx(0.98)
    assert grasp_score(False, 10) == 0.0  # a failure scores 0 however short
    assert grasp_score(True, 20, h_max=80) == pytest.approx(0.75)
    assert grasp_score(True, 60) == 0.0  # clipped: never negative
    with pytest.raises(ValueError):
        grasp_score(True, 1, h_max=0)


def test_episode_result_reads_success_from_the_last_terminal_flag():
    ok = episode_result([0.0] * 11 + [1.0], [False] * 11 + [True], seed=7)
    assert ok == EpisodeResult(success=True, length=12, ret=1.0, seed=7)
    timeout = episode_result([0.0] * 50, [False] * 50)
    assert not timeout.success and timeout.length == 50 and timeout.ret == 0.0
    with pytest.raises(ValueError):
        episode_result([0.0, 0.0], [False])


def test_summarize_averages_over_episodes_with_failures_scoring_zero():
    results = [
        EpisodeResult(True, 10, 1.0),  # s_g 0.8
        EpisodeResult(True, 30, 1.0),  # s_g 0.4
        EpisodeResult(False, 50, 0.0),  # s_g 0
        EpisodeResult(False, 50, 0.0),
    ]
    s = summarize(results)
    assert s.episodes == 4
    assert s.success_rate == 0.5
    assert s.mean_return == 0.5
    assert s.mean_length == pytest.approx(35.0)
    assert s.grasp_score == pytest.approx((0.8 + 0.4) / 4)
    none = summarize([EpisodeResult(False, 50, 0.0)] * 3)
    assert none.success_rate == 0.0 and none.grasp_score == 0.0
    with pytest.raises(ValueError):
        summarize([])


# ---------------------------------------------------------------------------- improvement timestep


@pytest.mark.parametrize(
    ("steps", "success", "expected"),
    [
        ([0, 250, 500, 750], [0.0, 0.0, 0.1, 0.3], 500),  # rises and stays
        ([0, 250, 500, 750], [0.0, 0.2, 0.0, 0.3], 750),  # drops back to 0: only the last streak counts
        ([0, 250, 500], [0.0, 0.0, 0.0], None),  # never > 0
        ([0, 250, 500], [0.2, 0.5, 0.0], None),  # ends at 0
        ([0, 250, 500], [0.1, 0.2, 0.3], 0),  # > 0 from the start
        ([300], [0.4], 300),  # single evaluation, > 0
        ([300], [0.0], None),  # single evaluation, 0
        ([], [], None),  # no evaluations
        ([500, 0, 250], [0.3, 0.0, 0.1], 250),  # ordered by steps, not by position
    ],
)
def test_improvement_timestep(steps, success, expected):
    assert improvement_timestep(steps, success) == expected


def test_improvement_timestep_of_a_history_ignores_unknown_steps():
    records = [
        {"env_steps": -1, "success_rate": 0.0},  # unknown steps: not on the curve
        {"env_steps": 100, "success_rate": 0.0},
        {"env_steps": 200, "success_rate": 0.5},
        {"env_steps": 300, "success_rate": 0.2},
    ]
    assert run_improvement_timestep(records) == 200
    assert run_improvement_timestep([]) is None
    with pytest.raises(ValueError):
        improvement_timestep([1, 2], [0.1])


# ---------------------------------------------------------------------------- area under the curve


@pytest.mark.parametrize(
    ("steps", "success", "expected"),
    [
        # even spacing: (0 + .5)/2*100 + (.5 + 1)/2*100 = 100 over a 200-step range
        ([0, 100, 200], [0.0, 0.5, 1.0], 0.5),
        # uneven spacing weighs each segment by its width: (.2+.6)/2*100 + (.6+0)/2*300 = 130 over 400
        ([0, 100, 400], [0.2, 0.6, 0.0], 0.325),
        # the same evaluations in another order: sorted by steps first
        ([400, 0, 100], [0.0, 0.2, 0.6], 0.325),
        # a range that does not start at 0: (0+1)/2*1000 + 1*2000 = 2500 over 3000
        ([1000, 2000, 4000], [0.0, 1.0, 1.0], 2500 / 3000),
        ([0, 1000], [1.0, 1.0], 1.0),  # always successful: 1
        ([0, 1000, 2000], [0.0, 0.0, 0.0], 0.0),
        ([500], [0.4], 0.4),  # a single evaluation: its own success
        ([500, 500], [0.2, 0.4], 0.3),  # several at one step, no range: their mean
        ([0, 100, 200], [0.2, float("nan"), 0.4], 0.3),  # a NaN point (no run there) is left out
        ([], [], None),
    ],
)
def test_success_auc_is_the_trapezoid_mean_over_the_evaluated_range(steps, success, expected):
    got = success_auc(steps, success)
    if expected is None:
        assert got is None
    else:
        assert got == pytest.approx(expected, abs=1e-12)
        assert 0.0 <= got <= 1.0


def test_success_auc_is_not_the_plain_mean_of_the_evaluations():
    # plain mean of [0, 0, 1] is 1/3; the curve spends 900 of 1000 steps at 0 and rises in the last 100
    assert success_auc([0, 900, 1000], [0.0, 0.0, 1.0]) == pytest.approx(0.05)
    with pytest.raises(ValueError):
        success_auc([0, 1], [0.5])


def test_success_auc_of_a_history_uses_its_curve():
    records = [
        {"env_steps": -1, "success_rate": 1.0},  # unknown steps: not on the curve
        {"env_steps": 0, "success_rate": 0.0},
        {"env_steps": 100, "success_rate": 0.9},  # replaced by the later record at 100
        {"env_steps": 300, "success_rate": 0.5},
        {"env_steps": 100, "success_rate": 0.5},
    ]
    # curve: (0, 0), (100, .5), (300, .5): (0+.5)/2*100 + .5*200 = 125 over 300
    assert run_success_auc(records) == pytest.approx(125 / 300)
    assert run_success_auc([]) is None


# ---------------------------------------------------------------------------- curves across runs


def test_curve_sorts_drops_unknown_steps_and_keeps_the_last_record_per_step():
    records = [
        {"env_steps": 200, "success_rate": 0.4},
        {"env_steps": 0, "success_rate": 0.0},
        {"env_steps": -1, "success_rate": 0.9},
        {"env_steps": 200, "success_rate": 0.6},  # re-evaluated at the same steps: this one counts
        {"success_rate": 1.0},
        {"env_steps": 100},
    ]
    xs, ys = curve(records)
    assert xs.tolist() == [0.0, 200.0] and ys.tolist() == [0.0, 0.6]


# Two runs evaluated at different steps; hand computation below.
RUN_A = (np.array([0.0, 100.0, 200.0]), np.array([0.0, 0.5, 1.0]))
RUN_B = (np.array([50.0, 150.0]), np.array([0.2, 0.4]))


def test_align_hold_and_mean_std_match_a_hand_computation():
    grid = common_grid([RUN_A, RUN_B])
    assert grid.tolist() == [0, 50, 100, 150, 200]  # union of evaluation steps
    m = align([RUN_A, RUN_B], grid, "hold")
    nan = np.nan
    np.testing.assert_array_equal(m[0], [0.0, 0.0, 0.5, 0.5, 1.0])
    np.testing.assert_array_equal(m[1], [nan, 0.2, 0.2, 0.4, nan])  # nothing outside B's span [50, 150]
    mean, std, n = mean_std(m)
    np.testing.assert_allclose(mean, [0.0, 0.1, 0.35, 0.45, 1.0])
    np.testing.assert_allclose(std, [0.0, 0.1, 0.15, 0.05, 0.0])  # population std over the covering runs
    assert n.tolist() == [1, 2, 2, 2, 1]
    _, std1, _ = mean_std(m, ddof=1)
    np.testing.assert_allclose(std1, [nan, np.sqrt(0.02), np.sqrt(0.045), np.sqrt(0.005), nan])


def test_align_linear_interpolates_between_evaluations_only():
    grid = np.array([0.0, 50.0, 100.0, 150.0, 200.0, 250.0])
    m = align([RUN_A, RUN_B], grid, "linear")
    nan = np.nan
    np.testing.assert_allclose(m[0], [0.0, 0.25, 0.5, 0.75, 1.0, nan])
    np.testing.assert_allclose(m[1], [nan, 0.2, 0.3, 0.4, nan, nan])
    mean, _, n = mean_std(m)
    np.testing.assert_allclose(mean, [0.0, 0.225, 0.4, 0.575, 1.0, nan])
    assert n.tolist() == [1, 2, 2, 2, 1, 0]


def test_common_grid_with_points_and_edge_cases():
    np.testing.assert_allclose(common_grid([RUN_A, RUN_B], points=5), [0, 50, 100, 150, 200])
    assert common_grid([]).size == 0
    assert common_grid([(np.zeros(0), np.zeros(0))]).size == 0
    with pytest.raises(ValueError):
        align([RUN_A], np.array([0.0]), "cubic")
    with pytest.raises(ValueError):
        align([(np.array([2.0, 1.0]), np.array([0.0, 0.0]))], np.array([1.0]))
    single = align([RUN_A], np.array([100.0]), "hold")
    mean, std, n = mean_std(single)
    assert mean.tolist() == [0.5] and std.tolist() == [0.0] and n.tolist() == [1]


def test_improvement_of_a_mean_curve_is_the_papers_reading():
    grid = common_grid([RUN_A, RUN_B])
    mean, _, _ = mean_std(align([RUN_A, RUN_B], grid, "hold"))
    # mean is [0, 0.1, 0.35, 0.45, 1.0]: > 0 from 50 steps on
    assert improvement_timestep(grid, mean) == 50
