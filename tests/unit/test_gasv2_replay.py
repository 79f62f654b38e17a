"""ChunkReplay as math: sampled windows equal a per-episode python loop, DreamerV2's step convention
(is_first, discounts, handover, the action feature *into* a row), padding, demo-aware draws identical
to SequenceReplay's, checkpoint round trips through torch, refused inserts, pinned demos.

Episodes are synthetic Surgical Grasp Any rollouts built with numpy: random DSA codes with a state row
written by the DSA encoder (``dsa_image_from_voxels`` with empty clouds writes only that row), jaw
commands that open and close along the episode, random controller states; one test uses the
env-faithful ``synthetic_surgical_episode``.
"""

from __future__ import annotations

import dataclasses
import functools
import io

import numpy as np
import pytest
import torch

from proto.episode import Augmentation, Episode
from services.algorithms.gasv2.action_features import TOGGLE
from services.algorithms.gasv2.chunk_replay import ChunkReplay, ChunkSample, to_chunk_batch
from services.algorithms.gasv2.chunks import ChunkBatch
from services.algorithms.replay import SequenceReplay
from services.learner.checkpoint import _to_numpy, _to_torch
from services.observation import image_format
from services.observation.dsa import (
    SURGICAL_GRASP_ANY,
    decode_state_rows,
    dsa_image_from_voxels,
    state_blocks,
)
from tests.helpers import build_episode
from tests.helpers.synthetic import synthetic_surgical_episode

pytestmark = pytest.mark.unit

SIZE = 64
SEQ = 24
SEED = 2024
NO_VOXELS = np.zeros((0, 3), np.int64)


@functools.cache
def state_row(gripper: int, fsm: int, controller: int) -> np.ndarray:
    """The (SIZE,) state row the DSA encoder writes for these states."""
    image = dsa_image_from_voxels(
        NO_VOXELS,
        NO_VOXELS,
        SURGICAL_GRASP_ANY,
        gripper_state=gripper,
        fsm_state=fsm,
        controller_state=controller,
    )
    return image[2, -1].copy()


def make_episode(
    T: int,
    seed: int,
    *,
    eid: str | None = None,
    demo: bool = False,
    terminated: bool = True,
    source: str | None = None,
    jaw: np.ndarray | None = None,
) -> Episode:
    """A surgical episode of ``T`` steps with (T+1, 3, 64, 64) uint8 DSA images.

    Jaw commands (action component 0, the command *after* the step, >= 0 open) toggle at random,
    with exact zeros among them (open); ``jaw`` overrides them. ``source`` makes it an augmented
    copy (of a demo if ``source`` is one: pinned through its source id, ``is_demo`` left False).
    """
    rng = np.random.default_rng(seed)
    if jaw is None:
        open_after = np.cumsum(rng.random(T) < 0.3) % 2 == 0  # starts open, toggles ~30% of steps
        jaw = np.where(open_after, rng.choice([0.0, 1.0], T), -1.0)
    actions = np.empty((T, 5), np.float32)
    actions[:, 0] = jaw
    actions[:, 1:] = rng.uniform(-1.0, 1.0, (T, 4))
    controller = rng.integers(0, 2, T + 1)
    gripper = np.r_[0, (actions[:, 0] < 0).astype(int)]
    fsm = rng.integers(0, 6, T + 1)
    images = rng.integers(0, 256, (T + 1, 3, SIZE, SIZE), dtype=np.uint8)
    for t in range(T + 1):
        images[t, 2, -1] = state_row(int(gripper[t]), int(fsm[t]), int(controller[t]))
    ends, never = np.zeros(T, bool), np.zeros(T, bool)
    ends[-1] = True
    aug = None
    if source is not None:
        aug = Augmentation(
            source_episode_id=source, kind="mea", seed=seed, copy_index=0, phase_split=0, params={}
        )
    base = build_episode(T=T, seed=seed, P=2, task="surgical_grasp_any", validate=False)
    return dataclasses.replace(
        base,
        episode_id=eid or f"ep-{seed}",
        is_demo=demo,
        actions=actions,
        rewards=rng.standard_normal(T).astype(np.float32),
        terminated=ends if terminated else never,
        truncated=never if terminated else ends,
        images=images,
        augmentation=aug,
    )


