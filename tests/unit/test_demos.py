"""`mea demos` records only successful scripted demonstrations, alternating styles, to MCAP."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.actor.demos import DemosConfig, record
from services.common.mcap_io import read_messages, read_metadata

pytestmark = pytest.mark.unit


@pytest.mark.timeout(120)
def test_demos_are_successful_alternating_and_readable(tmp_path):
    out = tmp_path / "demos.mcap"
    result = record(DemosConfig(task="block_pick", n=2, out=out))
    assert result["kept"] == 2
    episodes = [m for _, m in read_messages(out)]
    assert [e.policy_kind for e in episodes] == ["expert_probe", "expert_direct"]
    assert all(e.is_demo and e.terminated[-1] and e.rewards[-1] == 1.0 for e in episodes)
    # the probe demonstration touches both objects (the fixed one first); direct only the movable one
    probe, direct = episodes
    assert probe.contacts.any(axis=0).all()
    assert direct.contacts.any(axis=0).sum() == 1
    meta = read_metadata(out)
    assert json.loads(meta["config/demos"]["json"])["n"] == 2
    assert meta["seeds"]["seeds"] == ",".join(str(e.seed) for e in episodes)


@pytest.mark.timeout(120)
def test_surgical_demos_are_oracle_grasps_that_record_the_executed_actions(tmp_path):
    from proto.discrete_actions import index_of

    out = tmp_path / "surgical.mcap"
    result = record(DemosConfig(task="surgical_grasp_any", n=2, out=out))
    assert result["kept"] == 2 and result["attempts"] == 2
    episodes = [m for _, m in read_messages(out)]
    for e in episodes:
        assert e.policy_kind == "expert_direct" and e.is_demo and e.fixed_object == -1
        assert e.segments == ["gripper", "object_0"] and e.succeeded and e.rewards[-1] == 1.0
        assert e.terminated[-1] and not e.truncated.any()
        # the hybrid controller's approach first (continuous moves, saturated at one discrete step of
        # 0.3 cm real, 0.015 sim units, per axis: the same scale as the policy's actions), then the
        # oracle's discrete actions only, ending in a closing and lifts
        steps = np.abs(np.diff(e.gripper_pose[:, :3], axis=0)).max(axis=1)
        assert steps[0] == pytest.approx(0.015, abs=5e-4) and (steps < 0.015 + 5e-4).all()
        assert index_of(e.actions[0], True) is None  # a diagonal move: not one of the nine
        jaw_open, indices = True, []
        for a in e.actions:
            indices.append(index_of(a, jaw_open))
            jaw_open = bool(a[0] > 0)
        assert indices[-3:] == [8, 4, 4]  # close, then lift 2 x 0.3 cm real
