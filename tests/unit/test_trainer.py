"""The learner's training step and replay-gate arithmetic (``services.algorithms.trainer``), without
a bus: how many env steps the gate allows, when an update may run, what a step returns."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.algorithms.rate_limiter import SampleToInsertRatio
from services.algorithms.trainer import allowed_steps
from tests.helpers.learner import learner_episode, tiny_trainer

pytestmark = pytest.mark.unit


@pytest.mark.parametrize(
    ("inserted", "inserts_allowed", "max_env_steps", "expected"),
    [
        (0, 30, 0, 30),
        (40, 18, 0, 58),
        (40, 0, 0, 40),
        (40, -3, 0, 40),  # producers overshot: the gate never goes below what is in
        (40, 18, 50, 50),  # the run's budget caps the allowance
        (40, 18, 30, 40),  # ... but never below what is already in
        (0, 30, 100, 30),
    ],
)
def test_allowed_steps_reference_numbers(inserted, inserts_allowed, max_env_steps, expected) -> None:
    assert allowed_steps(inserted, inserts_allowed, max_env_steps) == expected


@pytest.mark.parametrize(
    ("spi", "min_steps", "error_buffer", "inserted", "updates", "allowed", "samples_allowed"),
    [
        # the paper's ratio: 1 update per env step, 100 steps first, 200 updates of slack
        (1.0, 100, 200.0, 0, 0, 300, 0),
        (1.0, 100, 200.0, 100, 0, 300, 200),
        (1.0, 100, 200.0, 300, 150, 450, 250),
        # cpu-small's: 0.5 updates per env step, so producers run 2 steps per update
        (0.5, 100, 100.0, 0, 0, 300, 0),
        (0.5, 100, 100.0, 300, 0, 300, 200),
        (0.5, 100, 100.0, 300, 10, 320, 190),
        # the learner service test's: updates allowed = 0.5 * steps - 5
        (0.5, 20, 5.0, 0, 0, 30, 0),
        (0.5, 20, 5.0, 30, 10, 50, 0),
        (0.5, 20, 5.0, 40, 14, 58, 1),
    ],
)
def test_gate_allowance_and_updates_allowed_for_reference_ratios(
    spi, min_steps, error_buffer, inserted, updates, allowed, samples_allowed
) -> None:
    limiter = SampleToInsertRatio(spi, min_steps, error_buffer)
    limiter.inserted(inserted)
    limiter.sampled(updates)
    assert allowed_steps(limiter.inserts, limiter.inserts_allowed()) == allowed
    assert limiter.samples_allowed() == samples_allowed
    assert limiter.can_sample() == (samples_allowed > 0)


def test_updates_run_only_within_the_ratio_and_copies_are_not_env_steps() -> None:
    trainer = tiny_trainer(samples_per_insert=0.5, min_steps=20, error_buffer=5.0, max_updates=5)
    raw = learner_episode(0, T=10, demo=True)
    trainer.insert(raw)
    trainer.insert(learner_episode(50, copy_of=raw.episode_id))
    g = trainer.gate()
    assert (g.inserted, g.replay_transitions, g.replay_episodes) == (10, 20, 2)
    assert not g.can_sample and g.samples_allowed == 0 and g.allowed == 30 and g.inserts_allowed == 20
    assert trainer.step() is None  # below min_steps: no update
    trainer.insert(learner_episode(1, T=10))
    g = trainer.gate()
    assert (
        g.inserted == trainer.env_steps == 20 and g.can_sample and g.samples_allowed == 5 and g.allowed == 30
    )
    due = []
    for _ in range(5):
        assert not trainer.done()
        info = trainer.step()
        assert info is not None and np.isfinite(info["critic_loss"])
        assert 0.0 <= info["batch_demo_share"] <= 1.0 and info["batch_reward_transitions"] >= 0.0
        due.append(trainer.publish_due())
    assert due == [False, True, False, True, False]  # publish_every 2
    assert trainer.step() is None  # 0.5 * 20 - 5 = 5 updates allowed, all done
    assert trainer.done() and trainer.updates == 5
    g = trainer.gate()
    assert (g.updates, g.samples_allowed, g.can_sample) == (5, 0, False)
    assert g.allowed == 40  # (max_diff 15 + 5 updates) / 0.5 = 40 env steps in total


def test_the_run_budget_caps_the_gate() -> None:
    trainer = tiny_trainer(samples_per_insert=0.5, min_steps=20, error_buffer=5.0, max_env_steps=25)
    trainer.insert(learner_episode(0, T=10))
    assert trainer.gate().allowed == 25
    for k in (1, 2):
        trainer.insert(learner_episode(k, T=10))
    g = trainer.gate()
    assert g.inserted == 30 and g.allowed == 30 and g.inserts_allowed == 0


def test_a_refused_episode_changes_nothing() -> None:
    trainer = tiny_trainer()
    with pytest.raises(ValueError, match="images"):
        trainer.insert(dataclasses.replace(learner_episode(0), images=None))
    g = trainer.gate()
    assert (g.inserted, g.replay_transitions, g.replay_episodes) == (0, 0, 0)


def test_the_gate_message_carries_the_reading() -> None:
    trainer = tiny_trainer(samples_per_insert=0.5, min_steps=20, error_buffer=5.0)
    trainer.insert(learner_episode(0, T=10))
    gate = trainer.gate().message("learner-0", "run-1", 3, 12.5)
    assert (gate.learner_id, gate.run_id, gate.policy_version, gate.created_at) == (
        "learner-0",
        "run-1",
        3,
        12.5,
    )
    assert (gate.inserted_steps, gate.allowed_steps, gate.updates, gate.replay_transitions) == (10, 30, 0, 10)


class Guard:
    """A lock stand-in that records how often it is taken and whether it is held."""

    def __init__(self) -> None:
        self.held, self.entries = False, 0

    def __enter__(self) -> None:
        assert not self.held
        self.held, self.entries = True, self.entries + 1

    def __exit__(self, *exc: object) -> None:
        self.held = False


def test_the_guard_covers_replay_and_limiter_but_never_an_update() -> None:
    guard = Guard()
    trainer = tiny_trainer(min_steps=10, guard=guard)
    update = trainer.agent.update

    def unguarded_update(batch):
        assert not guard.held, "a gradient update ran under the guard"
        return update(batch)

    trainer.agent.update = unguarded_update
    trainer.insert(learner_episode(0, T=10))
    trainer.gate()
    assert guard.entries == 2
    assert trainer.step() is not None
    assert guard.entries == 4  # drawing the batch, then counting the update
    trainer.limiter.sampled(100)
    assert trainer.step() is None and guard.entries == 5


def test_a_repeated_delivery_counts_its_env_steps_once() -> None:
    trainer = tiny_trainer()
    raw = learner_episode(0, T=9)
    trainer.insert(raw)
    with pytest.raises(ValueError, match="duplicate"):
        trainer.insert(raw)
    assert trainer.env_steps == 9 and trainer.gate().inserted == 9