def reference(replay: ChunkReplay, sample: ChunkSample, by_id: dict[str, Episode]) -> dict[str, np.ndarray]:
    """The windows rebuilt one entry at a time from the original episodes (the slow, obvious way)."""
    B, L = sample.shape
    ref = {
        "images": np.zeros((B, L, 3, SIZE, SIZE), np.uint8),
        "actions": np.zeros((B, L, 5), np.float32),
        "rewards": np.zeros((B, L), np.float32),
        "discounts": np.zeros((B, L), np.float32),
        "is_first": np.zeros((B, L), bool),
        "handover": np.zeros((B, L), bool),
        "mask": np.zeros((B, L), bool),
        "demo": np.zeros(B, np.float32),
    }
    for b in range(B):
        info = replay.episode_info(int(sample.episode_index[b]))
        ep = by_id[info["episode_id"]]
        T, t0 = ep.num_steps, int(sample.start[b])
        assert 0 <= t0 <= max(0, T + 1 - L), (t0, T, L)
        ref["demo"][b] = info["is_demo"]
        for t in range(L):
            r = t0 + t
            if r > T:
                continue  # padding: all zero
            ref["images"][b, t] = ep.images[r]
            ref["mask"][b, t] = True
            ref["handover"][b, t] = decode_state_rows(ep.images[r])[2] == 0
            ref["is_first"][b, t] = r == 0
            if r == 0:
                ref["discounts"][b, t] = 1.0
                continue
            a = ep.actions[r - 1]  # the action into row r
            was_open = True if r == 1 else ep.actions[r - 2, 0] >= 0  # the jaw opens before step 0
            ref["actions"][b, t, 0] = float((a[0] >= 0) != was_open)
            ref["actions"][b, t, 1:] = a[1:]
            ref["rewards"][b, t] = ep.rewards[r - 1]
            ref["discounts"][b, t] = 0.0 if ep.terminated[r - 1] else 1.0
    return ref


def assert_matches_reference(replay: ChunkReplay, sample: ChunkSample, by_id: dict[str, Episode]) -> None:
    ref = reference(replay, sample, by_id)
    for name, want in ref.items():
        got = getattr(sample, name)
        assert got.dtype == want.dtype and got.shape == want.shape, (name, got.dtype, got.shape)
        np.testing.assert_array_equal(got, want, err_msg=name)


def fill(replay: ChunkReplay, episodes: list[Episode]) -> dict[str, Episode]:
    for ep in episodes:
        assert replay.insert_episode(ep) == ep.num_steps
    return {ep.episode_id: ep for ep in episodes}


def mixed_episodes() -> list[Episode]:
    """Varied lengths (1 .. SEQ), terminated and truncated ends, demos and augmented copies of them."""
    eps = []
    lengths = [1, 2, 3, 4, 5, 7, 9, 12, 16, 20, 23, SEQ]
    for k, T in enumerate(lengths):
        eps.append(make_episode(T, seed=k, terminated=k % 2 == 0))
    eps.append(make_episode(6, seed=100, eid="demo-0", demo=True))
    eps.append(make_episode(6, seed=101, eid="demo-0-c0", source="demo-0"))
    eps.append(make_episode(SEQ, seed=102, eid="demo-1", demo=True, terminated=False))
    eps.append(make_episode(SEQ, seed=103, eid="demo-1-c0", source="demo-1", terminated=False))
    return eps


def state_arrays_equal(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], np.ndarray):
            np.testing.assert_array_equal(a[key], np.asarray(b[key]), err_msg=key)
            assert a[key].dtype == np.asarray(b[key]).dtype, key
        else:
            assert a[key] == b[key], key


# ------------------------------------------------------------------------------ window contents


