"""The actor's random prefill: uniformly random episodes until ``random_steps`` env steps, then the
configured policy (GASv2's reference prefills random steps beside its oracle demonstrations)."""

from __future__ import annotations

import pytest

from services.actor.config import ActorConfig
from services.actor.rollout import RolloutActor


@pytest.mark.parametrize("random_steps", [0, 1, 60])
@pytest.mark.slow
def test_random_episodes_come_first_until_the_prefill_is_done(random_steps):
    actor = RolloutActor(
        ActorConfig(task="block_pull", policy="expert", random_steps=random_steps), "actor-0"
    )
    try:
        kinds, steps = [], 0
        for k in range(4):
            b = actor.policy_episode(k)
            kinds.append(b.meta["policy_kind"])
            if b.meta["policy_kind"] == "random":
                assert steps < random_steps  # a random episode starts only while the prefill is short
                steps += b.num_steps
    finally:
        actor.env.close()
    n_random = kinds.count("random")
    assert kinds[:n_random] == ["random"] * n_random and all(k.startswith("expert") for k in kinds[n_random:])
    assert steps >= random_steps and (n_random == 0) == (random_steps == 0)


def test_random_steps_must_not_be_negative():
    with pytest.raises(ValueError, match="random_steps"):
        ActorConfig(random_steps=-1)
