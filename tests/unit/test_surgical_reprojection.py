"""Surgical Grasp Any MEA copies re-rendered through the env's DSA pipeline
(``pipeline.discrete_reprojector``): an unmoved row reproduces the raw image bit for bit, a row moved
by whole voxels shows the gripper where it was in its crop and the object shifted against it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from proto.episode import Episode
from services.augmenter.core.mea_discrete import MeaDiscreteSettings, mea_discrete_copies, offsets
from services.augmenter.core.pipeline import discrete_reprojector, reproject_dsa
from services.observation import dsa
from services.observation.dsa import SURGICAL_GRASP_ANY as SPEC

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def demo() -> Episode:
    """One oracle demonstration recorded as the actor records it (env images included)."""
    from services.episodes.builder import EpisodeBuilder
    from services.episodes.rollout import run_episode
    from services.tasks import make_env
    from services.tasks.surgical.oracle import Oracle

    env = make_env("surgical_grasp_any")
    try:
        b = EpisodeBuilder(task="surgical_grasp_any", seed=4, actor_id="t", policy_version=-1,
                           policy_kind="expert_direct", is_demo=True, segments=env.segment_names)  # fmt: skip
        run_episode(env, 4, lambda _o: Oracle(env).act(), b)
    finally:
        env.close()
    assert b.success
    return b.finish("demo-4")


def _voxels(ep: Episode, t: int) -> tuple[np.ndarray, np.ndarray]:
    g, o = dsa.world_clouds(ep.points[t], ep.point_counts[t], ep.gripper_pose[t, :3])
    return (dsa.voxelize(dsa.to_occupancy(g, SPEC), SPEC), dsa.voxelize(dsa.to_occupancy(o, SPEC), SPEC))


def _rows(voxels: np.ndarray) -> set[tuple[int, int, int]]:
    return set(map(tuple, voxels.tolist()))


@pytest.mark.timeout(60)
def test_the_surgical_task_has_a_reprojector_and_raw_rows_re_render_exactly(demo):
    assert discrete_reprojector("block_pull") is None
    reproject = discrete_reprojector("surgical_grasp_any")
    assert reproject is not None
    again = reproject(demo)  # the raw episode is its own unmoved copy: every row, bit for bit
    assert again.images is not demo.images and np.array_equal(again.images, demo.images)
    # the state rows come from the images it is given, not from the points
    flipped = demo.images.copy()
    a, b = dsa.state_blocks(flipped.shape[-1])[2]
    flipped[:, 2, dsa.STATE_ROW, a:b] = 255 - flipped[:, 2, dsa.STATE_ROW, a:b]  # controller_state 1 <-> 0
    states = [dsa.decode_state_rows(i) for i in reproject(dataclasses.replace(demo, images=flipped)).images]
    assert [s[2] for s in states] == [1 - dsa.decode_state_rows(i)[2] for i in demo.images]
    with pytest.raises(ValueError, match="images"):
        reproject(dataclasses.replace(demo, images=None))


@pytest.mark.timeout(60)
def test_an_unmoved_copy_carries_the_raw_images(demo):
    still = MeaDiscreteSettings(copies=2, p_rotate=0.0)  # every quarter turn 0: D_t = 0
    copies = mea_discrete_copies(demo, still, 5, discrete_reprojector(demo.task))
    assert len(copies) == 2
    for copy in copies:
        start = int(copy.augmentation.params["start"][0])
        assert np.array_equal(copy.gripper_pose, demo.gripper_pose[start:])
        assert np.array_equal(copy.images, demo.images[start:])


@pytest.mark.timeout(60)
def test_a_copy_moved_by_whole_voxels_shifts_the_object_against_the_gripper(demo):
    """D_t is a multiple of delta_xyz = 0.015 sim = 3 voxels: the copy's gripper voxels are the
    source's shifted by D_t / voxel, its object voxels the source's, and its image the DSA image of
    those sets. The crop follows the gripper, so the gripper channel does not change while the
    object channel moves by -D_t (checked pixel for pixel with a 60-pixel image: one pixel per
    voxel)."""
    copies = mea_discrete_copies(demo, MeaDiscreteSettings(copies=12), 9, discrete_reprojector(demo.task))
    per_voxel = dataclasses.replace(SPEC, image=SPEC.crop_voxels)
    theirs = reproject_dsa(demo, per_voxel).images
    S = SPEC.crop_voxels
    moved_rows = compared_pixels = 0
    for copy in copies:
        aug = copy.augmentation
        start, hp = int(aug.params["start"][0]), aug.phase_split
        D = offsets(demo.actions[start:], copy.actions, hp, 0.015)
        mine = reproject_dsa(dataclasses.replace(copy, images=demo.images[start:]), per_voxel).images
        for t in range(copy.num_steps + 1):
            shift = D[t] * SPEC.grid * SPEC.scale
            assert np.allclose(shift, np.rint(shift), atol=1e-9) and shift[2] == 0.0
            shift = np.rint(shift).astype(np.int64)
            g_src, o_src = _voxels(demo, start + t)
            g, o = _voxels(copy, t)
            assert _rows(g) == _rows(g_src + shift) and _rows(o) == _rows(o_src), (copy.episode_id, t)
            states = dsa.decode_state_rows(demo.images[start + t])
            want = dsa.dsa_image_from_voxels(g_src + shift, o_src, SPEC, gripper_state=states[0],
                                             fsm_state=states[1], controller_state=states[2])  # fmt: skip
            assert np.array_equal(copy.images[t], want)
            if not shift.any():
                assert np.array_equal(copy.images[t], demo.images[start + t])
                continue
            moved_rows += 1
            now, then = mine[t], theirs[start + t]
            assert np.array_equal(now[0], then[0])  # the gripper, where it was in its crop
            dx, dy = shift[:2]
            rows, cols = slice(max(0, -dx), min(S, S - dx)), slice(max(0, -dy), min(S, S - dy))
            src_rows, src_cols = (
                slice(rows.start + dx, rows.stop + dx),
                slice(cols.start + dy, cols.stop + dy),
            )
            assert np.array_equal(
                now[1][rows, cols], then[1][src_rows, src_cols]
            )  # the object, moved by -D_t
            compared_pixels += int((now[1][rows, cols] > 0).sum())
            if (then[1] > 0).any():
                assert not np.array_equal(now[1], then[1])
    assert moved_rows >= 20 and compared_pixels >= 100, (moved_rows, compared_pixels)