@pytest.mark.parametrize("length", [1, 6, 10, SEQ + 1])
def test_windows_equal_a_per_episode_loop(length):
    replay = ChunkReplay(2_000, seq_len=SEQ, seed=SEED)
    by_id = fill(replay, mixed_episodes())
    rng = np.random.default_rng(SEED + length)
    for demo_fraction in (0.0, 0.5):
        sample = replay.sample_chunks(96, length, rng, demo_fraction=demo_fraction)
        assert sample.images.shape == (96, length, 3, SIZE, SIZE) and sample.images.dtype == np.uint8
        assert sample.episode_index.dtype == np.int64 and sample.start.dtype == np.int64
        assert_matches_reference(replay, sample, by_id)


def test_step_convention_is_first_discounts_and_padding():
    replay = ChunkReplay(2_000, seq_len=SEQ, seed=SEED)
    by_id = fill(replay, mixed_episodes())
    sample = replay.sample_chunks(4_000, 8, np.random.default_rng(1))
    T = np.array([by_id[replay.episode_info(int(i))["episode_id"]].num_steps for i in sample.episode_index])
    term = np.array(
        [by_id[replay.episode_info(int(i))["episode_id"]].terminated[-1] for i in sample.episode_index]
    )
    row = sample.start[:, None] + np.arange(8)
    np.testing.assert_array_equal(sample.mask, row <= T[:, None])
    # is_first exactly at row 0, which only a window starting there holds, at its position 0
    np.testing.assert_array_equal(sample.is_first, row == 0)
    assert not sample.is_first[:, 1:].any() and sample.is_first[:, 0].any()
    # discount 0 exactly at the terminal row of a terminated episode; never for a truncated one
    np.testing.assert_array_equal(sample.discounts == 0, ~sample.mask | ((row == T[:, None]) & term[:, None]))
    assert (sample.discounts[~term][sample.mask[~term]] == 1).all()
    assert ((row == T[:, None]) & term[:, None]).any() and ((row == T[:, None]) & ~term[:, None]).any()
    # nothing arrives with an episode's first observation, and padding is all zero
    first = sample.is_first
    assert not sample.actions[first].any() and not sample.rewards[first].any()
    pad = ~sample.mask
    assert pad.any()
    assert not sample.images[pad].any() and not sample.actions[pad].any() and not sample.rewards[pad].any()
    assert not sample.handover[pad].any() and not sample.is_first[pad].any()
    # a window covers the episode's last row or starts at row 0 when the episode is shorter than it
    assert (sample.start[T + 1 < 8] == 0).all()


def test_window_starts_are_uniform_over_the_valid_range():
    replay = ChunkReplay(200, seq_len=SEQ, seed=SEED)
    fill(replay, [make_episode(10, seed=1)])
    start = replay.sample_chunks(8_000, 4, np.random.default_rng(3)).start
    counts = np.bincount(start, minlength=8)
    assert start.min() == 0 and start.max() == 7 and counts.size == 8  # 0 .. T + 1 - L
    expected = 8_000 / 8
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected * (1 - 1 / 8))), counts
    assert (replay.sample_chunks(50, 11, np.random.default_rng(4)).start == 0).all()  # T + 1 == L
    assert (replay.sample_chunks(50, SEQ + 1, np.random.default_rng(4)).start == 0).all()


def test_action_feature_is_that_of_the_action_into_the_row():
    replay = ChunkReplay(200, seq_len=SEQ, seed=SEED)
    jaw = np.array([1.0, -1.0, -1.0, 0.0, 1.0, -1.0])  # close, stay, open (0 is open), stay, close
    ep = make_episode(6, seed=5, jaw=jaw)
    fill(replay, [ep])
    sample = replay.sample_chunks(3, 7, np.random.default_rng(0))
    np.testing.assert_array_equal(sample.actions[:, :, TOGGLE], [[0, 0, 1, 0, 1, 0, 1]] * 3)
    np.testing.assert_array_equal(sample.actions[:, 1:, 1:], np.broadcast_to(ep.actions[:, 1:], (3, 6, 4)))
    np.testing.assert_array_equal(sample.rewards[:, 1:], np.broadcast_to(ep.rewards, (3, 6)))
    assert not sample.actions[:, 0].any()
    # the replay's action rows hold features, in its checkpoints too
    np.testing.assert_array_equal(replay.state_dict()["actions"][:, TOGGLE], [0, 1, 0, 1, 0, 1])


