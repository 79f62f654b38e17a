"""A sampled batch of whole episodes, as the replay hands it out: uint8 codes, padded to a length."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.observation import image_format


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
    def demo_share(self) -> float:
        """Share of the episodes drawn from the demonstration set."""
        return float(self.from_demo_set.mean())

    @property
    def reward_transitions(self) -> float:
        """Transitions with reward > 0."""
        return float((self.rewards > 0).sum())

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
