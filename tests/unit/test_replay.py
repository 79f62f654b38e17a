"""SequenceReplay as math: bit-exact round trips, vectorised gather vs a loop, FIFO with pinned demos.

Episodes come from ``tests.helpers.build_episode`` with policy images attached: channel 0 random
depth codes, channel 1 the jaw code tiled over the image (as ``quantized_observations`` makes it).
"""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest

from proto.episode import Augmentation, Episode
from services.algorithms.replay import SequenceReplay, public_reference_bytes
from services.algorithms.replay_batch import SequenceBatch
from tests.helpers import build_episode

pytestmark = pytest.mark.unit

SIZE = 8
SEQ_LEN = 12
SEED = 1234


def make_episode(
    T: int,
    seed: int,
    *,
    eid: str | None = None,
    demo: bool = False,
    kind: str | None = None,
    source: str | None = None,
    validate: bool = False,
) -> Episode:
    """A raw (or augmented, with ``kind``/``source``) episode with 2-channel uint8 policy images."""
    ep = build_episode(T=T, seed=seed, P=2, truncated=bool(seed % 2), validate=False)
    rng = np.random.default_rng(seed + 10_000)
    images = np.empty((T + 1, 2, SIZE, SIZE), np.uint8)
    images[:, 0] = rng.integers(0, 256, (T + 1, SIZE, SIZE), dtype=np.uint8)
    images[:, 1] = np.rint(ep.jaw * 255.0).astype(np.uint8)[:, None, None]
    aug = None
    if kind is not None:
        aug = Augmentation(
            source_episode_id=source, kind=kind, seed=seed, copy_index=0, phase_split=0, params={}
        )
    ep = dataclasses.replace(
        ep, episode_id=eid or f"ep-{seed}", is_demo=demo, images=images, augmentation=aug
    )
    return Episode.from_wire(ep.to_wire()) if validate else ep


def make_replay(capacity: int = 200, max_episodes: int | None = None, seed: int = SEED) -> SequenceReplay:
    return SequenceReplay(capacity, image_size=SIZE, seq_len=SEQ_LEN, max_episodes=max_episodes, seed=seed)


def loop_reference(
    replay: SequenceReplay, batch: SequenceBatch, by_id: dict[str, Episode]
) -> dict[str, np.ndarray]:
    """The batch rebuilt step by step from the original episodes (the slow, obvious way)."""
    B, L = batch.batch_size, replay.seq_len
    ref = {
        "images": np.zeros((B, L + 1, 2, SIZE, SIZE), np.uint8),
        "actions": np.zeros((B, L, 5), np.float32),
        "rewards": np.zeros((B, L), np.float32),
        "terminated": np.zeros((B, L), bool),
        "truncated": np.zeros((B, L), bool),
        "mask": np.zeros((B, L), bool),
        "obs_mask": np.zeros((B, L + 1), bool),
        "lengths": np.zeros(B, np.int64),
        "is_demo": np.zeros(B, bool),
    }
    for b in range(B):
        info = replay.episode_info(int(batch.episode_index[b]))
        ep = by_id[info["episode_id"]]
        ref["lengths"][b] = ep.num_steps
        ref["is_demo"][b] = info["is_demo"]
        for t in range(ep.num_steps + 1):
            ref["images"][b, t] = ep.images[t]
            ref["obs_mask"][b, t] = True
        for t in range(ep.num_steps):
            ref["actions"][b, t] = ep.actions[t]
            ref["rewards"][b, t] = ep.rewards[t]
            ref["terminated"][b, t] = ep.terminated[t]
            ref["truncated"][b, t] = ep.truncated[t]
            ref["mask"][b, t] = True
    return ref


