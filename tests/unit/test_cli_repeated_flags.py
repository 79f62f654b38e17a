"""A list option given twice on a command line is refused in one line (argparse would keep the last
list and drop the others without a word); a scalar given twice keeps the usual rule, the last wins
(the compose actor wrapper appends its overrides that way); options that collect every occurrence
(``--extra``) take any number."""

from __future__ import annotations

import pytest

from mea_tools.bench.learning import LearningBenchConfig
from services.common import config
from services.run_config import PRESETS as RUN_PRESETS
from services.run_config import RunConfig


def test_a_list_option_given_twice_is_refused_in_one_line(capsys):
    argv = ["--services", "learner", "evaluator", "--env-steps", "9", "--services", "actor"]
    with pytest.raises(SystemExit) as exc:
        config.parse(RunConfig, RUN_PRESETS, argv, "mea run", "")
    assert exc.value.code == 2
    assert capsys.readouterr().err.strip() == (
        "mea run: --services given more than once; give all its values after one --services"
    )


def test_scalars_keep_the_last_and_collecting_options_take_every_occurrence():
    parsed = config.parse(RunConfig, RUN_PRESETS, ["--demos", "2", "--demos", "0"], "mea run", "")
    assert parsed.demos == 0
    assert config.repeated_flags(RunConfig, ["--demos", "2", "--demos", "0"]) == []
    assert config.repeated_flags(LearningBenchConfig, ["--extra=--track", "--extra=--demos=3"]) == []
    assert config.repeated_flags(RunConfig, ["--services", "actor", "--", "--services"]) == []
    assert config.repeated_flags(RunConfig, ["--connect", "a", "--connect=b"]) == ["--connect"]
