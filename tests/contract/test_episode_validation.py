"""Episode-specific validation: finite arrays, action and jaw bounds, step counts, end flags, segments."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from proto.codec import decode
from proto.msgpack_wire import pack
from tests.helpers.wire_asserts import field_error
from tests.helpers.wire_samples import episode_wire

pytestmark = pytest.mark.contract


@pytest.mark.parametrize(
    "name", ["points", "jaw", "actions", "rewards", "gripper_pose", "object_poses", "images"]
)
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_in_finite_arrays(name: str, bad: float) -> None:
    wire = episode_wire(images=True, min_S=2)
    arr = wire[name].astype(np.float32) if name == "images" else wire[name]
    arr.reshape(-1)[arr.size // 2] = bad
    wire[name] = arr
    assert field_error(wire).field == f"Episode.{name}"


@pytest.mark.parametrize("bad", [1.0001, -1.0001, 2.0, -50.0])
def test_action_out_of_bounds(bad: float) -> None:
    wire = episode_wire()
    wire["actions"][-1, -1] = bad
    err = field_error(wire)
    assert err.field == "Episode.actions"


@pytest.mark.parametrize("bad", [-0.01, 1.01])
def test_jaw_out_of_bounds(bad: float) -> None:
    wire = episode_wire()
    wire["jaw"][0] = bad
    assert field_error(wire).field == "Episode.jaw"


def grow(a: np.ndarray, axis: int, by: int) -> np.ndarray:
    """``a`` with ``by`` rows added (by > 0) or removed (by < 0) along ``axis``."""
    if by < 0:
        return np.take(a, range(a.shape[axis] + by), axis=axis)
    pad = np.take(a, [0] * by, axis=axis)
    return np.concatenate([a, pad], axis=axis)


@pytest.mark.parametrize(
    ("name", "axis", "by"),
    [
        ("actions", 0, +1),  # T+2 rows of actions for T+1 observations
        ("actions", 0, -1),
        ("rewards", 0, +1),
        ("terminated", 0, -1),
        ("truncated", 0, +1),
        ("jaw", 0, -1),
        ("point_counts", 0, +1),
        ("gripper_pose", 0, +1),
        ("object_poses", 0, -1),
        ("contacts", 0, +1),
        ("images", 0, +1),
        ("point_counts", 1, +1),  # S segments
        ("contacts", 1, +1),  # S-1 objects, as in object_poses
        ("object_poses", 1, -1),  # S-1 is tied to the S of points
        ("actions", 1, +1),  # fixed dims
        ("gripper_pose", 1, -1),
        ("points", 3, +1),
    ],
)
def test_inconsistent_step_counts(name: str, axis: int, by: int) -> None:
    wire = episode_wire(images=True, min_T=2, min_S=2)
    wire[name] = grow(wire[name], axis, by)
    err = field_error(wire)
    assert err.field == f"Episode.{name}", err


def test_objects_axis_must_be_one_fewer_than_segments() -> None:
    wire = episode_wire(min_S=3)
    wire["object_poses"] = grow(wire["object_poses"], 1, +1)
    wire["contacts"] = grow(wire["contacts"], 1, +1)
    assert field_error(wire).field == "Episode.object_poses"


def test_points_bind_the_step_count() -> None:
    # points come first: with one more observation row everything after it is inconsistent
    wire = episode_wire(min_T=2)
    wire["points"] = grow(wire["points"], 0, +1)
    assert field_error(wire).field == "Episode.point_counts"


def test_episode_needs_a_step() -> None:
    wire = episode_wire()
    for name in ("points", "point_counts", "jaw", "gripper_pose", "object_poses", "contacts"):
        wire[name] = wire[name][:1]
    for name in ("actions", "rewards", "terminated", "truncated"):
        wire[name] = wire[name][:0]
    assert field_error(wire).field == "Episode.actions"
    wire["points"] = wire["points"][:0]
    assert field_error(wire).field == "Episode.points"


@pytest.mark.parametrize("flag", ["terminated", "truncated"])
def test_end_flag_on_a_non_final_step(flag: str) -> None:
    wire = episode_wire(min_T=2)
    wire[flag][0] = True
    assert field_error(wire).field == "Episode.terminated"


def test_neither_flag_on_the_last_step() -> None:
    wire = episode_wire()
    wire["terminated"][:] = False
    wire["truncated"][:] = False
    assert field_error(wire).field == "Episode.terminated"


def test_both_flags_on_the_last_step() -> None:
    wire = episode_wire()
    wire["terminated"][-1] = True
    wire["truncated"][-1] = True
    assert field_error(wire).field == "Episode.truncated"


@pytest.mark.parametrize(
    ("segments", "field"),
    [
        (["object_0", "gripper"], "Episode.segments"),  # gripper must come first
        (["gripper", "gripper"], "Episode.segments"),  # unique
        (["gripper"], "Episode.segments"),  # one name per point segment (S = 2)
        (["gripper", "a", "b"], "Episode.segments"),
        (["gripper", "Object-0"], "Episode.segments[1]"),  # [a-z0-9_]{1,32}
        (["gripper", ""], "Episode.segments[1]"),
        (["gripper", "x" * 33], "Episode.segments[1]"),
        (["gripper", 7], "Episode.segments[1]"),
        (["gripper"] + [f"o{i}" for i in range(16)], "Episode.segments"),  # at most 16
    ],
)
def test_bad_segment_names(segments: list[Any], field: str) -> None:
    wire = episode_wire(min_S=2)
    for name in ("points", "point_counts"):
        wire[name] = wire[name][:, :2]
    for name in ("object_poses", "contacts"):
        wire[name] = wire[name][:, :1]
    wire["segments"] = ["gripper", "object_0"]
    decode(pack(wire))  # the S = 2 episode itself is valid
    wire["segments"] = segments
    assert field_error(wire).field == field


def test_fixed_object_names_one_of_the_objects_or_none() -> None:
    wire = episode_wire(min_S=3)
    n_objects = len(wire["segments"]) - 1
    for ok in (-1, 0, n_objects - 1):
        wire["fixed_object"] = ok
        assert decode(pack(wire)).fixed_object == ok
    for bad in (n_objects, -2, 16):
        wire["fixed_object"] = bad
        assert field_error(wire).field == "Episode.fixed_object", bad
    del wire["fixed_object"]
    assert decode(pack(wire)).fixed_object == -1  # producers that do not know it leave it out


def test_negative_point_count() -> None:
    wire = episode_wire()
    wire["point_counts"][0, 0] = -1
    assert field_error(wire).field == "Episode.point_counts"


def test_wrong_dtype_refused() -> None:
    wire = episode_wire()
    wire["points"] = wire["points"].astype(np.float64)
    assert field_error(wire).field == "Episode.points"
    wire = episode_wire()
    wire["point_counts"] = wire["point_counts"].astype(np.int64)
    assert field_error(wire).field == "Episode.point_counts"


def test_phase_split_beyond_last_step() -> None:
    wire = episode_wire(augmented=True)
    wire["augmentation"]["phase_split"] = len(wire["actions"]) + 1
    assert field_error(wire).field == "Episode.augmentation.phase_split"
    wire["augmentation"]["kind"] = "rotate"
    assert field_error(wire).field == "Episode.augmentation.kind"