def assert_batch_matches(replay: SequenceReplay, batch: SequenceBatch, by_id: dict[str, Episode]) -> None:
    ref = loop_reference(replay, batch, by_id)
    np.testing.assert_array_equal(batch.images_uint8(), ref["images"])
    np.testing.assert_array_equal(batch.image_codes, ref["images"][:, :, [0]])
    np.testing.assert_array_equal(batch.constant, ref["images"][:, :, [1], 0, 0])
    for name in ("actions", "rewards", "terminated", "truncated", "mask", "obs_mask", "lengths", "is_demo"):
        np.testing.assert_array_equal(getattr(batch, name), ref[name], err_msg=name)


def assert_batches_equal(a: SequenceBatch, b: SequenceBatch) -> None:
    for f in dataclasses.fields(SequenceBatch):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name), err_msg=f.name)


# ------------------------------------------------------------------------------ round trip


def test_inserted_episodes_sample_back_bit_exact_with_zero_padding() -> None:
    replay = make_replay()
    lengths = [1, 5, SEQ_LEN, 7]
    eps = [make_episode(T, seed=i, validate=True) for i, T in enumerate(lengths)]
    assert [replay.insert(ep) for ep in eps] == lengths
    assert len(replay) == sum(lengths) and replay.num_episodes == 4

    batch = replay.sample(64, rng=np.random.default_rng(SEED))
    B, L = 64, SEQ_LEN
    assert batch.image_codes.shape == (B, L + 1, 1, SIZE, SIZE) and batch.image_codes.dtype == np.uint8
    assert batch.constant.shape == (B, L + 1, 1) and batch.constant.dtype == np.uint8
    assert batch.images_uint8().shape == (B, L + 1, 2, SIZE, SIZE)
    assert batch.actions.shape == (B, L, 5) and batch.actions.dtype == np.float32
    assert batch.rewards.dtype == np.float32 and batch.terminated.dtype == bool and batch.mask.dtype == bool
    assert batch.obs_mask.shape == (B, L + 1)

    by_id = {ep.episode_id: ep for ep in eps}
    sampled_ids = {replay.episode_info(int(i))["episode_id"] for i in batch.episode_index}
    assert sampled_ids == set(by_id), "64 draws over 4 episodes should hit each one"
    images = batch.images_uint8()
    for b in range(B):
        ep = by_id[replay.episode_info(int(batch.episode_index[b]))["episode_id"]]
        T = ep.num_steps
        assert batch.lengths[b] == T
        np.testing.assert_array_equal(images[b, : T + 1], ep.images)
        assert not images[b, T + 1 :].any()
        np.testing.assert_array_equal(batch.actions[b, :T], ep.actions)
        np.testing.assert_array_equal(batch.rewards[b, :T], ep.rewards)
        np.testing.assert_array_equal(batch.terminated[b, :T], ep.terminated)
        np.testing.assert_array_equal(batch.truncated[b, :T], ep.truncated)
        assert not batch.actions[b, T:].any() and not batch.rewards[b, T:].any()
        assert not batch.terminated[b, T:].any() and not batch.truncated[b, T:].any()
        np.testing.assert_array_equal(batch.mask[b], np.arange(L) < T)
        np.testing.assert_array_equal(batch.obs_mask[b], np.arange(L + 1) <= T)


def test_sample_draws_episodes_uniformly() -> None:
    replay = make_replay()
    for i, T in enumerate([1, SEQ_LEN, 3]):  # uniform over episodes, not over transitions
        replay.insert(make_episode(T, seed=i))
    counts = np.bincount(replay.sample(30_000, rng=np.random.default_rng(SEED)).episode_index, minlength=3)
    np.testing.assert_allclose(counts / counts.sum(), 1 / 3, atol=0.015)


def test_sampling_from_an_empty_replay_raises() -> None:
    with pytest.raises(ValueError, match="empty"):
        make_replay().sample(4)


# ------------------------------------------------------------------------------ eviction


