"""`mea run --learner-args`: learner flags applied to the preset by the learner's own parser, the
run's own settings winning, and a bad flag refused in one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.common.config import ServiceConfig
from services.plan import learner_config
from services.run_config import RunConfig

pytestmark = pytest.mark.unit


def cfg(args: str, **run):
    return learner_config(RunConfig(learner_args=args, **run), Path("/nonexistent/run"), ServiceConfig())


def test_flags_change_the_preset_and_the_run_keeps_its_own_settings():
    base = cfg("")
    c = cfg("--sac.bc-filter --demo-fraction 0.25 --sac.bc-decay-updates 500 --seed 9", seed=3)
    assert (c.sac.bc_filter, c.demo_fraction, c.sac.bc_decay_updates) == (True, 0.25, 500)
    assert not base.sac.bc_filter and base.demo_fraction == 0.5
    assert c.seed == 3  # the run's seed, not the flag's
    assert c.sac.bc_weight == base.sac.bc_weight  # untouched fields stay the preset's


@pytest.mark.parametrize(
    ("flags", "says"),
    [
        ("--sac.bc-weight x", "--sac.bc-weight"),
        ("--no-such-flag 1", "--no-such-flag"),
        ("--sac.bc-weight -1", "bc_weight must be >= 0"),
    ],
)
def test_a_bad_flag_is_one_line_naming_it(flags: str, says: str):
    with pytest.raises(ValueError) as err:
        cfg(flags)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("--learner-args") and says in msg
