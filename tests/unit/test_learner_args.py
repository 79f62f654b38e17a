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
    sac, base_sac = c.algorithm.sac, base.algorithm.sac
    assert (sac.bc_filter, c.demo_fraction, sac.bc_decay_updates) == (True, 0.25, 500)
    assert not base_sac.bc_filter and base.demo_fraction == 0.5
    assert c.seed == 3  # the run's seed, not the flag's
    assert sac.bc_weight == base_sac.bc_weight  # untouched fields stay the preset's


@pytest.mark.parametrize(
    ("flags", "says"),
    [
        ("--sac.bc-weight x", "--sac.bc-weight"),
        ("--no-such-flag 1", "--no-such-flag"),
        ("--sac.bc-weight -1", "bc_weight must be >= 0"),
        ("--dreamer.deter 64", "--dreamer.deter"),  # another algorithm's flag: the run trains equi_rsac
        ("--algorithm gasv2", "starts from a gasv2 preset"),  # the algorithm config's own check
    ],
)
def test_a_bad_flag_is_one_line_naming_it(flags: str, says: str):
    with pytest.raises(ValueError) as err:
        cfg(flags)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("--learner-args") and says in msg


def test_a_gasv2_learner_drops_the_task_group_compose_passes_and_a_sac_learner_keeps_it():
    from services.learner.config import without_foreign_group

    gasv2 = ["--preset", "gasv2", "--net.group", "c4", "--seed", "1"]
    assert without_foreign_group(gasv2) == ["--preset", "gasv2", "--seed", "1"]
    assert without_foreign_group(["--preset=gasv2-smoke", "--net.group=d4"]) == ["--preset=gasv2-smoke"]
    sac = ["--preset", "cpu-small", "--net.group", "d4"]
    assert without_foreign_group(sac) == sac
