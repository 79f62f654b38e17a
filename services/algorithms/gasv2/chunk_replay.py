"""GASv2's replay: whole Surgical Grasp Any episodes in ``SequenceReplay``'s arena, sampled as
fixed-length windows in DreamerV2's step convention (``chunks.ChunkBatch``).

Design notes: docs/architecture-notes.md, services/algorithms/gasv2/chunk_replay.py."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from services.algorithms.gasv2.action_features import features
from services.algorithms.gasv2.chunks import ChunkBatch
from services.algorithms.replay import SequenceReplay
from services.algorithms.tensors import images_from_codes
from services.observation.dsa import STATE_ROW, decode_state_rows

if TYPE_CHECKING:
    from proto.episode import Episode

CHANNELS = 3
"""Channels of the DSA image (gripper depth, object depth, mask ids with the state row)."""
IMAGE_SIZE = 64
"""H = W of the task's DSA image."""
SEQ_LEN = 80
"""The task's step limit: the longest episode stored."""
STATE_DIM = 1
"""State floats per observation: the controller_state."""
_MASK_CHANNEL = 2
"""Channel of the DSA image whose ``STATE_ROW`` carries the state codes."""
_CONTROLLER = 0
"""Column of the controller_state in the replay's state rows."""


@dataclass(frozen=True)
class ChunkSample:
    """``ChunkBatch``'s fields as numpy, images still uint8 codes (``to_chunk_batch`` converts).

    Two extra fields say where each window came from (tests, diagnostics); ``to_chunk_batch`` drops them.
    """

    images: np.ndarray
    """uint8 (B, L, 3, H, W): DSA codes of observation t (zeros where padded)."""
    actions: np.ndarray
    """float32 (B, L, 5): feature of the action into observation t (0 where ``is_first`` or padded)."""
    rewards: np.ndarray
    """float32 (B, L): reward of the action into observation t (0 where ``is_first`` or padded)."""
    discounts: np.ndarray
    """float32 (B, L): 0 where observation t is terminal or padded, else 1."""
    is_first: np.ndarray
    """bool (B, L): observation t is its episode's first (row 0)."""
    handover: np.ndarray
    """bool (B, L): controller_state is 0 at observation t (False where padded)."""
    mask: np.ndarray
    """bool (B, L): observation t is real."""
    demo: np.ndarray
    """float32 (B,): 1 for windows drawn from the demonstration set."""
    episode_index: np.ndarray
    """int64 (B,): insertion serial of each window's episode (``episode_info``)."""
    start: np.ndarray
    """int64 (B,): ``t0``, the episode row of each window's observation 0."""

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.rewards.shape[0]), int(self.rewards.shape[1])

    @property
    def demo_share(self) -> float:
        """Share of the windows drawn from the demonstration set."""
        return float(np.mean(self.demo))

    @property
    def reward_transitions(self) -> float:
        """Steps with reward > 0."""
        return float((self.rewards > 0).sum())


_BATCH_FIELDS = tuple(f.name for f in dataclasses.fields(ChunkBatch))


def to_chunk_batch(sample: ChunkSample, device: torch.device | str = "cpu") -> ChunkBatch:
    """The torch batch on ``device``; images move as uint8 and become float32 there
    (``tensors.images_from_codes``, bit for bit ``image_format.decode``)."""
    out: dict[str, torch.Tensor] = {}
    for name in _BATCH_FIELDS:
        out[name] = torch.from_numpy(getattr(sample, name)).to(device)
    out["images"] = images_from_codes(out["images"])
    return ChunkBatch(**out)


_FIXED = {"constant_channels": (), "channels": CHANNELS, "state_dim": STATE_DIM}
"""What every ``ChunkReplay`` stores besides its sizes: 3 image channels, none constant, controller_state."""


