"""What the services write to TensorBoard besides their means: tags given whole (eval/, charts/),
``due`` before a window's last call, the hparams records (with metrics of the services' runs) and a
Markdown table in the launcher's root run, and an animation TensorBoard decodes as a GIF of every
frame; read back with tensorboard's own event reader."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams import plugin_data_pb2

from services.common.scalars import ScalarLog, tag
from services.run_config import RunConfig
from services.tracking import settings, table

pytestmark = pytest.mark.unit


def _accumulator(log_dir) -> EventAccumulator:
    ea = EventAccumulator(str(log_dir), size_guidance={"scalars": 0, "images": 0, "tensors": 0})
    ea.Reload()
    return ea


def test_tags_with_a_prefix_are_kept():
    assert (
        tag("eval/success_rate") == "eval/success_rate" and tag("charts/weights_lag") == "charts/weights_lag"
    )
    assert tag("critic_loss") == "losses/critic_loss"


def test_due_says_the_next_add_writes(tmp_path):
    log = ScalarLog(tmp_path, every=3, suffix="x")
    dues, wrote = [], []
    for i in range(6):
        dues.append(log.due)
        wrote.append(log.add({"x": 1.0}, step=i))
    log.close()
    assert dues == wrote == [False, False, True, False, False, True]


def test_hparams_text_and_animation_land_in_the_writers_own_run(tmp_path):
    cfg = RunConfig(task="drawer_open", env_steps=1234, run_dir=tmp_path / "run")
    root = ScalarLog(tmp_path, every=1, suffix="")  # the launcher's: the run's root directory
    root.add_hparams(settings(cfg), (("evaluator-0", "eval/success_rate"),))
    root.add_text("config/run", table(cfg), step=0)
    root.close()
    log = ScalarLog(tmp_path, every=1, suffix="evaluator-0")  # a service's: its own directory
    frames = [np.full((32, 48, 3), 40 * i, np.uint8) for i in range(5)]
    log.add_animation("eval/video", frames, step=500, fps=10)
    log.add({"eval/success_rate": 0.25}, step=500)
    log.close()
    assert [p.name for p in tmp_path.iterdir() if p.is_dir()] == ["evaluator-0"]  # no other sub-run
    assert len(list(tmp_path.glob("events.out.tfevents.*"))) == 1
    assert len(list((tmp_path / "evaluator-0").glob("events.out.tfevents.*.evaluator-0"))) == 1

    ea = _accumulator(tmp_path)
    hp = ea.PluginTagToContent("hparams")
    start = plugin_data_pb2.HParamsPluginData.FromString(hp["_hparams_/session_start_info"])
    values = start.session_start_info.hparams
    assert values["task"].string_value == "drawer_open" and values["env_steps"].number_value == 1234
    assert values["record"].bool_value is True and values["run_dir"].string_value == str(tmp_path / "run")
    experiment = plugin_data_pb2.HParamsPluginData.FromString(hp["_hparams_/experiment"]).experiment
    assert [(m.name.group, m.name.tag) for m in experiment.metric_infos] == [
        ("evaluator-0", "eval/success_rate")
    ]
    assert {h.name for h in experiment.hparam_infos} == set(settings(cfg))
    text = ea.Tensors("config/run/text_summary")[0].tensor_proto.string_val[0].decode()
    assert text.startswith("| setting | value |") and "| task | `drawer_open` |" in text
    assert len(text.splitlines()) == 2 + len(settings(cfg))
    ea = _accumulator(tmp_path / "evaluator-0")
    assert [(e.step, e.value) for e in ea.Scalars("eval/success_rate")] == [(500, 0.25)]
    (image,) = ea.Images("eval/video")
    assert (image.step, image.width, image.height) == (500, 48, 32)
    gif = Image.open(io.BytesIO(image.encoded_image_string))
    assert gif.format == "GIF" and gif.n_frames == 5
