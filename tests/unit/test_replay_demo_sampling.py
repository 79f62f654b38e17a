"""Demo-aware sampling and trimmed batches of SequenceReplay.

The demonstration set is every pinned episode (raw demos and augmented copies of them); a batch takes
``round(demo_fraction * B)`` episodes from it and the rest from the other episodes.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.unit.test_replay import SEQ_LEN, make_episode, make_replay

pytestmark = pytest.mark.unit


def filled(n_demo_raw: int = 2, copies: int = 3, online: int = 30):
    replay = make_replay(capacity=2_000)
    for k in range(n_demo_raw):
        replay.insert(make_episode(4, seed=k, eid=f"demo-{k}", demo=True))
        for c in range(copies):  # copies of a demo are pinned through their source id
            replay.insert(
                make_episode(4, seed=100 + 10 * k + c, eid=f"demo-{k}-c{c}", kind="mea", source=f"demo-{k}")
            )
    for k in range(online):
        replay.insert(make_episode(SEQ_LEN, seed=1_000 + k, eid=f"online-{k}"))
    return replay


@pytest.mark.parametrize("fraction", [0.25, 0.5, 0.75])
def test_every_batch_holds_the_configured_demo_share(fraction):
    replay = filled()
    rng = np.random.default_rng(0)
    for _ in range(50):
        batch = replay.sample(8, rng, demo_fraction=fraction)
        assert batch.is_demo.sum() == round(fraction * 8)


def test_demo_episodes_are_drawn_uniformly_within_the_demo_set():
    replay = filled()
    batch = replay.sample(40_000, np.random.default_rng(1), demo_fraction=0.5)
    demo_idx = batch.episode_index[batch.is_demo]
    counts = np.bincount(demo_idx, minlength=8)[:8]  # serials 0..7: the 2 demos and their 6 copies
    assert counts.sum() == 20_000
    expected = 20_000 / 8
    # within 5 standard deviations of a binomial count
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected * (1 - 1 / 8))), counts
    online = batch.episode_index[~batch.is_demo]
    assert online.min() >= 8 and len(np.unique(online)) == 30


def test_uniform_sampling_gives_demos_only_their_share_of_the_episodes():
    replay = filled()
    share = replay.sample(40_000, np.random.default_rng(2)).is_demo.mean()
    assert abs(share - 8 / 38) < 0.01


def test_a_missing_set_falls_back_to_the_other():
    only_online = make_replay()
    only_online.insert(make_episode(3, seed=1))
    assert not only_online.sample(8, np.random.default_rng(0), demo_fraction=0.5).is_demo.any()
    only_demo = make_replay()
    only_demo.insert(make_episode(3, seed=2, demo=True))
    assert only_demo.sample(8, np.random.default_rng(0), demo_fraction=0.5).is_demo.all()


def test_demo_fraction_out_of_range_is_refused():
    with pytest.raises(ValueError, match="demo_fraction"):
        filled().sample(4, demo_fraction=1.5)


def test_trimmed_batches_are_the_padded_ones_cut_at_the_longest_episode():
    replay = make_replay()
    for k, T in enumerate([3, 7, 5]):
        replay.insert(make_episode(T, seed=k))
    padded = replay.sample(16, np.random.default_rng(3))
    trimmed = replay.sample(16, np.random.default_rng(3), trim=True)
    L = int(padded.lengths.max())
    assert trimmed.seq_len == L < SEQ_LEN
    for name in ("actions", "rewards", "terminated", "truncated", "mask"):
        np.testing.assert_array_equal(getattr(trimmed, name), getattr(padded, name)[:, :L], err_msg=name)
    for name in ("image_codes", "constant", "obs_mask"):
        np.testing.assert_array_equal(getattr(trimmed, name), getattr(padded, name)[:, : L + 1], err_msg=name)
    assert not padded.mask[:, L:].any()  # what was cut was padding only


def online(k: int, success: bool):
    """An online episode that succeeded (terminated, reward on the last step) or timed out (truncated)."""
    ep = make_episode(6, seed=500 + k, eid=f"online-{k}")
    end = np.zeros(6, bool)
    end[-1] = True
    return dataclasses.replace(ep, rewards=end.astype(np.float32) * success, terminated=end & success,
                               truncated=end & (not success))  # fmt: skip


def with_successes():
    """2 demos, 3 online successes, 20 online failures."""
    replay = make_replay(capacity=2_000)
    for k in range(2):
        replay.insert(make_episode(4, seed=k, eid=f"demo-{k}", demo=True))
    for k in range(23):
        replay.insert(online(k, success=k < 3))
    return replay


def test_success_is_one_definition_the_last_step_terminated():
    replay = make_replay(capacity=2_000)
    replay.insert(make_episode(4, seed=0, eid="demo-0", demo=True))
    won, lost = online(0, success=True), online(1, success=False)
    rewarded_timeout = dataclasses.replace(lost, rewards=np.ones(6, np.float32), episode_id="online-2")
    silent_win = dataclasses.replace(won, rewards=np.zeros(6, np.float32), episode_id="online-3")
    assert [e.succeeded for e in (won, lost, rewarded_timeout, silent_win)] == [True, False, False, True]
    for ep in (won, lost, rewarded_timeout, silent_win):
        replay.insert(ep)
    joined = replay.sample(2_000, np.random.default_rng(1), demo_fraction=0.5, successes_as_demos=True)
    assert set(joined.episode_index[joined.from_demo_set]) == {0, 1, 4}  # demo, won, silent_win


def test_successes_join_the_demo_set_only_when_asked():
    replay = with_successes()
    rng = np.random.default_rng(5)
    plain = replay.sample(4_000, rng, demo_fraction=0.5)
    assert set(plain.episode_index[plain.from_demo_set]) == {0, 1}
    np.testing.assert_array_equal(plain.from_demo_set, plain.is_demo)
    joined = replay.sample(4_000, rng, demo_fraction=0.5, successes_as_demos=True)
    assert set(joined.episode_index[joined.from_demo_set]) == {0, 1, 2, 3, 4}
    assert joined.from_demo_set.sum() == 2_000
    assert not joined.is_demo[joined.episode_index >= 2].any()  # successes are not demonstrations
    assert (joined.rewards[joined.from_demo_set & ~joined.is_demo].sum(1) > 0).all()


def test_the_success_set_survives_a_checkpoint_round_trip():
    replay = with_successes()
    restored = make_replay(capacity=2_000)
    restored.load_state_dict(replay.state_dict())
    a = replay.sample(64, np.random.default_rng(6), demo_fraction=0.5, successes_as_demos=True)
    b = restored.sample(64, np.random.default_rng(6), demo_fraction=0.5, successes_as_demos=True)
    np.testing.assert_array_equal(a.episode_index, b.episode_index)
    np.testing.assert_array_equal(a.from_demo_set, b.from_demo_set)


def test_a_repeated_delivery_of_an_episode_is_refused_and_changes_nothing():
    replay = with_successes()
    before = (len(replay), replay.num_episodes, replay.episode_ids())
    with pytest.raises(ValueError, match="duplicate: episode 'online-4'"):
        replay.insert(online(4, success=False))
    assert (len(replay), replay.num_episodes, replay.episode_ids()) == before
    # also after a checkpoint round trip, and an id is free again once its episode is evicted
    restored = make_replay(capacity=2_000)
    restored.load_state_dict(replay.state_dict())
    with pytest.raises(ValueError, match="duplicate"):
        restored.insert(online(4, success=False))
    small = make_replay(capacity=30)
    for k in range(8):  # 6 steps each: the oldest are evicted
        small.insert(online(k, success=False))
    assert "online-0" not in small.episode_ids()
    small.insert(online(0, success=False))
