"""The evaluator's schedule: which version is due when (env-step cadence, budget, restarts) and on
which held-out seeds, without a clock, a bus or a simulator."""

from __future__ import annotations

import pytest

from services.evaluator.core.schedule import Schedule, last_evaluated_env_steps

pytestmark = pytest.mark.unit


def schedule(**kw) -> Schedule:
    base = {"episodes": 3, "every_env_steps": 250, "seed_base": 1_000_000_000, "first_gate_wait": 2.0}
    return Schedule(**(base | kw))


def test_the_first_version_is_due_once_steps_are_known_or_the_gate_wait_is_over():
    s = schedule()
    assert not s.due(-1, None, waited=0.0)  # no gate yet: wait for the steps
    assert not s.due(-1, None, waited=1.99)
    assert s.due(-1, None, waited=2.0)  # waited long enough: evaluate with unknown steps
    assert s.due(0, None, waited=0.0)  # a gate: at once, whatever its steps
    assert s.due(40, None, waited=0.0)


@pytest.mark.parametrize(
    ("steps", "last", "due"),
    [
        (1100, 1000, False),
        (1249, 1000, False),
        (1250, 1000, True),  # advanced by every_env_steps
        (5000, 1000, True),
        (1000, 1000, False),
        (300, 1000, True),  # the learner went back (restarted): start afresh
        (-1, 1000, False),  # steps known before, not yet now (a resume): wait for the gate
        (1100, -1, True),  # the last evaluation had no steps: every new version
    ],
)
def test_the_cadence_in_env_steps(steps, last, due):
    assert schedule().due(steps, last, waited=100.0) is due


def test_the_budget_is_evaluated_off_the_cadence_once():
    s = schedule(final_env_steps=1200)
    for steps, due in ((1100, False), (1199, False), (1200, True), (1249, True)):
        assert s.due(steps, 1000, waited=100.0) is due, steps
    # evaluated at the budget: back to the cadence
    for steps, due in ((1200, False), (1449, False), (1450, True)):
        assert s.due(steps, 1200, waited=100.0) is due, steps
    assert not schedule(final_env_steps=0).due(1200, 1000, waited=100.0)  # no budget


def test_seeds_before_and_at_the_budget_are_one_sequence():
    s = schedule(seed_base=100, final_env_steps=2000, final_episodes=5)
    assert s.seeds_at(-1) == s.seeds_at(1999) == (100, 101, 102)
    assert s.seeds_at(2000) == s.seeds_at(2500) == (100, 101, 102, 103, 104)
    assert s.at_budget(2000) and s.at_budget(2500) and not s.at_budget(1999) and not s.at_budget(-1)
    # no budget, or no final size: every evaluation has `episodes`
    assert not schedule(final_episodes=5).at_budget(10**6)
    assert schedule(final_episodes=5).seeds_at(10**6) == (1_000_000_000, 1_000_000_001, 1_000_000_002)
    assert schedule(seed_base=0, final_env_steps=2000).seeds_at(2000) == (0, 1, 2)


def test_the_last_evaluated_steps_come_from_the_history():
    assert last_evaluated_env_steps([]) is None
    assert last_evaluated_env_steps([{"version": 1}, {"env_steps": 2.5}]) is None  # none with int steps
    records = [{"env_steps": 0}, {"env_steps": 500}, {"env_steps": 250}, {"version": 4}]
    assert last_evaluated_env_steps(records) == 250  # file order, not the largest
    assert last_evaluated_env_steps([{"env_steps": 250}, {"env_steps": -1}]) == -1