class ChunkReplay(SequenceReplay):
    """``SequenceReplay`` of Surgical Grasp Any episodes that samples DreamerV2 windows (docs/architecture-notes.md).

    Args:
        capacity_transitions: stored transitions at most (raw and augmented copies alike).
        seq_len: longest episode accepted (the task's step limit).
        image_size: H = W of the DSA images.
        max_episodes: stored episodes at most (default ``ceil(capacity / 4)``, as the parent).
        seed: seed of the generator ``sample_chunks`` uses when given no ``rng`` (saved with the contents).
    """

    def __init__(
        self,
        capacity_transitions: int,
        seq_len: int = SEQ_LEN,
        image_size: int = IMAGE_SIZE,
        max_episodes: int | None = None,
        seed: int | None = None,
    ) -> None:
        super().__init__(
            capacity_transitions,
            image_size=image_size,
            seq_len=seq_len,
            max_episodes=max_episodes,
            seed=seed,
            **_FIXED,
        )

    @classmethod
    def reserved_bytes(  # type: ignore[override]  # the configuration is fixed but for these
        cls,
        capacity_transitions: int,
        seq_len: int = SEQ_LEN,
        image_size: int = IMAGE_SIZE,
        max_episodes: int | None = None,
    ) -> int:
        """Bytes such a buffer's arrays reserve, computed without allocating (equals ``nbytes``)."""
        return SequenceReplay.reserved_bytes(
            capacity_transitions, image_size=image_size, seq_len=seq_len, max_episodes=max_episodes, **_FIXED
        )

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> ChunkReplay:
        """A new buffer with the configuration and contents of ``state`` (a ``ChunkReplay``'s)."""
        replay = cls(
            int(state["capacity_transitions"]),
            seq_len=int(state["seq_len"]),
            image_size=int(state["image_size"]),
            max_episodes=int(state["max_episodes"]),
        )
        replay.load_state_dict(state)
        return replay

    # ---------------------------------------------------------------- insert

    def insert_episode(self, ep: Episode) -> int:
        """Store ``ep`` (uint8 DSA ``images`` (T+1, 3, H, W)) with its actions replaced by their features
        and its controller_state per observation as the state column; returns its transitions.

        Raises ``ValueError`` naming the field (``images``: missing, not uint8, wrong shape, a state
        row that does not decode; ``actions``: more steps than ``seq_len``; ...), for a duplicate, or
        when it cannot fit beside the pinned demonstrations; the replay is then unchanged.
        """
        self._checked_arrays(ep)  # the parent's checks, before the images are read here
        controller = _controller_states(ep.images)
        stored = dataclasses.replace(ep, actions=features(ep.actions))
        return self.insert(stored, controller[:, None])

    # ---------------------------------------------------------------- sample

    def sample_chunks(
        self,
        batch_size: int,
        length: int,
        rng: np.random.Generator | None = None,
        *,
        demo_fraction: float = 0.0,
        successes_as_demos: bool = False,
    ) -> ChunkSample:
        """``batch_size`` windows of ``length`` observations (1 .. seq_len + 1), one per episode drawn
        with replacement as ``SequenceReplay.sample`` draws them (same arguments, same draws from
        ``rng``), then each window's start uniform in ``[0, max(0, T + 1 - length)]`` from ``rng``.
        """
        if int(length) != length or not 1 <= length <= self.seq_len + 1:
            raise ValueError(f"length must be an integer in [1, {self.seq_len + 1}], got {length}")
        rng = self._rng if rng is None else rng
        slots = self._draw_episodes(batch_size, rng, demo_fraction, successes_as_demos)
        lengths = self._ep_length[slots].astype(np.int64)
        start = rng.integers(0, np.maximum(lengths + 1 - int(length), 0) + 1)  # (B,), inclusive high
        return self._gather_windows(slots, lengths, start, int(length), successes_as_demos)

    def _gather_windows(
        self, slots: np.ndarray, lengths: np.ndarray, start: np.ndarray, length: int, successes_as_demos: bool
    ) -> ChunkSample:
        step = start[:, None] + np.arange(length)  # (B, L) episode row of each window entry, <= seq_len
        mask = step <= lengths[:, None]
        rows = self._ep_rows[slots[:, None], step]  # past the episode: the zero row
        # the transition into row s is transition s - 1 (stored on the episode's row s - 1); none into
        # row 0, and padding must not read the unused transition fields of an episode's last row
        into = self._ep_rows[slots[:, None], np.maximum(step - 1, 0)]
        into = np.where(mask & (step > 0), into, self._zero_row)  # zero row: all-zero fields
        return ChunkSample(
            images=self._codes[rows],
            actions=self._actions[into],
            rewards=self._rewards[into],
            discounts=(mask & ~self._terminated[into]).astype(np.float32),
            is_first=step == 0,
            handover=mask & (self._state[rows, _CONTROLLER] == 0.0),
            mask=mask,
            demo=self._in_demo_set(slots, successes_as_demos).astype(np.float32),
            episode_index=self._ep_serial[slots],
            start=start.astype(np.int64),
        )


def _controller_states(images: np.ndarray) -> np.ndarray:
    """float32 (T+1,) controller_state of each image's state row; ``ValueError`` naming ``images`` if
    a row does not decode. Decodes each distinct state row once (a handful per episode)."""
    rows = images[:, _MASK_CHANNEL, STATE_ROW, :]
    distinct, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    values = np.empty(len(distinct), np.float32)
    for k in np.argsort(first):  # in time order: an error names the first bad observation
        t = first[k]
        try:
            values[k] = decode_state_rows(images[t])[2]
        except ValueError as exc:
            raise ValueError(f"images: observation {int(t)} has a corrupted state row: {exc}") from None
    return values[inverse.reshape(-1)]
