"""Storage of the sequence replay: a preallocated arena of uint8 observation rows, inserts with
their validation, and eviction. Sampling and checkpoint state are ``replay.SequenceReplay``'s.

Design notes: docs/architecture-notes.md, services/algorithms/replay_storage.py."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from proto.actions import ACTION_DIM
from proto.episode import succeeded
from services.observation import image_format

if TYPE_CHECKING:
    from proto.episode import Episode

RAW_KIND = "raw"
"""Provenance kind of an episode without ``augmentation``."""
DEFAULT_STEPS_PER_EPISODE = 4
"""``max_episodes`` defaults to ``ceil(capacity / 4)``: room for episodes of 4+ steps on average."""


def _layout(
    capacity_transitions: int,
    image_size: int,
    seq_len: int,
    channels: int,
    constant_channels: Sequence[int],
    max_episodes: int,
    state_dim: int = 0,
) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shape and dtype of every preallocated array (one source for allocation and ``reserved_bytes``)."""
    rows = capacity_transitions + max_episodes + 1  # every episode's T+1 observations, + the zero row
    E, L, H = max_episodes, seq_len, image_size
    index = np.dtype(np.int32) if rows < 2**31 else np.dtype(np.int64)
    n_const = len(constant_channels)
    return {
        "codes": ((rows, channels - n_const, H, H), image_format.DTYPE),
        "constant": ((rows, n_const), image_format.DTYPE),
        "actions": ((rows, ACTION_DIM), np.dtype(np.float32)),
        "rewards": ((rows,), np.dtype(np.float32)),
        "terminated": ((rows,), np.dtype(np.bool_)),
        "truncated": ((rows,), np.dtype(np.bool_)),
        "state": ((rows, state_dim), np.dtype(np.float32)),
        "free_rows": ((rows - 1,), index),
        "ep_rows": ((E, L + 1), index),
        "ep_length": ((E,), np.dtype(np.int32)),
        "ep_serial": ((E,), np.dtype(np.int64)),
        "ep_demo": ((E,), np.dtype(np.bool_)),
        "ep_success": ((E,), np.dtype(np.bool_)),
        "ep_kind": ((E,), np.dtype(np.int16)),
        "free_slots": ((E,), np.dtype(np.int32)),
        "order": ((E,), np.dtype(np.int32)),
    }


def _default_max_episodes(capacity_transitions: int) -> int:
    return max(1, math.ceil(capacity_transitions / DEFAULT_STEPS_PER_EPISODE))


