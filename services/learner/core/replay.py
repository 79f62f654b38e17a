"""Sequence replay for recurrent SAC: whole episodes, uint8 observations stored once.

Why this layout (tasks-and-baselines.md §8 P4): the public code keeps float32 ``obs`` and
``next_obs`` per transition, about 11.3e9 bytes for 1e5 transitions of (2, 84, 84). Here:

* an episode of ``T`` transitions stores its ``T+1`` observations once (the next observation of
  step ``t`` is row ``t+1``), as uint8 codes;
* a channel that is constant over the image (the tiled jaw code, channel 1 of the policy image
  format, ``services.observation.image_format``) is stored as one byte per observation and
  re-tiled by the consumer (``SequenceBatch.images_uint8``);
* actions float32 (T, 5), rewards float32, ``terminated``/``truncated`` bool;
* optionally ``state_dim`` float32 per observation: the privileged state a state critic reads
  (``services.learner.core.privileged``), given beside the episode at insert.

Storage is preallocated once as a flat arena of rows, one row per observation (the transition
fields of an episode's last row are unused and never read), plus one all-zero row that padding points at. An
episode table maps each stored episode to its rows, padded to ``seq_len + 1`` with the zero row,
so a batch is a single fancy-indexing gather with a (B, L+1) index array and padded entries come
out as zeros without any masking pass. Free rows and table slots are kept on stacks: episodes need
not be contiguous, so pinned demonstrations never fragment the arena and eviction is O(T) numpy
work with no compaction.

Capacity and eviction policy:

* capacity counts stored transitions, raw and augmented copies alike (Equi-RSAC's 1e5 includes
  the augmented copies, P7); the table also holds at most ``max_episodes`` episodes (default
  ``ceil(capacity / 4)``), which bounds the arena at ``capacity + max_episodes`` observation rows;
* when an insert does not fit, the oldest non-demonstration episodes are evicted first (FIFO by
  insertion order) until it does;
* demonstrations are pinned and never evicted: raw demos and augmented copies of demos (the
  augmenter copies ``is_demo`` from the source with ``dataclasses.replace``; an augmented episode
  whose ``source_episode_id`` is a stored raw demo counts as a demo too);
* an insert that cannot fit even after evicting every non-demo episode (the demos alone would
  exceed the capacity or the table) raises ``ValueError``: nothing is dropped silently, and a
  rejected insert leaves the buffer unchanged.

Sampling draws whole episodes with replacement, uniformly among the stored ones or with a fixed
share from the demonstration set (``sample(demo_fraction=...)``), indexed in insertion order, so a
checkpoint round trip (``state_dict``/``load_state_dict``) reproduces the same batches for the same
generator state. Not thread-safe: the caller serialises inserts and samples.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from proto.actions import ACTION_DIM
from services.observation import image_format

if TYPE_CHECKING:
    from proto.episode import Episode

RAW_KIND = "raw"
"""Provenance kind of an episode without ``augmentation``."""
DEFAULT_STEPS_PER_EPISODE = 4
"""``max_episodes`` defaults to ``ceil(capacity / 4)``: room for episodes of 4+ steps on average."""
STATE_FORMAT = 1
"""Version of the ``state_dict`` layout."""

_PUBLIC_OBS_COPIES = 2  # obs and next_obs
_FLOAT32_BYTES = 4


def public_reference_bytes(capacity_transitions: int, image_size: int = 84, channels: int = 2) -> int:
    """Bytes of the public code's float32 ``obs`` + ``next_obs`` arrays for this many transitions.

    ``1e5 * 2 * 2 * 84 * 84 * 4`` = 11.29e9 bytes (10.5 GiB), the figure in platform-notes.md §8.
    """
    return (
        int(capacity_transitions) * _PUBLIC_OBS_COPIES * channels * image_size * image_size * _FLOAT32_BYTES
    )


@dataclass(frozen=True)
class SequenceBatch:
    """``B`` whole episodes padded to ``L = seq_len``; padded entries are zeros.

    Observation ``t`` of a sequence is ``(image_codes[:, t], constant[:, t])``; transition ``t``
    goes from observation ``t`` to ``t+1`` with ``actions[:, t]`` and ``rewards[:, t]``.
    """

    image_codes: np.ndarray
    """uint8 (B, L+1, Cv, H, W): the channels that vary over the image (depth codes)."""
    constant: np.ndarray
    """uint8 (B, L+1, Cc): one code per constant channel (the jaw), to be tiled over (H, W)."""
    actions: np.ndarray
    """float32 (B, L, 5)."""
    rewards: np.ndarray
    """float32 (B, L)."""
    terminated: np.ndarray
    """bool (B, L): the task ended on this step (bootstrapping stops)."""
    truncated: np.ndarray
    """bool (B, L): the time limit ended the episode on this step (bootstrapping continues)."""
    mask: np.ndarray
    """bool (B, L): true for real transitions (``t < lengths``)."""
    obs_mask: np.ndarray
    """bool (B, L+1): true for real observations (``t <= lengths``)."""
    lengths: np.ndarray
    """int32 (B,): transitions per episode, 1..L."""
    episode_index: np.ndarray
    """int64 (B,): insertion serial of each episode (``SequenceReplay.episode_info``)."""
    is_demo: np.ndarray
    """bool (B,): demonstration (raw or augmented copy of one)."""
    from_demo_set: np.ndarray
    """bool (B,): drawn from the demonstration set (``is_demo``, or a success with ``successes_as_demos``)."""
    code_channels: tuple[int, ...]
    """Channel index in the full image of each ``image_codes`` channel."""
    constant_channels: tuple[int, ...]
    """Channel index in the full image of each ``constant`` entry."""
    state: np.ndarray
    """float32 (B, L+1, state_dim): privileged state per observation (state_dim may be 0)."""

    @property
    def batch_size(self) -> int:
        return int(self.actions.shape[0])

    @property
    def seq_len(self) -> int:
        return int(self.actions.shape[1])

    def images_uint8(self) -> np.ndarray:
        """The full uint8 stack (B, L+1, C, H, W), constant channels tiled over the image."""
        return image_format.tile_constant(
            self.image_codes, self.constant, self.code_channels, self.constant_channels
        )


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


class SequenceReplay:
    """Whole-episode replay with a fixed memory budget; see the module docstring for the policy.

    Args:
        capacity_transitions: stored transitions at most (raw and augmented copies alike).
        image_size: H = W of the policy images.
        seq_len: longest episode accepted, and the padded length of sampled sequences.
        constant_channels: channels constant over each image (the tiled jaw code), stored as one byte.
        channels: channels of the policy image.
        max_episodes: stored episodes at most (default ``ceil(capacity / 4)``).
        seed: seed of the generator ``sample`` uses when given no ``rng``.
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
        self._ep_success[slot] = bool((rewards > 0).any())
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
        self._ep_id[slot] = self._ep_source[slot] = ""

    # ---------------------------------------------------------------- sample

    def sample(
        self,
        batch_size: int,
        rng: np.random.Generator | None = None,
        *,
        demo_fraction: float = 0.0,
        successes_as_demos: bool = False,
        trim: bool = False,
    ) -> SequenceBatch:
        """``batch_size`` stored episodes drawn with replacement.

        ``demo_fraction`` = 0 draws uniformly among all stored episodes (the paper). Otherwise
        ``round(demo_fraction * batch_size)`` episodes are drawn uniformly from the demonstration set
        (raw demos and every augmented copy of one) and the rest uniformly from the other episodes
        (RLPD's symmetric sampling); while one of the two sets is empty the whole batch comes from the
        other. ``successes_as_demos`` adds every episode with a positive reward (online successes and
        their copies) to that set (self-imitation); ``SequenceBatch.from_demo_set`` tells which episodes
        were drawn from it. ``trim`` pads to the longest sampled episode instead of ``seq_len`` (the losses are
        masked and the LSTM causal, so padding past the longest episode changes nothing but the cost).
        """
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if not 0.0 <= demo_fraction <= 1.0:
            raise ValueError(f"demo_fraction must be in [0, 1], got {demo_fraction}")
        if self._n == 0:
            raise ValueError("cannot sample from an empty replay")
        rng = self._rng if rng is None else rng
        if demo_fraction == 0.0:
            slots = self._order[rng.integers(0, self._n, size=batch_size)]
        else:
            slots = self._sample_split(batch_size, rng, demo_fraction, successes_as_demos)
        return self._gather(slots, trim, successes_as_demos)

    def _in_demo_set(self, slots: np.ndarray, successes_as_demos: bool) -> np.ndarray:
        demo = self._ep_demo[slots]
        return demo | self._ep_success[slots] if successes_as_demos else demo

    def _sample_split(
        self, batch_size: int, rng: np.random.Generator, demo_fraction: float, successes_as_demos: bool
    ) -> np.ndarray:
        live = self._order[: self._n]
        demo = self._in_demo_set(live, successes_as_demos)
        demos, online = live[demo], live[~demo]
        n_demo = int(round(demo_fraction * batch_size))
        if online.size == 0:
            n_demo = batch_size
        elif demos.size == 0:
            n_demo = 0
        parts = []
        if n_demo:
            parts.append(demos[rng.integers(0, demos.size, size=n_demo)])
        if batch_size - n_demo:
            parts.append(online[rng.integers(0, online.size, size=batch_size - n_demo)])
        return np.concatenate(parts)

    def _gather(
        self, slots: np.ndarray, trim: bool = False, successes_as_demos: bool = False
    ) -> SequenceBatch:
        lengths = self._ep_length[slots]
        L = int(lengths.max()) if trim else self.seq_len
        rows = self._ep_rows[slots, : L + 1]  # (B, L+1), padded with the zero row
        mask = np.arange(L) < lengths[:, None]
        obs_mask = np.arange(L + 1) <= lengths[:, None]
        trans = np.where(mask, rows[:, :L], self._zero_row)  # an episode's last row holds no transition
        return SequenceBatch(
            image_codes=self._codes[rows],
            constant=self._const[rows],
            actions=self._actions[trans],
            rewards=self._rewards[trans],
            terminated=self._terminated[trans],
            truncated=self._truncated[trans],
            mask=mask,
            obs_mask=obs_mask,
            lengths=lengths.copy(),
            episode_index=self._ep_serial[slots],
            is_demo=self._ep_demo[slots],
            from_demo_set=self._in_demo_set(slots, successes_as_demos),
            code_channels=self.code_channels,
            constant_channels=self.constant_channels,
            state=self._state[rows],
        )

    # ---------------------------------------------------------------- checkpoints

    def state_dict(self) -> dict[str, Any]:
        """The occupied part as numpy arrays and plain python values (safe for ``weights_only`` loads).

        Episodes are saved in insertion order with their observations and transitions concatenated;
        the generator state of ``sample``'s default rng is a JSON string.
        """
        live = self._order[: self._n]
        rows = self._ep_rows[live]
        lengths = self._ep_length[live]
        obs_rows = rows[np.arange(self.seq_len + 1) <= lengths[:, None]]
        trans_rows = rows[:, : self.seq_len][np.arange(self.seq_len) < lengths[:, None]]
        return {
            "format": STATE_FORMAT,
            "capacity_transitions": self.capacity_transitions,
            "image_size": self.image_size,
            "seq_len": self.seq_len,
            "channels": self.channels,
            "constant_channels": list(self.constant_channels),
            "max_episodes": self.max_episodes,
            "state_dim": self.state_dim,
            "lengths": lengths.copy(),
            "state": self._state[obs_rows],
            "image_codes": self._codes[obs_rows],
            "constant": self._const[obs_rows],
            "actions": self._actions[trans_rows],
            "rewards": self._rewards[trans_rows],
            "terminated": self._terminated[trans_rows],
            "truncated": self._truncated[trans_rows],
            "serial": self._ep_serial[live],
            "is_demo": self._ep_demo[live],
            "kind": self._ep_kind[live],
            "kind_names": list(self._kind_names),
            "episode_id": self.episode_ids(),
            "source_episode_id": [self._ep_source[int(s)] for s in live],
            "next_serial": self._next_serial,
            "evicted_episodes": self._evicted_episodes,
            "evicted_transitions": self._evicted_transitions,
            "rng_state": json.dumps(self._rng.bit_generator.state),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace the contents with a ``state_dict`` of a buffer of the same configuration.

        Arrays may arrive as anything ``np.asarray`` accepts (CPU tensors included).
        """
        saved = (
            int(state["capacity_transitions"]),
            int(state["image_size"]),
            int(state["seq_len"]),
            int(state["channels"]),
            tuple(int(c) for c in state["constant_channels"]),
            int(state["max_episodes"]),
        )
        mine = (*self._config_tuple()[:4], self.constant_channels, self.max_episodes)
        if int(state.get("format", -1)) != STATE_FORMAT:
            raise ValueError(
                f"format: expected replay state format {STATE_FORMAT}, got {state.get('format')}"
            )
        if int(state.get("state_dim", 0)) != self.state_dim:
            raise ValueError(f"state_dim: saved {state.get('state_dim', 0)}, this buffer's {self.state_dim}")
        if saved != mine:
            raise ValueError(
                f"state_dict configuration (capacity, image_size, seq_len, channels, constant_channels, "
                f"max_episodes)={saved} differs from this buffer's {mine}"
            )
        lengths = np.asarray(state["lengths"], np.int32).reshape(-1)
        arrays = _checked_state_arrays(
            state, lengths, self._codes.shape[1:], self._const.shape[1:], self.state_dim
        )
        n, total_t = lengths.size, int(lengths.sum())
        if total_t > self.capacity_transitions or n > self.max_episodes or (lengths < 1).any():
            raise ValueError(f"lengths: {n} episodes of {total_t} transitions do not fit this buffer")
        self._reset_bookkeeping(lengths)
        obs_rows = self._ep_rows[:n][np.arange(self.seq_len + 1) <= lengths[:, None]]
        trans_rows = self._ep_rows[:n, : self.seq_len][np.arange(self.seq_len) < lengths[:, None]]
        self._codes[obs_rows] = arrays["image_codes"]
        self._const[obs_rows] = arrays["constant"]
        self._state[obs_rows] = arrays["state"]
        for name in ("actions", "rewards", "terminated", "truncated"):
            self._arrays[name][trans_rows] = arrays[name]
        self._ep_serial[:n] = arrays["serial"]
        self._ep_demo[:n] = arrays["is_demo"]
        self._ep_success[:n] = (
            np.add.reduceat(arrays["rewards"] > 0, np.cumsum(lengths) - lengths) > 0 if n else False
        )
        self._ep_kind[:n] = arrays["kind"]
        self._kind_names = [str(k) for k in state["kind_names"]]
        ids, sources = [str(s) for s in state["episode_id"]], [str(s) for s in state["source_episode_id"]]
        if len(ids) != n or len(sources) != n:
            raise ValueError(
                f"episode_id: expected {n} ids and source ids, got {len(ids)} and {len(sources)}"
            )
        if n and (self._ep_kind[:n].min() < 0 or self._ep_kind[:n].max() >= len(self._kind_names)):
            raise ValueError("kind: code outside kind_names")
        self._ep_id[:n], self._ep_source[:n] = ids, sources
        demo = self._ep_demo[:n]
        self._demo_transitions = int(lengths[demo].sum())
        self._demo_episodes = int(demo.sum())
        self._demo_ids = {ids[i] for i in np.flatnonzero(demo & (self._ep_kind[:n] == 0))}
        self._next_serial = int(state["next_serial"])
        self._evicted_episodes = int(state["evicted_episodes"])
        self._evicted_transitions = int(state["evicted_transitions"])
        self._rng.bit_generator.state = json.loads(str(state["rng_state"]))

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> SequenceReplay:
        """A new buffer with the configuration and contents of ``state``."""
        replay = cls(
            int(state["capacity_transitions"]),
            image_size=int(state["image_size"]),
            seq_len=int(state["seq_len"]),
            constant_channels=[int(c) for c in state["constant_channels"]],
            channels=int(state["channels"]),
            max_episodes=int(state["max_episodes"]),
            state_dim=int(state.get("state_dim", 0)),
        )
        replay.load_state_dict(state)
        return replay

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


def _checked_state_arrays(
    state: dict[str, Any],
    lengths: np.ndarray,
    code_shape: tuple[int, ...],
    const_shape: tuple[int, ...],
    state_dim: int,
) -> dict[str, np.ndarray]:
    n, n_obs, n_trans = lengths.size, int((lengths + 1).sum()), int(lengths.sum())
    expected = {
        "image_codes": ((n_obs, *code_shape), image_format.DTYPE),
        "constant": ((n_obs, *const_shape), image_format.DTYPE),
        "actions": ((n_trans, ACTION_DIM), np.float32),
        "rewards": ((n_trans,), np.float32),
        "terminated": ((n_trans,), np.bool_),
        "truncated": ((n_trans,), np.bool_),
        "serial": ((n,), np.int64),
        "is_demo": ((n,), np.bool_),
        "kind": ((n,), np.int16),
        "state": ((n_obs, state_dim), np.float32),
    }
    out = {}
    for name, (shape, dtype) in expected.items():
        # a state saved before privileged rows existed has none: the empty (n_obs, 0) array
        arr = np.asarray(state[name]) if name in state or state_dim else np.zeros((n_obs, 0), np.float32)
        if arr.shape != shape or arr.dtype != dtype:
            raise ValueError(
                f"{name}: expected {np.dtype(dtype).name} {shape}, got {arr.dtype.name} {arr.shape}"
            )
        out[name] = arr
    return out
