"""Signals outside training: a job stopped by SIGTERM/SIGINT is recorded and exits 128 + signal (the
training case, a checkpoint at the signal and a bit-for-bit resume, is in test_resume.py)."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
from omegaconf import OmegaConf

from src.utils.errors import exit_on_user_error
from src.run.failures import record_failures


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_outside_training_is_recorded_and_exits_non_zero(tmp_path, capsys, signum):
    def task(cfg):  # e.g. src.eval, or src.train's test after fit
        os.kill(os.getpid(), signum)
        time.sleep(30)  # the handler raises before this ends
        return "finished"

    cfg = OmegaConf.create({"output_dir": str(tmp_path), "on_failure": "record"})  # even in a sweep: stop
    with pytest.raises(SystemExit) as exit_info:
        exit_on_user_error(record_failures(task))(cfg)
    assert exit_info.value.code == 128 + signum
    name = signal.Signals(signum).name
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"error: interrupted by {name}"
    failure = json.loads((tmp_path / "failure.json").read_text())
    assert failure["status"] == "interrupted" and failure["signal"] == name
    assert signal.getsignal(signum) is not None and signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
