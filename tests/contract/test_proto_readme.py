"""proto/README.md sections 3 to 5 against the code they describe.

The hand-written sections (episode geometry, point clouds, images, ``Augmentation.params``, MCAP
recordings) are checked against the constants and the behaviour of the code: a key, metadata name,
channel or constant added or changed in the code without the README following fails here.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import re
import shutil
import zlib
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

import proto
from proto.actions import DELTA_THETA, DELTA_XYZ
from proto.seeds import MEA_COPY_SEED_OFFSET, SHARED_ROTATION_STREAM
from services.augmenter.core.mea_discrete import MeaDiscreteSettings
from services.augmenter.core.pipeline import (
    AUGMENTATION_PARAM_KEYS,
    AugmentSettings,
    augment_episode,
    episode_seed,
)
from services.common.mcap_io import (
    CONFIG_METADATA_PREFIX,
    LIBRARY,
    MAX_CHUNK_BYTES,
    MESSAGE_ENCODING,
    PROFILE,
    RECORDING_METADATA,
    RUN_METADATA,
    SCHEMA_ENCODING,
    TMP_SUFFIX,
    McapRecorder,
    default_topic,
    read_metadata,
    recover,
)
from services.common.mcap_io.layout import MAGIC
from services.common.retention import segment_name
from services.observation import image_format
from services.observation.depth_image import DEFAULT_DEPTH_SPEC, depth_codes
from services.observation.projection import DEFAULT_SPEC, quantize_depth
from services.run_config import RunConfig, recording_metadata
from tests.helpers import build_episode
from tests.helpers.synthetic import synthetic_episode, synthetic_surgical_episode

pytestmark = pytest.mark.contract

README = Path(proto.__file__).with_name("README.md").read_text(encoding="utf-8")


def section(number: int) -> str:
    """The text of the README's ``## <number>.`` section, up to the next ``## `` heading."""
    m = re.search(rf"^## {number}\. .*?(?=^## |\Z)", README, re.M | re.S)
    assert m, f"proto/README.md has no section {number}"
    return m.group(0)


EPISODE, AUGMENTATION, RECORDINGS = section(3), section(4), section(5)


def flat(text: str) -> str:
    """``text`` with every run of whitespace (line breaks included) as one space."""
    return " ".join(text.split())


def table_row(text: str, first_cell: str) -> str:
    """The table row of ``text`` whose first cell is ``first_cell``."""
    rows = [line for line in text.splitlines() if line.startswith(f"| {first_cell} |")]
    assert len(rows) == 1, f"expected one table row starting with {first_cell!r}, found {len(rows)}"
    return rows[0]


def backticked(text: str) -> set[str]:
    return set(re.findall(r"`([^`]+)`", text))


# ------------------------------------------------------------------------------------------------
# 4. Augmentation.params
# ------------------------------------------------------------------------------------------------


def produced_params() -> dict[str, set[str]]:
    """Every ``params`` key the augmenter actually writes, with the dtype names it writes it with."""
    keys: dict[str, set[str]] = {}
    settings = AugmentSettings(mea_on="all", reproject=False)
    for seed in range(3):
        raw, _ = synthetic_episode(seed)
        out, stats = augment_episode(raw, settings)
        assert stats.mea_made > 0, "the synthetic episode must give MEA copies"
        for ep in out[1:]:
            for key, value in ep.augmentation.params.items():
                keys.setdefault(key, set()).add(value.dtype.name)
    discrete = dataclasses.replace(settings, mea_discrete=MeaDiscreteSettings(copies=3))
    for seed in range(2):  # the discrete-action task's MEA copies
        out, stats = augment_episode(synthetic_surgical_episode(seed), discrete)
        assert stats.mea_made > 0, "the synthetic surgical episode must give MEA copies"
        for ep in out[1:]:
            for key, value in ep.augmentation.params.items():
                keys.setdefault(key, set()).add(value.dtype.name)
    return keys