class ReplayStorage:
    """Whole-episode storage with a fixed memory budget; see docs/architecture-notes.md for the policy.

    Args:
        capacity_transitions: stored transitions at most (raw and augmented copies alike).
        image_size: H = W of the policy images.
        seq_len: longest episode accepted, and the padded length of sampled sequences.
        constant_channels: channels constant over each image (the tiled jaw code), stored as one byte.
        channels: channels of the policy image.
        max_episodes: stored episodes at most (default ``ceil(capacity / 4)``).
        seed: seed of the generator ``SequenceReplay.sample`` uses when given no ``rng`` (its state
            is saved with the contents).
        state_dim: privileged state floats per observation that ``insert`` requires (0: none).
    """

    def __init__(
        self,
        capacity_transitions: int,
        image_size: int = 84,
        seq_len: int = 50,
        constant_channels: Iterable[int] = image_format.CONSTANT_CHANNELS,
        channels: int = image_format.N_CHANNELS,
        max_episodes: int | None = None,
        seed: int | None = None,
        state_dim: int = 0,
    ) -> None:
        const = tuple(int(c) for c in constant_channels)
        cfg = _check_config(capacity_transitions, image_size, seq_len, const, channels, max_episodes)
        self.capacity_transitions, self.image_size, self.seq_len, self.channels, self.max_episodes = cfg
        if int(state_dim) != state_dim or state_dim < 0:
            raise ValueError(f"state_dim must be a non-negative integer, got {state_dim!r}")
        self.state_dim = int(state_dim)
        self.constant_channels = const
        self.code_channels = image_format.code_channels(channels, const)
        self._rng = np.random.default_rng(seed)
        self._arrays = {
            name: np.zeros(shape, dtype)
            for name, (shape, dtype) in _layout(
                *self._config_tuple(), self.max_episodes, self.state_dim
            ).items()
        }
        a = self._arrays
        self._codes, self._const = a["codes"], a["constant"]
        self._actions, self._rewards = a["actions"], a["rewards"]
        self._terminated, self._truncated = a["terminated"], a["truncated"]
        self._state = a["state"]
        self._free_rows, self._free_slots, self._order = a["free_rows"], a["free_slots"], a["order"]
        self._ep_rows, self._ep_length, self._ep_serial = a["ep_rows"], a["ep_length"], a["ep_serial"]
        self._ep_demo, self._ep_kind, self._ep_success = a["ep_demo"], a["ep_kind"], a["ep_success"]
        self._zero_row = self._codes.shape[0] - 1
        self._reset_bookkeeping(np.zeros(0, np.int32))

    # ---------------------------------------------------------------- sizes

    @classmethod
    def reserved_bytes(
        cls,
        capacity_transitions: int,
        image_size: int = 84,
        seq_len: int = 50,
        constant_channels: Iterable[int] = image_format.CONSTANT_CHANNELS,
        channels: int = image_format.N_CHANNELS,
        max_episodes: int | None = None,
        state_dim: int = 0,
    ) -> int:
        """Bytes the arrays of such a buffer reserve, computed without allocating (equals ``nbytes``)."""
        const = tuple(int(c) for c in constant_channels)
        cap, size, L, C, E = _check_config(
            capacity_transitions, image_size, seq_len, const, channels, max_episodes
        )
        layout = _layout(cap, size, L, C, const, E, int(state_dim))
        return sum(math.prod(shape) * dtype.itemsize for shape, dtype in layout.values())

    @property
    def nbytes(self) -> int:
        """Bytes actually reserved by the preallocated arrays (python-side id lists not counted)."""
        return sum(arr.nbytes for arr in self._arrays.values())

    def __len__(self) -> int:
        """Stored transitions."""
        return self._transitions

    @property
    def num_episodes(self) -> int:
        return self._n

    def stats(self) -> dict[str, Any]:
        """Counters for metrics: plain ints (and one dict of ints by augmentation kind)."""
        live = self._order[: self._n]
        lengths = self._ep_length[live].astype(np.int64)
        by_kind = np.bincount(self._ep_kind[live], weights=lengths, minlength=len(self._kind_names))
        augmented = {name: int(by_kind[k]) for k, name in enumerate(self._kind_names) if name != RAW_KIND}
        return {
            "transitions": self._transitions,
            "episodes": self._n,
            "capacity_transitions": self.capacity_transitions,
            "max_episodes": self.max_episodes,
            "demo_transitions": self._demo_transitions,
            "demo_episodes": self._demo_episodes,
            "raw_transitions": int(by_kind[0]),
            "augmented_transitions": sum(augmented.values()),
            "augmented_transitions_by_kind": augmented,
            "evicted_episodes": self._evicted_episodes,
            "evicted_transitions": self._evicted_transitions,
        }

    def episode_ids(self) -> list[str]:
        """``episode_id`` of every stored episode, oldest first."""
        return [self._ep_id[int(s)] for s in self._order[: self._n]]

    def episode_info(self, episode_index: int) -> dict[str, Any]:
        """Provenance of a stored episode by its insertion serial (``SequenceBatch.episode_index``)."""
        live = self._order[: self._n]
        hits = np.flatnonzero(self._ep_serial[live] == int(episode_index))
        if hits.size == 0:
            raise KeyError(f"episode_index {episode_index} is not stored (evicted or never inserted)")
        slot = int(live[hits[0]])
        return {
            "episode_id": self._ep_id[slot],
            "source_episode_id": self._ep_source[slot],
            "kind": self._kind_names[int(self._ep_kind[slot])],
            "is_demo": bool(self._ep_demo[slot]),
            "length": int(self._ep_length[slot]),
        }

    # ---------------------------------------------------------------- insert

    def insert(self, ep: Episode, state: np.ndarray | None = None) -> int:
        """Store ``ep`` (with uint8 ``images``), evicting old non-demo episodes; returns its transitions.
        ``state``: (T+1, state_dim) privileged rows, required iff the buffer has a ``state_dim``.

        Raises ``ValueError`` naming the offending field if the episode does not match the buffer's
        configuration, or if it cannot fit beside the pinned demonstrations; the buffer is then unchanged.
        """
        if str(ep.episode_id) in self._stored:
            raise ValueError(f"duplicate: episode {ep.episode_id!r} is already stored (a repeated delivery)")
        T, codes, const = self._checked_arrays(ep)
        state = self._checked_state(T, state)
        aug = ep.augmentation
        kind = RAW_KIND if aug is None else str(aug.kind)
        source = ep.episode_id if aug is None else str(aug.source_episode_id)
        demo = bool(ep.is_demo) or (aug is not None and source in self._demo_ids)
        if (
            self._demo_transitions + T > self.capacity_transitions
            or self._demo_episodes + 1 > self.max_episodes
        ):
            what = "demonstration" if demo else "episode"
            raise ValueError(
                f"{what} {ep.episode_id!r} ({T} transitions) does not fit: pinned demonstrations hold "
                f"{self._demo_transitions} transitions in {self._demo_episodes} episodes of a capacity of "
                f"{self.capacity_transitions} transitions and {self.max_episodes} episodes; demonstrations "
                "are never evicted, so raise the capacity"
            )
        while self._transitions + T > self.capacity_transitions or self._n + 1 > self.max_episodes:
            self._evict_oldest_unpinned()
        if kind not in self._kind_names:
            self._kind_names.append(kind)
        self._store(T, codes, const, ep.actions, ep.rewards, ep.terminated, ep.truncated, state)
        self._set_episode_meta(self._n - 1, str(ep.episode_id), source, self._kind_names.index(kind), demo)
        return T

    def _checked_arrays(self, ep: Episode) -> tuple[int, np.ndarray, np.ndarray]:
        """Validate ``ep`` against the configuration; returns (T, codes (T+1, Cv, H, W), constant (T+1, Cc))."""
        T = int(np.shape(ep.actions)[0]) if np.ndim(ep.actions) == 2 else -1
        if T < 1 or np.shape(ep.actions) != (T, ACTION_DIM):
            raise ValueError(f"actions: expected shape (T >= 1, {ACTION_DIM}), got {np.shape(ep.actions)}")
        if self.seq_len < T:
            raise ValueError(f"actions: episode has {T} steps, more than seq_len={self.seq_len}")
        for name in ("rewards", "terminated", "truncated"):
            if np.shape(getattr(ep, name)) != (T,):
                raise ValueError(f"{name}: expected shape ({T},), got {np.shape(getattr(ep, name))}")
        images = ep.images
        if images is None:
            raise ValueError("images: None; the replay stores policy images, attach them before inserting")
        if not isinstance(images, np.ndarray) or images.dtype != image_format.DTYPE:
            raise ValueError(
                f"images: dtype must be uint8, got {getattr(images, 'dtype', type(images).__name__)}"
            )
        expected = (T + 1, self.channels, self.image_size, self.image_size)
        if images.shape != expected:
            raise ValueError(f"images: expected shape {expected} (T+1, C, H, W), got {images.shape}")
        try:
            codes, const = image_format.split_constant(images, self.code_channels, self.constant_channels)
        except ValueError as exc:
            raise ValueError(f"images: {exc}") from None
        return T, codes, const

    def _checked_state(self, T: int, state: np.ndarray | None) -> np.ndarray:
        if self.state_dim == 0:
            if state is not None:
                raise ValueError("state: this replay stores no privileged state (state_dim 0)")
            return np.zeros((T + 1, 0), np.float32)
        if state is None:
            raise ValueError(f"state: this replay needs {self.state_dim} privileged floats per observation")
        state = np.asarray(state, np.float32)
        if state.shape != (T + 1, self.state_dim) or not np.isfinite(state).all():
            raise ValueError(f"state: expected finite ({T + 1}, {self.state_dim}), got {state.shape}")
        return state

    def _store(
        self,
        T: int,
        codes: np.ndarray,
        const: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        state: np.ndarray,
    ) -> None:
        """Write one episode into free rows and a free slot appended to the insertion order."""
        top = self._n_free_rows
        rows = self._free_rows[top - (T + 1) : top][::-1].copy()  # pop T+1 rows (ascending when fresh)
        self._n_free_rows = top - (T + 1)
        self._codes[rows] = codes
        self._const[rows] = const
        self._state[rows] = state
        self._actions[rows[:T]] = actions
        self._rewards[rows[:T]] = rewards
        self._terminated[rows[:T]] = terminated
        self._truncated[rows[:T]] = truncated
        self._n_free_slots -= 1
        slot = int(self._free_slots[self._n_free_slots])
        self._ep_rows[slot, : T + 1] = rows
        self._ep_rows[slot, T + 1 :] = self._zero_row
        self._ep_length[slot] = T
        self._ep_success[slot] = succeeded(terminated, rewards)
        self._order[self._n] = slot
        self._n += 1
        self._transitions += T

    def _set_episode_meta(self, position: int, episode_id: str, source: str, kind: int, demo: bool) -> None:
        slot = int(self._order[position])
        self._ep_serial[slot] = self._next_serial
        self._next_serial += 1
        self._ep_kind[slot] = kind
        self._ep_demo[slot] = demo
        self._ep_id[slot] = episode_id
        self._stored.add(episode_id)
        self._ep_source[slot] = source
        if demo:
            self._demo_transitions += int(self._ep_length[slot])
            self._demo_episodes += 1
            if kind == 0:
                self._demo_ids.add(episode_id)

    def _evict_oldest_unpinned(self) -> None:
        live = self._order[: self._n]
        unpinned = np.flatnonzero(~self._ep_demo[live])
        pos = int(unpinned[0])  # exists: the caller checked that the demos alone leave room
        slot = int(live[pos])
        T = int(self._ep_length[slot])
        self._free_rows[self._n_free_rows : self._n_free_rows + T + 1] = self._ep_rows[slot, : T + 1][::-1]
        self._n_free_rows += T + 1
        self._free_slots[self._n_free_slots] = slot
        self._n_free_slots += 1
        self._order[pos : self._n - 1] = self._order[pos + 1 : self._n].copy()
        self._n -= 1
        self._transitions -= T
        self._evicted_episodes += 1
        self._evicted_transitions += T
        self._stored.discard(self._ep_id[slot])
        self._ep_id[slot] = self._ep_source[slot] = ""

    # ---------------------------------------------------------------- internals

    def _config_tuple(self) -> tuple[int, int, int, int, tuple[int, ...]]:
        return self.capacity_transitions, self.image_size, self.seq_len, self.channels, self.constant_channels

    def _reset_bookkeeping(self, lengths: np.ndarray) -> None:
        """Lay ``len(lengths)`` episodes out contiguously in rows 0.. and slots 0..; everything else free."""
        n = int(lengths.size)
        L = self.seq_len
        starts = np.concatenate([[0], np.cumsum(lengths + 1)[:-1]]).astype(np.int64)
        steps = np.arange(L + 1)
        self._ep_rows[:n] = np.where(steps <= lengths[:, None], starts[:, None] + steps, self._zero_row)
        self._ep_rows[n:] = self._zero_row
        self._ep_length[:n] = lengths
        self._ep_length[n:] = 0
        used = int((lengths + 1).sum())
        n_rows = self._zero_row  # rows usable by episodes: 0 .. zero_row - 1
        self._n_free_rows = n_rows - used
        self._free_rows[: self._n_free_rows] = np.arange(n_rows - 1, used - 1, -1)  # top of stack: lowest row
        self._n_free_slots = self.max_episodes - n
        self._free_slots[: self._n_free_slots] = np.arange(self.max_episodes - 1, n - 1, -1)
        self._order[:n] = np.arange(n)
        self._n = n
        self._transitions = int(lengths.sum())
        self._ep_id = [""] * self.max_episodes
        self._ep_source = [""] * self.max_episodes
        self._ep_serial[:], self._ep_demo[:], self._ep_kind[:], self._ep_success[:] = 0, False, 0, False
        self._kind_names = [RAW_KIND]
        self._demo_ids: set[str] = set()
        self._stored: set[str] = set()  # ids of the stored episodes: a repeated delivery is refused
        self._demo_transitions = self._demo_episodes = 0
        self._next_serial = 0
        self._evicted_episodes = self._evicted_transitions = 0


def _check_config(
    capacity_transitions: int,
    image_size: int,
    seq_len: int,
    constant_channels: tuple[int, ...],
    channels: int,
    max_episodes: int | None,
) -> tuple[int, int, int, int, int]:
    for name, value in (
        ("capacity_transitions", capacity_transitions),
        ("image_size", image_size),
        ("seq_len", seq_len),
        ("channels", channels),
    ):
        if int(value) != value or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if len(set(constant_channels)) != len(constant_channels) or any(
        not 0 <= c < channels for c in constant_channels
    ):
        raise ValueError(
            f"constant_channels must be distinct indices in [0, {channels}), got {constant_channels}"
        )
    E = _default_max_episodes(int(capacity_transitions)) if max_episodes is None else max_episodes
    if int(E) != E or E < 1:
        raise ValueError(f"max_episodes must be a positive integer, got {max_episodes!r}")
    return int(capacity_transitions), int(image_size), int(seq_len), int(channels), int(E)
