"""The robot side's hold rules and the server's per-robot limits file."""

from __future__ import annotations

import json

import pytest

from services.inference.config import ServeConfig, load_limits
from services.inference.core.envelope import Limits
from services.inference.core.robot_safety import RobotSafety


def test_hold_reasons_in_priority_order_and_the_watchdog_timeout():
    s = RobotSafety(command_timeout=0.5, require_operator=True)
    assert s.reason(0.0) == "operator_lost"
    s.operator_alive = True
    assert s.reason(0.0) == "server_lost"
    s.server_alive = True
    assert s.reason(0.0) is None  # not commanding: no watchdog
    s.last_command = 10.0
    assert s.reason(10.5) is None
    assert s.reason(10.5001) == "watchdog"
    s.estop = True
    assert s.reason(10.0) == "estop"  # an e-stop wins over everything
    assert RobotSafety(require_operator=False, server_alive=True).reason(0.0) is None


def test_limits_file_default_overlaid_per_robot(tmp_path):
    path = tmp_path / "limits.json"
    path.write_text(json.dumps({"default": {"max_translation": 0.02, "workspace_low": [-0.1, -0.1, 0.0]},
                                "robots": {"psm1": {"metres_per_unit": 0.01}}}))  # fmt: skip
    default, robots = load_limits(path)
    assert default.max_translation == 0.02 and default.workspace_low == (-0.1, -0.1, 0.0)
    assert robots["psm1"].metres_per_unit == 0.01 and robots["psm1"].max_translation == 0.02
    limits_for = ServeConfig(limits_file=str(path)).limits_for()
    assert limits_for("psm1") == robots["psm1"] and limits_for("other") == default


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("{not json", "not JSON"),
        ('{"default": {"max_speed": 1}}', "unknown key.*max_speed"),
        ('{"default": {"max_translation": -1}}', "default: .*must be > 0"),
        ('{"robots": {"psm1": {"workspace_low": [0, 0, 1], "workspace_high": [1, 1, 0.5]}}}', "robots.psm1"),
        ('{"robots": []}', "robots"),
        ('{"defaults": {}}', "default"),
    ],
)
def test_a_bad_limits_file_is_refused_naming_what_is_wrong(tmp_path, content, match):
    path = tmp_path / "limits.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=match):
        ServeConfig(limits_file=str(path))


def test_missing_limits_file(tmp_path):
    with pytest.raises(ValueError, match="cannot read"):
        load_limits(tmp_path / "nonexistent.json")
    assert ServeConfig().limits_for()("any") == Limits()
