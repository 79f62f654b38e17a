"""The safety envelope: whatever a policy outputs, the command sent stays within the robot's per-step
limits and workspace, bad actions and observations give a hold with a reason, and what is within
the limits passes unchanged."""

from __future__ import annotations

import math

import numpy as np
import pytest

from proto.actions import JAW, THETA, XYZ
from services.inference.core.envelope import CLAMP_REASONS, HOLD_REASONS, Envelope, Limits

LIMITS = Limits(max_translation=0.03, max_rotation=math.pi / 16, min_interval=0.0)
LOW, HIGH = np.array(LIMITS.workspace_low), np.array(LIMITS.workspace_high)


def moved(limits: Limits, action: np.ndarray) -> tuple[np.ndarray, float]:
    return action[XYZ].astype(np.float64) * limits.metres_per_unit, float(
        action[THETA]
    ) * limits.radians_per_unit


def test_an_action_within_the_limits_is_sent_as_asked():
    env = Envelope(LIMITS)
    a = np.array([-0.5, 0.2, -0.3, 0.1, 0.4], np.float32)  # 0.019 m, pi/20 rad
    d = env.command(a, np.array([0.0, 0.0, 0.1]), now=0.0)
    assert not d.hold and d.reasons == () and np.array_equal(d.action, a)
    assert env.jaw == -0.5


def test_adversarial_actions_never_leave_the_limits():
    rng = np.random.default_rng(0)
    env = Envelope(LIMITS)
    seen = set()
    for k in range(5_000):
        a = rng.normal(0.0, 10.0 ** rng.uniform(-1, 6), 5)
        if k % 50 == 0:
            a[rng.integers(0, 5)] = rng.choice([np.nan, np.inf, -np.inf])
        pivot = rng.uniform(LOW, HIGH)
        d = env.command(a, pivot, now=float(k))
        seen.update(d.reasons)
        assert (
            d.action.shape == (5,) and np.isfinite(d.action).all() and (np.abs(d.action) <= 1.0 + 1e-6).all()
        )
        move, turn = moved(LIMITS, d.action)
        assert np.linalg.norm(move) <= LIMITS.max_translation + 1e-7
        assert abs(turn) <= LIMITS.max_rotation + 1e-7
        assert ((pivot + move >= LOW - 1e-7) & (pivot + move <= HIGH + 1e-7)).all()
        if d.hold:
            assert not move.any() and turn == 0.0 and set(d.reasons) <= set(HOLD_REASONS)
        else:
            assert set(d.reasons) <= set(CLAMP_REASONS)
    assert {"non_finite_action", "range", "max_translation", "max_rotation", "workspace"} <= seen


def test_a_long_move_is_shortened_along_its_direction():
    env = Envelope(LIMITS)
    d = env.command(np.array([1, 1, 1, 0, 0], np.float32), np.zeros(3) + [0, 0, 0.1], now=0.0)
    move, _ = moved(LIMITS, d.action)
    assert d.reasons == ("max_translation",)
    np.testing.assert_allclose(move, np.array([1, 1, 0]) / math.sqrt(2) * 0.03, atol=1e-7)


def test_the_workspace_cuts_moves_out_and_lets_a_stray_pivot_come_back():
    env = Envelope(LIMITS)
    edge = np.array([HIGH[0] - 0.01, 0.0, 0.1])  # 1 cm inside the +x face
    d = env.command(np.array([1, 1, 0.5, 0, 0], np.float32), edge, now=0.0)  # out along +x, and +y
    move, _ = moved(LIMITS, d.action)
    assert d.reasons == ("max_translation", "workspace")
    assert move[0] == pytest.approx(0.01, rel=1e-6) and move[1] == pytest.approx(
        0.03 / math.sqrt(5), rel=1e-6
    )
    outside = np.array([HIGH[0] + 0.02, 0.0, 0.1])  # 2 cm out (within the 5 cm observation margin)
    back = env.command(np.array([1, -0.4, 0, 0, 0], np.float32), outside, now=1.0)
    assert not back.hold and moved(LIMITS, back.action)[0][0] == pytest.approx(-0.02, rel=1e-6)
    further = env.command(np.array([1, 0.4, 0, 0, 0], np.float32), outside, now=2.0)
    assert "workspace" in further.reasons and moved(LIMITS, further.action)[0][0] == 0.0


@pytest.mark.parametrize(
    ("pivot", "reason"),
    [([np.nan, 0, 0.1], "non_finite_observation"), ([0, 0, np.inf], "non_finite_observation"),
     ([HIGH[0] + 0.2, 0, 0.1], "out_of_workspace"), ([0, 0], "non_finite_observation")],
)  # fmt: skip
def test_bad_observations_hold_with_the_last_jaw_command(pivot, reason):
    env = Envelope(LIMITS)
    env.command(np.array([-1, 0, 0, 0, 0], np.float32), np.array([0, 0, 0.1]), now=0.0)  # close
    d = env.command(np.array([1, 1, 0, 0, 0], np.float32), np.array(pivot, float), now=1.0)
    assert d.hold and d.reasons == (reason,) and d.action.tolist() == [-1, 0, 0, 0, 0]


def test_the_rate_limit_holds_commands_that_come_too_soon():
    env = Envelope(Limits(min_interval=0.1))
    a, p = np.array([1, 0.1, 0, 0, 0], np.float32), np.array([0, 0, 0.1])
    assert not env.command(a, p, now=10.0).hold
    assert env.command(a, p, now=10.05).reasons == ("rate",)
    assert not env.command(a, p, now=10.2).hold


@pytest.mark.parametrize(
    "kw",
    [{"workspace_low": (0, 0, 0), "workspace_high": (1, 1, 0)}, {"max_translation": 0.0},
     {"radians_per_unit": float("nan")}, {"min_interval": -1.0}, {"workspace_low": (0, 0)}],
)  # fmt: skip
def test_limits_refuse_what_cannot_be_an_envelope(kw):
    with pytest.raises(ValueError):
        Limits(**kw)


def test_a_hold_keeps_the_jaw_open_at_start():
    d = Envelope(LIMITS).command(np.full(5, np.nan), np.zeros(3) + [0, 0, 0.1], now=0.0)
    assert d.hold and d.action[JAW] == 1.0 and not d.action[1:].any()