def test_a_surgical_rollout_ends_with_the_close_toggle_at_its_terminal_row():
    ep = synthetic_surgical_episode(7)
    T = ep.num_steps
    assert T + 1 <= 80
    replay = ChunkReplay(1_000, seed=SEED)  # the task's configuration: seq_len 80, 64 x 64
    by_id = fill(replay, [ep])
    sample = replay.sample_chunks(1, T + 1, np.random.default_rng(0))
    assert_matches_reference(replay, sample, by_id)
    toggle = sample.actions[0, :, TOGGLE]
    assert toggle[T] == 1 and not toggle[:T].any()  # the jaw stayed open until the grasp
    assert sample.discounts[0, T] == 0 and (sample.discounts[0, :T] == 1).all()
    assert sample.rewards[0, T] == 1.0
    controller = np.array([decode_state_rows(im)[2] for im in ep.images])
    np.testing.assert_array_equal(sample.handover[0], controller == 0)
    assert sample.handover[0].any() and not sample.handover[0].all()  # P-controller, then the policy
    assert sample.demo[0] == 1.0
    padded = replay.sample_chunks(2, 81, np.random.default_rng(1))
    assert padded.mask[:, : T + 1].all() and not padded.mask[:, T + 1 :].any()
    assert_matches_reference(replay, padded, by_id)


# ------------------------------------------------------------------------------ draws


@pytest.mark.parametrize(("fraction", "successes"), [(0.0, False), (0.25, False), (0.5, True), (1.0, False)])
def test_episodes_are_drawn_as_sequence_replay_draws_them(fraction, successes):
    replay = ChunkReplay(2_000, seq_len=SEQ, seed=SEED)
    fill(replay, mixed_episodes())
    a, b = np.random.default_rng(9), np.random.default_rng(9)
    for _ in range(5):
        ref = SequenceReplay.sample(replay, 16, a, demo_fraction=fraction, successes_as_demos=successes)
        sample = replay.sample_chunks(16, 5, b, demo_fraction=fraction, successes_as_demos=successes)
        np.testing.assert_array_equal(sample.episode_index, ref.episode_index)
        np.testing.assert_array_equal(sample.demo, ref.from_demo_set.astype(np.float32))
        # then one draw of the starts, uniform in [0, max(0, T + 1 - L)]
        np.testing.assert_array_equal(sample.start, a.integers(0, np.maximum(ref.lengths + 1 - 5, 0) + 1))
        if fraction:
            assert sample.demo.sum() == round(fraction * 16)
        assert a.bit_generator.state == b.bit_generator.state


def test_default_generator_is_the_seeded_one():
    one, two = (ChunkReplay(2_000, seq_len=SEQ, seed=SEED) for _ in range(2))
    eps = mixed_episodes()
    fill(one, eps), fill(two, eps)
    for _ in range(3):
        x, y = one.sample_chunks(8, 6), two.sample_chunks(8, 6)
        np.testing.assert_array_equal(x.episode_index, y.episode_index)
        np.testing.assert_array_equal(x.start, y.start)


# ------------------------------------------------------------------------------ checkpoints


def torch_round_trip(state: dict) -> dict:
    buf = io.BytesIO()
    torch.save(_to_torch(state), buf)
    buf.seek(0)
    return _to_numpy(torch.load(buf, weights_only=True))


