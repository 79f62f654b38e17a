"""Video frames and files: the scene beside the policy's image over a caption whose text is drawn in
the outcome's colour; MP4 and GIF read back with imageio at the frame count and size written; a bad
--out is refused before anything is written."""

from __future__ import annotations

import imageio.v2 as imageio
import numpy as np
import pytest

from services.evaluator.video import CAPTION, COLOURS, check_out, compose, policy_view, write

pytestmark = pytest.mark.unit
SIZE = 128


def _pictures(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    scene = rng.integers(0, 256, (SIZE, SIZE, 3), np.uint8)
    policy = policy_view(rng.integers(0, 256, (2, 84, 84), np.uint8), SIZE)
    return scene, policy


def test_policy_view_keeps_each_policy_pixel_and_colour_images():
    codes = np.zeros((2, 84, 84), np.uint8)
    codes[0, 10, 20] = 200
    codes[1] = 255  # the jaw channel is not shown
    view = policy_view(codes, 168)
    assert view.shape == (168, 168, 3) and view.dtype == np.uint8
    assert (view[20:22, 40:42] == 200).all() and view.sum() == 200 * 4 * 3  # one pixel, 2x2, grey
    dsa = np.zeros((3, 64, 64), np.uint8)
    dsa[0] = 255  # a red DSA image stays red
    assert (policy_view(dsa, 64)[..., 0] == 255).all() and policy_view(dsa, 64)[..., 1:].max() == 0


def test_frame_holds_both_pictures_and_the_outcome_drawn_in_its_colour():
    scene, policy = _pictures()
    lines = ("v7 at 1,000 env steps  episode 1 seed 1000000000", "step 3/50  failure  return 0")
    frame = compose(scene, policy, lines, "failure")
    bare = compose(scene, policy, ())
    assert frame.shape == bare.shape == (SIZE + CAPTION, 2 * SIZE, 3)
    assert np.array_equal(frame[:SIZE, :SIZE], scene) and np.array_equal(frame[:SIZE, SIZE:], policy)
    assert not bare[SIZE:].any()  # without text the caption is black
    text = np.abs(frame[SIZE:].astype(int) - bare[SIZE:]).sum(axis=-1) > 0
    assert text.sum() > 200  # the lines were drawn
    second = frame[SIZE + CAPTION // 2 :]  # the outcome line, in the failure colour
    assert (second == COLOURS["failure"]).all(axis=-1).sum() > 20
    assert not (second == COLOURS["success"]).all(axis=-1).any()
    success = compose(scene, policy, lines, "success")[SIZE + CAPTION // 2 :]
    assert (success == COLOURS["success"]).all(axis=-1).sum() > 20
    alone = compose(None, policy, lines)  # a recording without a simulator: the policy's image only
    assert alone.shape == (SIZE + CAPTION, SIZE, 3) and np.array_equal(alone[:SIZE], policy)


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_videos_read_back_with_their_frame_count_and_size(tmp_path, suffix):
    frames = [compose(*_pictures(i), (f"frame {i}",)) for i in range(7)]
    path = write(tmp_path / f"v{suffix}", frames, fps=10)
    with imageio.get_reader(path) as reader:  # its len() is inf for an MP4: iterate
        got = [frame for frame in reader]
    assert len(got) == 7 and got[0].shape[:2] == (SIZE + CAPTION, 2 * SIZE)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"v{suffix}"]  # no temporary file left


@pytest.mark.parametrize(
    ("name", "problem"),
    [
        ("v.avi", "must end in .mp4 or .gif"),
        ("no/such/dir/v.mp4", "no such directory"),
        ("d.mp4", "is a directory"),
    ],
)
def test_a_bad_out_is_refused(tmp_path, name, problem):
    (tmp_path / "d.mp4").mkdir()
    with pytest.raises(ValueError, match=problem):
        check_out(tmp_path / name)
