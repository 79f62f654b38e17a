"""`mea demos --task surgical_grasp_any`, then the augmenter's ``augment_episode``: every MEA copy
carries re-rendered DSA images and survives the wire (encode, decode with the default limits)."""

from __future__ import annotations

import numpy as np
import pytest

from proto.codec import decode
from proto.episode import Episode
from services.augmenter.core.pipeline import AugmentSettings, augment_episode
from services.cli import main
from services.common.mcap_io import read_messages
from services.observation.dsa import decode_state_rows

pytestmark = pytest.mark.integration


@pytest.mark.timeout(240)
@pytest.mark.slow
def test_surgical_demos_augment_into_copies_that_validate_on_the_wire(tmp_path):
    out = tmp_path / "surgical.mcap"
    assert main(["demos", "--task", "surgical_grasp_any", "--n", "2", "--out", str(out)]) == 0
    demos = [m for _, m in read_messages(out)]
    assert len(demos) == 2
    settings = AugmentSettings()
    for demo in demos:
        assert demo.images.shape == (demo.num_steps + 1, 3, 64, 64) and demo.images.dtype == np.uint8
        outputs, stats = augment_episode(demo, settings)
        assert outputs[0] is demo and stats.outputs == len(outputs)
        copies = outputs[1:]
        assert len(copies) == stats.mea_made >= 0.9 * settings.mea_discrete.copies
        moved = 0
        for copy in copies:
            wire = copy.encode()
            back = decode(wire)
            assert isinstance(back, Episode) and back.encode() == wire
            aug = back.augmentation
            assert aug.kind == "mea" and aug.source_episode_id == demo.episode_id
            start = int(aug.params["start"][0])
            assert back.images.shape == (back.num_steps + 1, 3, 64, 64) and back.images.dtype == np.uint8
            src = demo.images[start : start + back.num_steps + 1]
            assert [decode_state_rows(i) for i in back.images] == [decode_state_rows(i) for i in src]
            same = np.all(back.gripper_pose[:, :3] == demo.gripper_pose[start:, :3], axis=1)
            assert np.array_equal(back.images[same], src[same])  # unmoved rows: the raw images
            moved += int((~same).sum())
        assert moved > 0