def fifo_model_insert(model: list[tuple[str, int, bool]], ep: Episode, capacity: int, max_eps: int) -> bool:
    """Reference policy on a python list: returns False where the replay must raise."""
    raw_demo_ids = {eid for eid, _, demo in model if demo and not eid.startswith("aug")}
    aug = ep.augmentation
    demo = ep.is_demo or (aug is not None and aug.source_episode_id in raw_demo_ids)
    demo_t = sum(T for _, T, d in model if d)
    if demo_t + ep.num_steps > capacity or sum(d for *_, d in model) + 1 > max_eps:
        return False
    while sum(T for _, T, _ in model) + ep.num_steps > capacity or len(model) + 1 > max_eps:
        model.pop(next(i for i, (_, _, d) in enumerate(model) if not d))
    model.append((ep.episode_id, ep.num_steps, demo))
    return True


def test_fifo_eviction_keeps_demos_and_their_copies_and_matches_a_loop_reference() -> None:
    capacity, max_eps = 150, 24
    replay = make_replay(capacity, max_episodes=max_eps)
    rng = np.random.default_rng(SEED)
    model: list[tuple[str, int, bool]] = []
    by_id: dict[str, Episode] = {}
    raw_demos: list[str] = []
    rejected = evicted_before = 0
    for i in range(250):
        T = int(rng.integers(1, SEQ_LEN + 1))
        u = rng.random()
        if u < 0.04:
            ep = make_episode(T, seed=i, eid=f"demo-{i}", demo=True)
            raw_demos.append(ep.episode_id)
        elif u < 0.08 and raw_demos:  # augmented copy of a demo; is_demo copied from the source
            ep = make_episode(T, seed=i, eid=f"aug-{i}", demo=True, kind="isometric", source=raw_demos[-1])
        elif u < 0.10 and raw_demos:  # is_demo lost on the way: the source id still pins it
            ep = make_episode(T, seed=i, eid=f"aug-{i}", kind="mea", source=raw_demos[0])
        elif u < 0.3:  # augmented copy of a non-demo: evictable
            ep = make_episode(T, seed=i, eid=f"aug-{i}", kind="mea+isometric", source=f"ep-{i - 1}")
        else:
            ep = make_episode(T, seed=i, eid=f"ep-{i}")
        by_id[ep.episode_id] = ep
        if fifo_model_insert(model, ep, capacity, max_eps):
            assert replay.insert(ep) == T
        else:
            rejected += 1
            with pytest.raises(ValueError, match="does not fit"):
                replay.insert(ep)
        assert replay.episode_ids() == [eid for eid, _, _ in model]
        assert len(replay) == sum(T for _, T, _ in model) <= capacity
        assert replay.num_episodes <= max_eps
        evicted_before = replay.stats()["evicted_episodes"]
    assert evicted_before > 100 and rejected > 0, "the sequence should exercise eviction and rejection"
    stats = replay.stats()
    assert stats["demo_transitions"] == sum(T for _, T, d in model if d)
    assert stats["demo_episodes"] == sum(d for *_, d in model) > 3

    batch = replay.sample(256, rng=np.random.default_rng(SEED + 1))
    assert_batch_matches(replay, batch, by_id)


def test_eviction_is_oldest_first() -> None:
    replay = make_replay(capacity=30, max_episodes=10)
    for i in range(6):
        replay.insert(make_episode(5, seed=i))
    assert len(replay) == 30
    replay.insert(make_episode(5, seed=6))
    assert replay.episode_ids() == [f"ep-{i}" for i in range(1, 7)]
    replay.insert(make_episode(12, seed=7))  # needs 12: evicts three of 5
    assert replay.episode_ids() == ["ep-4", "ep-5", "ep-6", "ep-7"] and len(replay) == 27


def test_episode_table_limit_evicts_by_count() -> None:
    replay = make_replay(capacity=100, max_episodes=3)
    for i in range(5):
        replay.insert(make_episode(1, seed=i))
    assert replay.episode_ids() == ["ep-2", "ep-3", "ep-4"] and len(replay) == 3