def test_checkpoint_round_trip_reproduces_windows_and_the_controller_state():
    replay = ChunkReplay(2_000, seq_len=SEQ, seed=SEED)
    eps = mixed_episodes()
    by_id = fill(replay, eps)
    replay.sample_chunks(8, 6)  # advance the default generator before saving
    state = replay.state_dict()
    np.testing.assert_array_equal(
        state["state"][:, 0], np.concatenate([[decode_state_rows(im)[2] for im in ep.images] for ep in eps])
    )
    loaded = torch_round_trip(state)
    restored = ChunkReplay.from_state_dict(loaded)
    other = ChunkReplay(2_000, seq_len=SEQ, seed=0)
    other.load_state_dict(loaded)
    state_arrays_equal(state, restored.state_dict())
    state_arrays_equal(state, other.state_dict())
    assert restored.nbytes == replay.nbytes
    for r in (restored, other):  # the saved default generator
        x, y = replay.sample_chunks(32, 7), r.sample_chunks(32, 7)
        for f in dataclasses.fields(ChunkSample):
            np.testing.assert_array_equal(getattr(x, f.name), getattr(y, f.name), err_msg=f.name)
        replay.load_state_dict(state)  # rewind the original's generator for the next copy
    rng_a, rng_b = np.random.default_rng(5), np.random.default_rng(5)  # an explicit generator
    x = replay.sample_chunks(32, 9, rng_a, demo_fraction=0.5)
    y = restored.sample_chunks(32, 9, rng_b, demo_fraction=0.5)
    for f in dataclasses.fields(ChunkSample):
        np.testing.assert_array_equal(getattr(x, f.name), getattr(y, f.name), err_msg=f.name)
    assert_matches_reference(restored, y, by_id)
    # a plain SequenceReplay of another configuration refuses the state
    with pytest.raises(ValueError):
        SequenceReplay(2_000, image_size=SIZE, seq_len=SEQ).load_state_dict(loaded)


# ------------------------------------------------------------------------------ inserts


def _no_images(ep):
    return dataclasses.replace(ep, images=None)


def _float_images(ep):
    return dataclasses.replace(ep, images=ep.images.astype(np.float32))


def _small_images(ep):
    return dataclasses.replace(ep, images=np.ascontiguousarray(ep.images[:, :, :32, :32]))


def _two_channels(ep):
    return dataclasses.replace(ep, images=np.ascontiguousarray(ep.images[:, :2]))


def _one_image_short(ep):
    return dataclasses.replace(ep, images=np.ascontiguousarray(ep.images[:-1]))


def _block_not_constant(ep):
    images = ep.images.copy()
    start, stop = state_blocks(SIZE)[2]
    images[3, 2, -1, start:stop] = 255
    images[3, 2, -1, stop - 1] = 0  # the controller block holds two codes
    return dataclasses.replace(ep, images=images)


def _invalid_code(ep):
    images = ep.images.copy()
    start, stop = state_blocks(SIZE)[1]
    images[4, 2, -1, start:stop] = 7  # not 51 * fsm_state
    return dataclasses.replace(ep, images=images)


def _too_long(_ep):
    return make_episode(SEQ + 1, seed=77, eid="ep-new")


@pytest.mark.parametrize(
    ("corrupt", "match"),
    [
        (_no_images, "images: None"),
        (_float_images, "images: dtype must be uint8"),
        (_small_images, "images: expected shape"),
        (_two_channels, "images: expected shape"),
        (_one_image_short, "images: expected shape"),
        (_block_not_constant, "images: observation 3 has a corrupted state row.*controller_state"),
        (_invalid_code, "images: observation 4 has a corrupted state row.*fsm_state"),
        (_too_long, "actions: episode has 25 steps, more than seq_len=24"),
    ],
)
def test_refused_inserts_name_the_field_and_leave_the_replay_unchanged(corrupt, match):
    replay = ChunkReplay(60, seq_len=SEQ, seed=SEED)  # full: a valid insert of ep would evict
    fill(replay, [make_episode(20, seed=1), make_episode(20, seed=2, demo=True), make_episode(15, seed=3)])
    before = replay.state_dict()
    ep = make_episode(8, seed=77, eid="ep-new")
    with pytest.raises(ValueError, match=match):
        replay.insert_episode(corrupt(ep))
    state_arrays_equal(before, replay.state_dict())
    assert replay.stats() == ChunkReplay.from_state_dict(before).stats()
    assert replay.insert_episode(ep) == 8  # the id was not taken by the refused insert
    with pytest.raises(ValueError, match="duplicate"):
        replay.insert_episode(ep)