def test_every_augmentation_param_key_is_documented_with_its_dtype() -> None:
    produced = produced_params()
    assert set(produced) == set(AUGMENTATION_PARAM_KEYS)
    for key, dtypes in produced.items():
        row = table_row(AUGMENTATION, f"`{key}`")
        for dtype in dtypes:
            assert dtype in row, (key, dtype, row)


def test_the_params_table_lists_no_other_key() -> None:
    rows = [line for line in AUGMENTATION.splitlines() if line.startswith("| `")]
    documented = {re.match(r"\| `([^`]+)` \|", line).group(1) for line in rows}
    assert documented == set(AUGMENTATION_PARAM_KEYS)


def test_copy_seeds_are_as_documented() -> None:
    for base, episode_id in [(0, "actor-0-5-1"), (7, "x"), (2**40, "demos-123-0")]:
        expected = (zlib.crc32(episode_id.encode("utf-8")) ^ (base * 0x9E3779B1)) & (2**63 - 1)
        assert episode_seed(base, episode_id) == expected
    assert "`(crc32(utf8(episode_id)) XOR (base · 0x9E3779B1)) & (2^63 - 1)`" in AUGMENTATION
    assert f"`default_rng([seed, {MEA_COPY_SEED_OFFSET:_} + k])`" in AUGMENTATION
    assert f"`default_rng([seed, {SHARED_ROTATION_STREAM:_}])`" in AUGMENTATION


# ------------------------------------------------------------------------------------------------
# 5. MCAP recordings
# ------------------------------------------------------------------------------------------------


def test_mcap_layout_constants_are_documented() -> None:
    names = backticked(RECORDINGS)
    for value in (PROFILE, LIBRARY, MESSAGE_ENCODING, SCHEMA_ENCODING, RUN_METADATA, RECORDING_METADATA):
        assert value in names, value
    assert default_topic("<_type>") in names
    assert CONFIG_METADATA_PREFIX + "<name>" in names
    assert f"<path>{TMP_SUFFIX}" in names
    assert MAX_CHUNK_BYTES == 2**30 and "1 GiB uncompressed (`MAX_CHUNK_BYTES`)" in flat(RECORDINGS)
    assert " ".join(f"{b:02X}" for b in MAGIC) in flat(RECORDINGS)
    defaults = inspect.signature(McapRecorder).parameters
    assert defaults["chunk_size"].default == 2**20 and "`chunk_size` (default 1 MiB)" in flat(RECORDINGS)
    flush = defaults["flush_interval_s"].default
    assert f"`flush_interval_s` (default {flush:g} s)" in flat(RECORDINGS)
    assert f"compression `{defaults['compression'].default}`" in flat(RECORDINGS)


def _metadata_row(name: str) -> str:
    return table_row(RECORDINGS, f"`{name}`")