def test_demos_exceeding_capacity_raise_and_leave_the_buffer_unchanged() -> None:
    replay = make_replay(capacity=10, max_episodes=4)
    replay.insert(make_episode(6, seed=0, eid="demo-0", demo=True))
    replay.insert(make_episode(4, seed=1))
    with pytest.raises(ValueError, match="demonstration 'demo-2'.*never evicted"):
        replay.insert(make_episode(5, seed=2, eid="demo-2", demo=True))
    with pytest.raises(ValueError, match="episode 'ep-3'"):  # a non-demo that cannot fit beside the demos
        replay.insert(make_episode(5, seed=3))
    assert replay.episode_ids() == ["demo-0", "ep-1"] and len(replay) == 10
    replay.insert(make_episode(4, seed=4, eid="demo-4", demo=True))  # fits once ep-1 is evicted
    assert replay.episode_ids() == ["demo-0", "demo-4"]


def test_stats_count_transitions_by_provenance() -> None:
    replay = make_replay()
    replay.insert(make_episode(3, seed=0, eid="demo-0", demo=True))
    replay.insert(make_episode(4, seed=1, eid="aug-1", demo=True, kind="mea", source="demo-0"))
    replay.insert(make_episode(5, seed=2))
    replay.insert(make_episode(6, seed=3, eid="aug-3", kind="isometric", source="ep-2"))
    replay.insert(make_episode(7, seed=4, eid="aug-4", kind="isometric", source="ep-2"))
    stats = replay.stats()
    assert stats["transitions"] == 25 and stats["episodes"] == 5
    assert stats["demo_transitions"] == 7 and stats["demo_episodes"] == 2
    assert stats["raw_transitions"] == 8 and stats["augmented_transitions"] == 17
    assert stats["augmented_transitions_by_kind"] == {"mea": 4, "isometric": 13}
    info = replay.episode_info(3)
    assert info == {
        "episode_id": "aug-3",
        "source_episode_id": "ep-2",
        "kind": "isometric",
        "is_demo": False,
        "length": 6,
    }


# ------------------------------------------------------------------------------ bad input


def _bad_episodes() -> list[tuple[str, Episode, str]]:
    ep = make_episode(4, seed=99, eid="bad")
    jaw_varies = ep.images.copy()
    jaw_varies[2, 1, 3, 3] ^= 1
    return [
        ("images None", dataclasses.replace(ep, images=None), "images: None"),
        (
            "uint16",
            dataclasses.replace(ep, images=ep.images.astype(np.uint16)),
            "images: dtype must be uint8",
        ),
        ("float32", dataclasses.replace(ep, images=ep.images.astype(np.float32)), "images: dtype"),
        (
            "3 channels",
            dataclasses.replace(ep, images=np.zeros((5, 3, SIZE, SIZE), np.uint8)),
            "images: expected shape",
        ),
        (
            "wrong size",
            dataclasses.replace(ep, images=np.zeros((5, 2, 16, 16), np.uint8)),
            "images: expected shape",
        ),
        ("T rows", dataclasses.replace(ep, images=ep.images[:4]), "images: expected shape"),
        ("jaw varies", dataclasses.replace(ep, images=jaw_varies), "images: channel 1 .* varies in frame 2"),
        ("too long", make_episode(SEQ_LEN + 1, seed=98), "actions: .*more than seq_len"),
        ("rewards", dataclasses.replace(ep, rewards=ep.rewards[:3]), "rewards: expected shape"),
        ("actions", dataclasses.replace(ep, actions=ep.actions[:, :4]), "actions: expected shape"),
    ]


@pytest.mark.parametrize(("case", "ep", "message"), _bad_episodes(), ids=[c for c, _, _ in _bad_episodes()])
def test_bad_episode_raises_naming_the_field_and_leaves_the_buffer_unchanged(
    case: str, ep: Episode, message: str
) -> None:
    replay = make_replay(capacity=20)
    for i in range(5):  # full: a valid insert would evict
        replay.insert(make_episode(4, seed=i))
    before = replay.state_dict()
    with pytest.raises(ValueError, match=message):
        replay.insert(ep)
    after = replay.state_dict()
    assert before.keys() == after.keys()
    for key in before:
        np.testing.assert_array_equal(np.asarray(before[key]), np.asarray(after[key]), err_msg=key)


