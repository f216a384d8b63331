"""benchmarks.studies.lockstep.harness's shared start check (the IDAM and PRNet adapters call it)."""

import json

import pytest

from benchmarks.studies.lockstep.harness import START_EVAL_TOLERANCE, START_TRAIN_TOLERANCE, check_start
from src.utils.errors import ConfigError


def test_the_start_check_is_written_and_refuses_a_difference_over_either_tolerance(tmp_path, capsys):
    result = {"eval": {"embedding": 1e-15}, "train": {"loss_rel": 1e-16}}
    check_start(tmp_path, result, eval_diff=START_EVAL_TOLERANCE, train_diff=START_TRAIN_TOLERANCE)  # at: passes
    assert json.loads((tmp_path / "start_check.json").read_text()) == result
    assert capsys.readouterr().out.startswith("same start: ")
    for diffs in ({"eval_diff": 2 * START_EVAL_TOLERANCE, "train_diff": 0.0},
                  {"eval_diff": 0.0, "train_diff": 2 * START_TRAIN_TOLERANCE}):
        (tmp_path / "start_check.json").unlink()
        with pytest.raises(ConfigError, match="differ at the start .*the weight mapping is wrong"):
            check_start(tmp_path, result, **diffs)
        assert (tmp_path / "start_check.json").is_file()  # written before the refusal: the numbers are kept