def test_eviction_keeps_demos_and_their_copies_and_windows_stay_exact():
    replay = ChunkReplay(100, seq_len=SEQ, max_episodes=12, seed=SEED)
    demos = [
        make_episode(10, seed=1, eid="demo-a", demo=True),
        make_episode(5, seed=2, eid="demo-a-c0", source="demo-a"),
        make_episode(7, seed=3, eid="demo-b", demo=True, terminated=False),
    ]
    by_id = fill(replay, demos)
    online = [
        make_episode(int(T), seed=10 + k, terminated=k % 3 > 0) for k, T in enumerate([SEQ, 19, 3, 11] * 5)
    ]
    for ep in online:  # long episodes evicted, their rows reused by shorter ones
        by_id.update(fill(replay, [ep]))
    ids = replay.episode_ids()
    assert ids[:3] == ["demo-a", "demo-a-c0", "demo-b"]
    assert replay.stats()["demo_transitions"] == 22 and replay.stats()["evicted_episodes"] > 0
    assert len(replay) <= 100 and replay.num_episodes <= 12
    kept = [ep.episode_id for ep in online if ep.episode_id in ids]
    assert kept == [ep.episode_id for ep in online][-len(kept) :]  # FIFO: the newest survive
    rng = np.random.default_rng(11)
    for length in (4, SEQ + 1):
        assert_matches_reference(replay, replay.sample_chunks(128, length, rng), by_id)
        split = replay.sample_chunks(128, length, rng, demo_fraction=0.25)
        assert split.demo.sum() == 32
        assert_matches_reference(replay, split, by_id)


# ------------------------------------------------------------------------------ batch and sizes


def test_to_chunk_batch_converts_without_changing_anything():
    replay = ChunkReplay(2_000, seq_len=SEQ, seed=SEED)
    fill(replay, mixed_episodes())
    sample = replay.sample_chunks(16, 6, np.random.default_rng(2), demo_fraction=0.5)
    batch = to_chunk_batch(sample)
    assert isinstance(batch, ChunkBatch) and batch.shape == (16, 6)
    assert batch.images.dtype == torch.float32 and batch.images.shape == (16, 6, 3, SIZE, SIZE)
    np.testing.assert_array_equal(batch.images.numpy(), image_format.decode(sample.images))
    assert batch.images.max() <= 1.0 and batch.images.min() >= 0.0
    for f in dataclasses.fields(ChunkBatch):
        if f.name != "images":
            got = getattr(batch, f.name)
            np.testing.assert_array_equal(got.numpy(), getattr(sample, f.name), err_msg=f.name)
    assert batch.discounts.dtype == torch.float32 and batch.demo.dtype == torch.float32
    assert batch.is_first.dtype == batch.handover.dtype == batch.mask.dtype == torch.bool


def test_reserved_bytes_are_what_the_arrays_hold():
    replay = ChunkReplay(500, seq_len=SEQ, max_episodes=40)
    assert ChunkReplay.reserved_bytes(500, seq_len=SEQ, max_episodes=40) == replay.nbytes
    full = ChunkReplay(300)
    assert ChunkReplay.reserved_bytes(300) == full.nbytes
    rows = 300 + 75 + 1  # capacity + default max_episodes (ceil(300 / 4)) + the zero row
    assert full.nbytes > rows * 3 * 64 * 64
    assert (full.channels, full.constant_channels, full.state_dim, full.seq_len) == (3, (), 1, 80)


def test_bad_sample_arguments_are_refused():
    empty = ChunkReplay(100, seq_len=SEQ)
    with pytest.raises(ValueError, match="empty"):
        empty.sample_chunks(2, 3)
    fill(empty, [make_episode(3, seed=0)])
    for kwargs in ({"batch_size": 0, "length": 3}, {"batch_size": 2, "length": 0}):
        with pytest.raises(ValueError):
            empty.sample_chunks(**kwargs)
    with pytest.raises(ValueError, match="length"):
        empty.sample_chunks(2, SEQ + 2)
    with pytest.raises(ValueError, match="demo_fraction"):
        empty.sample_chunks(2, 3, demo_fraction=1.5)