def test_constructor_rejects_bad_configuration() -> None:
    with pytest.raises(ValueError, match="capacity_transitions"):
        SequenceReplay(0)
    with pytest.raises(ValueError, match="constant_channels"):
        SequenceReplay(10, constant_channels=(2,))
    with pytest.raises(ValueError, match="max_episodes"):
        SequenceReplay(10, max_episodes=0)


# ------------------------------------------------------------------------------ checkpoints


def _filled_after_wraparound(seed: int = SEED) -> tuple[SequenceReplay, dict[str, Episode]]:
    replay = make_replay(capacity=60, max_episodes=12, seed=seed)
    rng = np.random.default_rng(seed)
    by_id = {}
    for i in range(40):
        T = int(rng.integers(1, SEQ_LEN + 1))
        demo = i in (3, 17)
        ep = make_episode(T, seed=i, eid=f"demo-{i}" if demo else None, demo=demo)
        by_id[ep.episode_id] = ep
        replay.insert(ep)
    assert replay.stats()["evicted_episodes"] > 10
    return replay, by_id


def _weights_only_round_trip(state: dict) -> dict:
    """What the learner's checkpoint does: arrays to tensors, torch.save, torch.load(weights_only=True)."""
    import torch

    as_tensors = {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in state.items()}
    buf = io.BytesIO()
    torch.save(as_tensors, buf)
    buf.seek(0)
    return torch.load(buf, weights_only=True)


def test_state_dict_holds_only_plain_values() -> None:
    replay, _ = _filled_after_wraparound()
    for key, value in replay.state_dict().items():
        if isinstance(value, list):
            assert all(isinstance(v, str | int) for v in value), key
        else:
            assert isinstance(value, np.ndarray | int | float | str), key


def test_state_dict_round_trip_reproduces_samples_and_later_evictions() -> None:
    replay, by_id = _filled_after_wraparound()
    restored = SequenceReplay.from_state_dict(_weights_only_round_trip(replay.state_dict()))
    assert restored.episode_ids() == replay.episode_ids() and len(restored) == len(replay)
    assert restored.stats() == replay.stats()
    for seed in (0, 1):
        assert_batches_equal(
            replay.sample(16, np.random.default_rng(seed)), restored.sample(16, np.random.default_rng(seed))
        )
    assert_batches_equal(replay.sample(16), restored.sample(16))  # the default generator's state travels too
    for i in range(100, 110):
        ep = make_episode(1 + i % SEQ_LEN, seed=i)
        by_id[ep.episode_id] = ep
        replay.insert(ep)
        restored.insert(ep)
    assert restored.episode_ids() == replay.episode_ids()
    batch = restored.sample(32, np.random.default_rng(5))
    assert_batches_equal(replay.sample(32, np.random.default_rng(5)), batch)
    assert_batch_matches(restored, batch, by_id)


def test_load_state_dict_rejects_another_configuration() -> None:
    replay, _ = _filled_after_wraparound()
    other = SequenceReplay(61, image_size=SIZE, seq_len=SEQ_LEN, max_episodes=12)
    with pytest.raises(ValueError, match="configuration"):
        other.load_state_dict(replay.state_dict())


# ------------------------------------------------------------------------------ memory


def test_reserved_bytes_for_1e5_transitions_is_ten_times_below_the_public_code() -> None:
    ours = SequenceReplay.reserved_bytes(100_000, image_size=84, seq_len=50)
    public = public_reference_bytes(100_000)
    assert public == 100_000 * 2 * 2 * 84 * 84 * 4  # float32 obs and next_obs, (2, 84, 84) each
    assert ours <= public / 10
    assert ours <= 1.05e9