def test_a_recording_holds_the_documented_records(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    custom_topic = "mea/v1/default/episodes/raw/actor-0"
    with McapRecorder(path, metadata={"task": "block_pull"}) as rec:
        rec.write_config("demo", '{"a": 1}')
        rec.write(build_episode())
        rec.write(build_episode(), topic=custom_topic)
    names = backticked(RECORDINGS)
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
    assert (header.profile, header.library) == (PROFILE, LIBRARY)
    for schema in summary.schemas.values():
        assert schema.encoding in names and schema.name == "Episode"
    assert {ch.topic for ch in summary.channels.values()} == {default_topic("Episode"), custom_topic}
    for channel in summary.channels.values():
        assert channel.message_encoding in names
        assert set(channel.metadata) == {"type", "version"}
        for key in channel.metadata:
            assert f"`{key}`" in table_row(RECORDINGS, "channel")
    meta = read_metadata(path)
    assert set(meta) == {RUN_METADATA, CONFIG_METADATA_PREFIX + "demo", RECORDING_METADATA}
    assert set(meta[CONFIG_METADATA_PREFIX + "demo"]) <= backticked(_metadata_row("config/<name>"))
    recording = meta[RECORDING_METADATA]
    assert recording["status"] == "complete" and "complete" in backticked(_metadata_row(RECORDING_METADATA))
    assert set(recording) <= backticked(_metadata_row(RECORDING_METADATA))


def test_schemas_and_channels_live_inside_chunks(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with McapRecorder(path) as rec:
        rec.write(build_episode())
    top_level = []
    with open(path, "rb") as f:
        for record in StreamReader(f, emit_chunks=True).records:
            top_level.append(type(record).__name__)
            if type(record).__name__ == "DataEnd":
                break
    assert "Chunk" in top_level
    assert not {"Schema", "Channel", "Message"} & set(top_level)
    assert top_level.index("Metadata") < top_level.index("Chunk"), "`recording` precedes the last chunk"


def test_aborted_and_recovered_recordings_use_documented_keys(tmp_path: Path) -> None:
    row = backticked(_metadata_row(RECORDING_METADATA))
    aborted = tmp_path / "aborted.mcap"
    with pytest.raises(RuntimeError), McapRecorder(aborted) as rec:
        rec.write(build_episode())
        raise RuntimeError("boom")
    status = read_metadata(aborted)[RECORDING_METADATA]
    assert status["status"] == "aborted" and status["status"] in row
    assert set(status) <= row and "error" in status

    live = tmp_path / "live.mcap"
    crashed = tmp_path / f"crashed.mcap{TMP_SUFFIX}"
    rec = McapRecorder(live)
    rec.write(build_episode())
    rec.flush()
    shutil.copyfile(rec.tmp_path, crashed)  # what a killed recorder leaves behind
    rec.close()
    out = tmp_path / "recovered.mcap"
    assert recover(crashed, out=out) == 1
    status = read_metadata(out)[RECORDING_METADATA]
    assert status["status"] == "recovered" and status["status"] in row
    assert set(status) <= row


def test_mea_run_and_demos_metadata_are_documented(tmp_path: Path) -> None:
    from services.actor.demos import (
        CONFIG_NAME,
        SEEDS_METADATA,
        DemosConfig,
        run_metadata,
        seeds_metadata,
    )

    run_row = backticked(_metadata_row(RUN_METADATA))
    assert set(recording_metadata(RunConfig())) <= run_row
    demos = run_metadata(DemosConfig(out=tmp_path / "d.mcap"))
    assert set(demos) <= run_row and demos["kind"] in run_row
    assert set(seeds_metadata([1, 2], 3)) <= backticked(_metadata_row(SEEDS_METADATA))
    assert CONFIG_METADATA_PREFIX + CONFIG_NAME in backticked(RECORDINGS)
    assert f"`{DemosConfig.__dataclass_fields__['out'].default}`" in RECORDINGS
    assert segment_name(3, 12) == "raw-3-0012.mcap"
    assert "`RUN_DIR/episodes/raw-<resumes>-<k>.mcap`" in RECORDINGS


# ------------------------------------------------------------------------------------------------
# 3. Episode contents: images
# ------------------------------------------------------------------------------------------------


def test_every_policy_image_channel_is_documented() -> None:
    channels = {
        name: getattr(image_format, name) for name in image_format.__all__ if name.endswith("_CHANNEL")
    }
    assert len(channels) == image_format.N_CHANNELS
    for name, index in channels.items():
        table_row(EPISODE, f"{index} | `{name}`")
    size = DEFAULT_SPEC.size
    assert f"uint8 (T+1, {image_format.N_CHANNELS}, {size}, {size})" in EPISODE
    assert DEFAULT_DEPTH_SPEC.size == size and f"float16 (T+1, 1, {size}, {size})" in EPISODE
    assert image_format.CODE_MAX == 255 and np.uint8 == image_format.DTYPE
    jaw = np.linspace(0.0, 1.0, 1001, dtype=np.float32)
    codes = image_format.jaw_codes(jaw)
    assert np.array_equal(codes, np.rint(np.clip(jaw.astype(np.float64), 0, 1) * 255).astype(np.uint8))
    assert np.array_equal(image_format.decode_jaw(codes), codes.astype(np.float32) / np.float32(255))


def test_voxel_depth_codes_are_as_documented() -> None:
    s = DEFAULT_SPEC
    assert (s.size, s.voxel, s.z_top, s.depth) == (84, 0.4 / 84, 0.1, 0.6)
    assert "`size` 84, `voxel` v = 0.4/84 m, `z_top` 0.1 m, `depth` 0.6 m" in EPISODE
    levels = round(s.depth / s.voxel)
    k = np.arange(levels)
    documented = np.where(k <= 63, 2 * k + 1, 2 * k + 2)
    assert np.array_equal(quantize_depth(s.depth_levels[:levels], s), documented)
    assert f"`64 <= k_min <= {levels - 1}`" in EPISODE
    assert math.isclose(s.quant_step, (s.depth + s.voxel) / 255) and "`s = (0.6 + v)/255` m" in EPISODE
    assert quantize_depth(np.zeros(1), s)[0] == 0


def test_rendered_depth_codes_are_as_documented() -> None:
    from services.tasks.camera import FINGER_THICKNESS, FINGER_WIDTH, render_gripper_depth

    far = DEFAULT_DEPTH_SPEC.far
    defaults = inspect.signature(render_gripper_depth).parameters
    assert defaults["far"].default == far == 0.5 and defaults["span"].default == 0.4
    assert defaults["height"].default == 0.06 and "0.06 m above the pivot, clipped to [0, 0.5]" in EPISODE
    assert (FINGER_THICKNESS, FINGER_WIDTH) == (0.012, 0.025) and "12 mm x 25 mm" in EPISODE
    n = DEFAULT_DEPTH_SPEC.size
    q = np.resize(np.arange(256), (n, n))  # every code, a few times over
    assert np.array_equal(depth_codes(q * far / 255), q)
    assert np.array_equal(depth_codes(np.full((n, n), far + 1.0)), np.full((n, n), 255))
    assert "`q = rint(clip(d, 0, 0.5) / 0.5 ·" in EPISODE and "`d = q · 0.5/255`" in EPISODE


# ------------------------------------------------------------------------------------------------
# 3. Episode contents: frame, yaw, resampling, objects
# ------------------------------------------------------------------------------------------------


def test_frame_and_yaw_constants_are_documented() -> None:
    from services.geometry import rotate_z, wrap_angle
    from services.tasks import EnvSettings
    from services.tasks.robot import (
        BASE_POSITION,
        FINGER_JOINTS,
        FLANGE_LINK,
        GRIPPER_LINKS,
        JAW_CLOSED_ANGLE,
        JAW_OPEN_ANGLE,
        WORKSPACE,
        YAW_LIMIT,
        YAW_OFFSET,
    )

    text = flat(EPISODE)
    assert math.pi == YAW_OFFSET and "`YAW_OFFSET = π`" in text
    assert f"[-{YAW_LIMIT}, {YAW_LIMIT}] (`YAW_LIMIT`)" in text
    assert f"link {FLANGE_LINK}, `FLANGE_LINK`" in text
    assert (JAW_CLOSED_ANGLE, JAW_OPEN_ANGLE, FINGER_JOINTS[1]) == (-0.05, 0.3, 11)
    assert "`clip((a + 0.05) / 0.35, 0, 1)` of the angle `a` (rad) of finger joint 11" in text
    assert tuple(GRIPPER_LINKS) == tuple(range(7, 14)) and "links 7 to 13, `GRIPPER_LINKS`" in text
    assert BASE_POSITION == (-0.2, 0.0, 0.0) and "robot base stands at (-0.2, 0, 0)" in text
    (x0, x1), (y0, y1), (z0, z1) = WORKSPACE.tolist()
    assert f"x in [{x0}, {x1}], y in [{y0}, {y1}] for the pivot and z in [{z0}, {z1}]" in text
    assert EnvSettings().initial_tip_height == 0.2 and "finger tips at 0.2 m" in text
    assert (0.05, math.pi / 8) == (DELTA_XYZ, DELTA_THETA) and "`a · 0.05 m`" in text and "`a · π/8`" in text
    # a quarter turn takes (x, y) to (-y, x); wrapped yaws lie in [-pi, pi)
    np.testing.assert_allclose(
        rotate_z(np.array([[2.0, 1.0, 3.0]]), math.pi / 2), [[-1.0, 2.0, 3.0]], atol=1e-12
    )
    assert "a quarter turn takes (x, y) to (-y, x)" in text
    assert (
        wrap_angle(math.pi) == -math.pi and wrap_angle(-math.pi) == -math.pi and "range **[-π, π)**" in text
    )


def test_yaw_zero_closes_the_jaw_along_world_x() -> None:
    import pybullet as pb

    from services.tasks.robot import TIP_JOINTS, Robot

    client = pb.connect(pb.DIRECT)
    try:
        robot = Robot(client)
        for yaw in (0.0, 0.7, -2.0):
            robot.reset(np.array([0.5, 0.0, 0.35]), yaw, jaw=1.0)
            a, b = (np.array(pb.getLinkState(robot.body, j, physicsClientId=client)[4]) for j in TIP_JOINTS)
            across = (a - b)[:2] / np.linalg.norm((a - b)[:2])
            heading = np.array([math.cos(yaw), math.sin(yaw)])
            assert abs(abs(float(across @ heading)) - 1.0) < 1e-6, (yaw, across)
            assert abs(robot.pivot()[1] - yaw) < 1e-6
    finally:
        pb.disconnect(client)
    assert "**zero when the jaw closes along world x**" in EPISODE


def test_resampling_rule_is_as_documented() -> None:
    from services.tasks.camera import CameraSettings, sample_fixed
    from services.tasks.env import ManipulationEnv

    cam = CameraSettings()
    text = flat(EPISODE)
    assert f"(default {cam.points_per_segment}," in text
    assert cam.downsample_voxel == 0.004 and "4 mm voxels (`downsample_voxel`)" in text
    assert cam.image_size == 128 and cam.fov_deg == 42.0 and "128 x 128 px, 42° vertical" in text
    assert len(cam.views) == 5 and "Five fixed depth cameras" in text
    assert "np.random.default_rng([self.seed, self.t, 1])" in inspect.getsource(ManipulationEnv.observe)
    assert "`default_rng([seed, t, 1])`" in text
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(10, 3))
    few, n = sample_fixed(pts, 16, np.random.default_rng(1))
    assert n == 10 and np.array_equal(few[:10], pts) and all(any((p == pts).all(1)) for p in few[10:])
    many, n = sample_fixed(pts, 4, np.random.default_rng(1))
    assert n == 10 and len({tuple(p) for p in many}) == 4
    none, n = sample_fixed(np.zeros((0, 3)), 4, np.random.default_rng(1))
    assert n == 0 and not none.any() and none.shape == (4, 3)
    for phrase in ("**without replacement**", "**with replacement**", "rows of (0, 0, 0)"):
        assert phrase in text


def test_object_rows_are_as_documented() -> None:
    from services.tasks import GENERAL_TASKS, TASK_CLASSES, task_class

    for name in GENERAL_TASKS:
        assert task_class(name).object_names == ("object_0", "object_1"), name
    for name in set(TASK_CLASSES) - set(GENERAL_TASKS):
        assert task_class(name).object_names == ("object_0",), name
    assert '`surgical_grasp_any` has `segments = ["gripper", "object_0"]`' in EPISODE
    assert '`segments = ["gripper", "object_0", "object_1"]`' in EPISODE
    assert "`segments[1 + i]`" in EPISODE
