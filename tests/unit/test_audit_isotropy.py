"""The simulator-isotropy probe of `mea audit`: a pushed block's slide read in its own frame."""

from __future__ import annotations

import pytest

from services.augmenter.audit_isotropy import drag_isotropy, spread
from services.tasks import EnvSettings, make_env


@pytest.fixture(scope="module")
def pull_env():
    env = make_env("block_pull", EnvSettings())
    yield env
    env.close()


@pytest.mark.timeout(60)
def test_a_quarter_turn_of_a_square_block_slides_alike_and_is_read_in_its_own_frame(pull_env):
    rows = drag_isotropy(pull_env, angles_deg=(0.0, 45.0, 90.0))
    assert [r["yaw (deg)"] for r in rows] == [0.0, 45.0, 90.0]
    first, _, quarter = rows
    assert first["along (mm)"] > 50.0  # it slid
    assert abs(first["own turn (deg)"]) < 1.0  # and did not tip or spin
    # a square footprint turned by 90 degrees is the same body: same slide, along its push
    assert quarter["along (mm)"] == pytest.approx(first["along (mm)"], abs=0.5)
    assert abs(quarter["across (mm)"]) < 0.5
    s = spread(rows)
    along = [r["along (mm)"] for r in rows]
    assert s["along spread (mm)"] == pytest.approx(max(along) - min(along))
    assert s["max sideways (mm)"] == pytest.approx(max(abs(r["across (mm)"]) for r in rows))


@pytest.mark.timeout(60)
def test_a_drawer_has_no_free_body_to_push():
    env = make_env("drawer_open", EnvSettings())
    try:
        assert drag_isotropy(env) == []
    finally:
        env.close()
    assert spread([]) == {}
