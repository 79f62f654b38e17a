"""`mea demos` records only successful scripted demonstrations, alternating styles, to MCAP."""

from __future__ import annotations

import json

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