@pytest.mark.parametrize(
    ("capacity", "size", "seq_len", "max_episodes"), [(200, 8, 12, None), (37, 5, 3, 9), (1000, 16, 50, 20)]
)
def test_nbytes_equals_reserved_bytes(
    capacity: int, size: int, seq_len: int, max_episodes: int | None
) -> None:
    replay = SequenceReplay(capacity, image_size=size, seq_len=seq_len, max_episodes=max_episodes)
    assert replay.nbytes == SequenceReplay.reserved_bytes(capacity, size, seq_len, max_episodes=max_episodes)
    rows = capacity + replay.max_episodes + 1
    assert replay.nbytes >= rows * size * size  # at least the depth codes of every observation row


# ------------------------------------------------------------------------------ privileged state


def _with_state(ep: Episode, dim: int) -> np.ndarray:
    """Rows that name their episode and step, so a gather from the wrong row shows."""
    T = ep.num_steps
    seed = int(ep.episode_id.split("-")[-1])
    return (seed * 1000 + np.arange(T + 1)[:, None] + np.arange(dim)[None] / 100).astype(np.float32)


def test_privileged_state_samples_back_beside_its_observations_and_survives_a_checkpoint() -> None:
    dim = 3
    replay = SequenceReplay(200, image_size=SIZE, seq_len=SEQ_LEN, seed=SEED, state_dim=dim)
    eps = {}
    for i in range(30):  # wraps around: evicted rows are reused
        ep = make_episode(1 + i % SEQ_LEN, seed=i)
        eps[ep.episode_id] = ep
        replay.insert(ep, _with_state(ep, dim))
    batch = replay.sample(16, np.random.default_rng(0))
    assert batch.state.shape == (16, SEQ_LEN + 1, dim) and batch.state.dtype == np.float32
    for b in range(16):
        ep = eps[replay.episode_info(int(batch.episode_index[b]))["episode_id"]]
        expected = _with_state(ep, dim)
        np.testing.assert_array_equal(batch.state[b, : len(expected)], expected)
        np.testing.assert_array_equal(batch.state[b, len(expected) :], 0.0)  # padding reads the zero row
    restored = SequenceReplay.from_state_dict(_weights_only_round_trip(replay.state_dict()))
    assert restored.state_dim == dim
    assert_batches_equal(
        replay.sample(16, np.random.default_rng(1)), restored.sample(16, np.random.default_rng(1))
    )
    plain = SequenceReplay(200, image_size=SIZE, seq_len=SEQ_LEN, seed=SEED)
    with pytest.raises(ValueError, match="state_dim"):
        plain.load_state_dict(replay.state_dict())


@pytest.mark.parametrize(
    ("state_dim", "rows"),
    [(0, "given"), (3, None), (3, "short"), (3, "wide"), (3, "nan")],
)
def test_privileged_state_that_does_not_fit_is_refused_and_leaves_the_buffer_unchanged(
    state_dim, rows
) -> None:
    replay = SequenceReplay(200, image_size=SIZE, seq_len=SEQ_LEN, seed=SEED, state_dim=state_dim)
    ep = make_episode(5, seed=1)
    state = {
        "given": np.zeros((6, 3), np.float32),
        None: None,
        "short": np.zeros((5, 3), np.float32),
        "wide": np.zeros((6, 4), np.float32),
        "nan": np.full((6, 3), np.nan, np.float32),
    }[rows]
    with pytest.raises(ValueError, match="state"):
        replay.insert(ep, state)
    assert len(replay) == 0 and replay.stats()["transitions"] == 0


def test_a_checkpoint_saved_before_privileged_state_existed_still_loads() -> None:
    replay, _ = _filled_after_wraparound()
    state = replay.state_dict()
    del state["state"], state["state_dim"]
    restored = SequenceReplay.from_state_dict(state)
    assert restored.state_dim == 0 and restored.episode_ids() == replay.episode_ids()
