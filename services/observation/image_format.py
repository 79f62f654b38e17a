"""The policy image's uint8 format: one definition for every writer and reader.

Design notes: docs/architecture-notes.md, services/observation/image_format.py."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = [
    "CODE_MAX",
    "CONSTANT_CHANNELS",
    "DEPTH_CHANNEL",
    "DTYPE",
    "INPUT_SCALE",
    "JAW_CHANNEL",
    "N_CHANNELS",
    "code_channels",
    "decode",
    "decode_jaw",
    "encode",
    "encode_jaw",
    "jaw_codes",
    "split_constant",
    "tile_constant",
]

DTYPE = np.dtype(np.uint8)
"""Storage type of every channel."""
CODE_MAX = 255
"""Largest code; the jaw channel maps [0, 1] onto 0 .. CODE_MAX."""
DEPTH_CHANNEL = 0
"""Index of the depth codes in an image stack (..., 2, N, N)."""
JAW_CHANNEL = 1
"""Index of the tiled jaw code in an image stack (..., 2, N, N)."""
N_CHANNELS = 2
"""Channels of the policy image."""
CONSTANT_CHANNELS = (JAW_CHANNEL,)
"""Channels constant over each image, stored as one code per image."""
INPUT_SCALE = 1.0 / CODE_MAX
"""Network input = code * INPUT_SCALE (as float32): codes 0 .. 255 -> [0, 1]."""


# ------------------------------------------------------------------------------------------------
# Encoding
# ------------------------------------------------------------------------------------------------


def encode_jaw(jaw: np.ndarray) -> np.ndarray:
    """Jaw openings (0 closed .. 1 open, any float dtype) -> uint8 codes ``round(clip(jaw, 0, 1) * 255)``,
    in float64 arithmetic on the values as given."""
    return np.rint(np.clip(np.asarray(jaw, dtype=np.float64), 0.0, 1.0) * float(CODE_MAX)).astype(DTYPE)


def jaw_codes(jaw: np.ndarray) -> np.ndarray:
    """``encode_jaw`` of the jaw taken as float32 first (as observations store it), so every kind of
    policy image gets the same codes from the same recorded jaw."""
    return encode_jaw(np.asarray(jaw, dtype=np.float32))


def encode(depth_codes: np.ndarray, jaw: np.ndarray) -> np.ndarray:
    """(T, N, N) uint8 depth codes and (T,) jaw openings -> (T, 2, N, N) uint8 policy images.

    The depth codes come from the image kind's own depth scale; the jaw is encoded by ``jaw_codes``
    and tiled over the image. Shapes are the caller's to check (its errors name its arguments).
    """
    depth = np.asarray(depth_codes)
    out = np.empty((depth.shape[0], N_CHANNELS, *depth.shape[1:]), DTYPE)
    out[:, DEPTH_CHANNEL] = depth
    out[:, JAW_CHANNEL] = jaw_codes(jaw)[:, None, None]
    return out


# ------------------------------------------------------------------------------------------------
# Decoding
# ------------------------------------------------------------------------------------------------


def decode(codes: np.ndarray) -> np.ndarray:
    """uint8 codes (..., C, H, W) -> float32 network input in [0, 1]: ``float32(code) * float32(1/255)``."""
    return np.asarray(codes).astype(np.float32) * np.float32(INPUT_SCALE)


def decode_jaw(codes: np.ndarray) -> np.ndarray:
    """Jaw codes -> float32 openings ``code / 255`` (a division, the exact inverse of ``encode_jaw`` on
    its codes; ``decode`` multiplies by 1/255 instead and may differ from it in the last bit)."""
    return np.asarray(codes).astype(np.float32) / np.float32(CODE_MAX)


# ------------------------------------------------------------------------------------------------
# Constant channels: one code per image in storage, tiled back on the way out
# ------------------------------------------------------------------------------------------------


def code_channels(channels: int, constant_channels: Sequence[int]) -> tuple[int, ...]:
    """The channels that vary over the image: every channel index not in ``constant_channels``."""
    return tuple(c for c in range(channels) if c not in constant_channels)


def split_constant(
    images: np.ndarray, code_channels: Sequence[int], constant_channels: Sequence[int]
) -> tuple[np.ndarray, np.ndarray]:
    """Image stacks (T, C, H, W) -> (varying channels (T, Cv, H, W), constant codes (T, Cc)).

    Raises ``ValueError`` naming the first channel and frame where a constant channel varies.
    """
    const = images[:, list(constant_channels), 0, 0]
    varies = images[:, list(constant_channels)] != const[..., None, None]
    if varies.any():
        t, c = np.argwhere(varies.any(axis=(2, 3)))[0]
        raise ValueError(
            f"channel {constant_channels[c]} must be constant over each image "
            f"(the tiled jaw code) but varies in frame {t}"
        )
    return images[:, list(code_channels)], const


def tile_constant(
    codes: np.ndarray,
    constant: np.ndarray,
    code_channels: Sequence[int],
    constant_channels: Sequence[int],
) -> np.ndarray:
    """Inverse of ``split_constant`` for any leading axes: varying codes (..., Cv, H, W) and constant
    codes (..., Cc) -> the full uint8 stack (..., C, H, W), each constant code tiled over (H, W)."""
    *lead, _, H, W = codes.shape
    out = np.empty((*lead, len(code_channels) + len(constant_channels), H, W), DTYPE)
    out[..., list(code_channels), :, :] = codes
    out[..., list(constant_channels), :, :] = constant[..., None, None]
    return out
