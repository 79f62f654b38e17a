"""Sequence replay for recurrent SAC: whole episodes, uint8 observations stored once.

``SequenceReplay`` is the storage of ``replay_storage`` (arena layout, inserts, capacity and
eviction policy) plus what the learner does with it: sampling batches (``replay_batch``) and
checkpoint state.

Sampling draws whole episodes with replacement, uniformly among the stored ones or with a fixed
share from the demonstration set (``sample(demo_fraction=...)``), indexed in insertion order, so a
checkpoint round trip (``state_dict``/``load_state_dict``) reproduces the same batches for the same
generator state. Not thread-safe: the caller serialises inserts and samples.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

import numpy as np

from proto.actions import ACTION_DIM
from services.algorithms.privileged import episode_critic_state
from services.algorithms.replay_batch import SequenceBatch
from services.algorithms.replay_storage import ReplayStorage
from services.observation import image_format

if TYPE_CHECKING:
    from proto.episode import Episode

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


class SequenceReplay(ReplayStorage):
    """Whole-episode replay with a fixed memory budget (``ReplayStorage``, same arguments) that samples
    batches and saves and restores its contents."""

    def insert_episode(self, ep: Episode) -> int:
        """``insert`` with the episode's privileged state rows where the buffer keeps them (a state
        critic's: ``privileged.episode_critic_state``); ValueError (unchanged) when refused."""
        return self.insert(ep, episode_critic_state(ep) if self.state_dim else None)

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
        other. ``successes_as_demos`` adds every episode that succeeded (online successes and
        their copies) to that set (self-imitation); ``SequenceBatch.from_demo_set`` tells which episodes
        were drawn from it. ``trim`` pads to the longest sampled episode instead of ``seq_len`` (the losses are
        masked and the LSTM causal, so padding past the longest episode changes nothing but the cost).
        """
        rng = self._rng if rng is None else rng
        slots = self._draw_episodes(batch_size, rng, demo_fraction, successes_as_demos)
        return self._gather(slots, trim, successes_as_demos)

    def slots(self, *, demo: bool | None = None, success: bool | None = None) -> np.ndarray:
        """Table slots of the stored episodes, oldest first: those that are (``demo``) demonstrations
        or not and that succeeded (``success``) or not; None: either."""
        live = self._order[: self._n]
        keep = np.ones(live.size, bool)
        if demo is not None:
            keep &= self._ep_demo[live] == demo
        if success is not None:
            keep &= self._ep_success[live] == success
        return live[keep]

    def gather(self, slots: np.ndarray, trim: bool = True) -> SequenceBatch:
        """The episodes at ``slots`` (``slots()``) as one batch, laid out as ``sample``'s."""
        return self._gather(np.asarray(slots, dtype=np.int64), trim)

    def _draw_episodes(
        self, batch_size: int, rng: np.random.Generator, demo_fraction: float, successes_as_demos: bool
    ) -> np.ndarray:
        """Table slots of ``batch_size`` stored episodes drawn with replacement, uniformly or with the
        demonstration split (``sample``'s draw; ValueError for a bad size or share, or an empty replay)."""
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if not 0.0 <= demo_fraction <= 1.0:
            raise ValueError(f"demo_fraction must be in [0, 1], got {demo_fraction}")
        if self._n == 0:
            raise ValueError("cannot sample from an empty replay")
        if demo_fraction == 0.0:
            return self._order[rng.integers(0, self._n, size=batch_size)]
        return self._sample_split(batch_size, rng, demo_fraction, successes_as_demos)

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

    def live_episodes(self) -> tuple[np.ndarray, np.ndarray]:
        """(serials, transitions) of the stored episodes, in insertion order: what a checkpoint needs
        to tell which episodes it already holds (serials are never reused within a buffer's life)."""
        live = self._order[: self._n]
        return self._ep_serial[live].copy(), self._ep_length[live].copy()

    def state_dict(self, serials: np.ndarray | None = None) -> dict[str, Any]:
        """The occupied part as numpy arrays and plain python values (safe for ``weights_only`` loads).

        Episodes are saved in insertion order with their observations and transitions concatenated;
        the generator state of ``sample``'s default rng is a JSON string. With ``serials``, only the
        stored episodes among them (an incremental checkpoint's new part); the rest is the same.
        """
        live = self._order[: self._n]
        if serials is not None:
            live = live[np.isin(self._ep_serial[live], serials)]
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
            "episode_id": [self._ep_id[int(s)] for s in live],
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
        self._stored = set(ids)
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
