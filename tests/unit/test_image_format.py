"""The policy image's one uint8 format: jaw codes, the network decode (numpy and torch alike), the
constant-channel split and tiling, and that both image kinds write this layout."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from services.algorithms.policy import images_from_codes
from services.observation import image_format as fmt
from services.observation.depth_image import policy_images
from services.observation.projection import dequantize, quantize, quantized_observations

pytestmark = pytest.mark.unit

ALL_CODES = np.arange(256, dtype=np.uint8)


def test_layout_constants() -> None:
    assert (fmt.DEPTH_CHANNEL, fmt.JAW_CHANNEL, fmt.N_CHANNELS) == (0, 1, 2)
    assert fmt.CONSTANT_CHANNELS == (fmt.JAW_CHANNEL,)
    assert np.uint8 == fmt.DTYPE and fmt.CODE_MAX == 255
    assert fmt.code_channels(fmt.N_CHANNELS, fmt.CONSTANT_CHANNELS) == (fmt.DEPTH_CHANNEL,)
    assert fmt.code_channels(4, (1, 3)) == (0, 2)


def test_jaw_codes_reference_values() -> None:
    jaw = np.array([0.0, 1.0, 0.5, -0.2, 1.3, 0.3, 0.7, 0.1])
    codes = fmt.encode_jaw(jaw)
    assert codes.dtype == np.uint8
    # 0.5 * 255 = 127.5 rounds half to even; out-of-range openings clip to 0 and 255
    assert codes.tolist() == [0, 255, 128, 0, 255, 76, 178, 26]
    # the same openings taken as float32 first: float32(0.3) * 255 = 76.500003 rounds up
    assert fmt.jaw_codes(jaw).tolist() == [0, 255, 128, 0, 255, 77, 178, 26]
    assert np.array_equal(fmt.jaw_codes(jaw), fmt.encode_jaw(jaw.astype(np.float32)))


def test_jaw_round_trip() -> None:
    assert np.array_equal(fmt.encode_jaw(fmt.decode_jaw(ALL_CODES)), ALL_CODES)
    jaw = np.random.default_rng(0).random(10_000)
    assert np.abs(fmt.decode_jaw(fmt.encode_jaw(jaw)) - jaw).max() <= 1 / 510 + 1e-7


def test_decode_reference_values_and_round_trip() -> None:
    x = fmt.decode(np.array([0, 1, 128, 254, 255], np.uint8))
    assert x.dtype == np.float32
    assert x.view(np.uint32).tolist() == [0, 998277249, 1056997505, 1065287424, 1065353216]
    assert x[0] == 0.0 and x[-1] == 1.0
    # decode multiplies by float32(1/255); decode_jaw divides by 255 and differs in the last bit here
    assert fmt.decode_jaw(np.array([254], np.uint8)).view(np.uint32)[0] == 1065287423
    assert np.array_equal(np.rint(fmt.decode(ALL_CODES) * fmt.CODE_MAX).astype(np.uint8), ALL_CODES)


def test_torch_decode_is_the_numpy_decode_bit_for_bit() -> None:
    codes = np.random.default_rng(1).integers(0, 256, (3, 7, fmt.N_CHANNELS, 16, 16), dtype=np.uint8)
    codes[0, 0, 0, 0, :] = ALL_CODES[:16]
    for batch in (ALL_CODES, codes):
        ours = fmt.decode(batch)
        theirs = images_from_codes(torch.from_numpy(batch)).numpy()
        assert theirs.dtype == ours.dtype == np.float32
        assert np.array_equal(theirs.view(np.uint32), ours.view(np.uint32))


def test_encode_stacks_depth_codes_and_tiled_jaw() -> None:
    rng = np.random.default_rng(2)
    depth = rng.integers(0, 256, (4, 6, 6), dtype=np.uint8)
    jaw = np.array([0.0, 0.3, 1.0, 0.5], np.float32)
    images = fmt.encode(depth, jaw)
    assert images.shape == (4, 2, 6, 6) and images.dtype == np.uint8
    assert np.array_equal(images[:, fmt.DEPTH_CHANNEL], depth)
    assert np.array_equal(
        images[:, fmt.JAW_CHANNEL], np.broadcast_to(fmt.jaw_codes(jaw)[:, None, None], (4, 6, 6))
    )
    assert images[:, fmt.JAW_CHANNEL, 0, 0].tolist() == [0, 77, 255, 128]


def test_split_and_tile_round_trip() -> None:
    rng = np.random.default_rng(3)
    images = fmt.encode(rng.integers(0, 256, (5, 8, 8), dtype=np.uint8), rng.random(5))
    codes, const = fmt.split_constant(images, (0,), fmt.CONSTANT_CHANNELS)
    assert codes.shape == (5, 1, 8, 8) and const.shape == (5, 1)
    assert np.array_equal(const[:, 0], images[:, fmt.JAW_CHANNEL, 0, 0])
    assert np.array_equal(fmt.tile_constant(codes, const, (0,), fmt.CONSTANT_CHANNELS), images)
    # any leading axes: a (B, L+1, ...) batch of stored rows tiles the same way
    batch = fmt.tile_constant(codes[None].repeat(2, 0), const[None].repeat(2, 0), (0,), (1,))
    assert batch.shape == (2, 5, 2, 8, 8) and np.array_equal(batch[1], images)


def test_split_refuses_a_varying_constant_channel() -> None:
    images = fmt.encode(np.zeros((4, 3, 3), np.uint8), np.zeros(4))
    images[2, fmt.JAW_CHANNEL, 1, 1] = 9
    with pytest.raises(
        ValueError, match=r"^channel 1 must be constant over each image .* varies in frame 2$"
    ):
        fmt.split_constant(images, (0,), fmt.CONSTANT_CHANNELS)


def test_both_image_kinds_write_this_layout() -> None:
    rng = np.random.default_rng(4)
    jaw = rng.random(3).astype(np.float32)
    points = rng.uniform(-0.1, 0.05, (3, 50, 3))
    voxel = quantized_observations(points, jaw)
    depth = policy_images(rng.uniform(0.0, 0.5, (3, 84, 84)), jaw)
    for images in (voxel, depth):
        assert images.dtype == fmt.DTYPE and images.shape[1] == fmt.N_CHANNELS
        _, const = fmt.split_constant(images, (0,), fmt.CONSTANT_CHANNELS)
        assert np.array_equal(const[:, 0], fmt.jaw_codes(jaw))
    # the float stack's quantize / dequantize use the same jaw codes and their exact inverse
    q = quantize(dequantize(voxel))
    assert np.array_equal(q[:, fmt.JAW_CHANNEL], voxel[:, fmt.JAW_CHANNEL])
