"""What the product prints or documents for resuming a run works when run as printed (through ``src.train``'s own
entry point, in this process): the command printed after a SIGTERM during the last training step, and the
documented ``ckpt_path=last`` loop after a run was killed before its first ``last.ckpt``."""

from __future__ import annotations

import json
import shlex
import sys

import pytest
import torch

from src.train import main as train_main
from tests.helpers.registration_helpers import TINY

RUN = [*TINY, "+exp=unseen_shapes", "trainer.val_check_interval=2", "trainer.check_val_every_n_epoch=null",
       "trainer.limit_val_batches=1", "trainer.limit_test_batches=1"]


def _train(monkeypatch, *args: str) -> int:
    """``python -m src.train <args>``'s exit status."""
    monkeypatch.setattr(sys, "argv", ["src.train", *args])
    try:
        train_main()
    except SystemExit as exit_info:
        return exit_info.code
    return 0


def test_the_command_printed_after_a_signal_in_the_last_step_finishes_the_run(tmp_path, monkeypatch, capsys):
    """It resumed last.ckpt at trainer.max_steps, which is refused (it would train nothing): the signal's checkpoint
    is now the step before the last, so that the printed command trains the last step, then tests."""
    run = tmp_path / "run"
    signal = ["+callbacks.signal._target_=tests.helpers.signal_self.SignalAt", "+callbacks.signal.step=2",
              f"+callbacks.signal.sent={tmp_path / 'sent'}"]
    status = _train(monkeypatch, *RUN, "trainer.max_steps=3", f"data.cache_root={tmp_path / 'cache'}", *signal,
                    f"hydra.run.dir={run}")
    line = capsys.readouterr().err.strip().splitlines()[-1]
    prefix = "error: interrupted by SIGTERM at step 2; resume it in its folder with: "
    assert status == 143 and line.startswith(prefix), line
    command = shlex.split(line.removeprefix(prefix))
    last = run / "checkpoints" / "last.ckpt"
    assert command[:3] == ["python", "-m", "src.train"] and command[-1] == f"ckpt_path={last}"
    assert torch.load(last, weights_only=False)["global_step"] == 2

    assert _train(monkeypatch, *command[3:]) == 0, capsys.readouterr().err[-3000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["global_step"] == 3 and not (run / "failure.json").exists()


def test_ckpt_path_last_after_a_kill_before_the_first_checkpoint_starts_again(tmp_path, monkeypatch, capsys):
    """The folder held the killed run's logs, so the documented loop's next command was refused (a second run in
    the folder of another), with a resume command naming a last.ckpt that did not exist."""
    run = tmp_path / "run"
    command = [*RUN, "trainer.max_steps=4", f"data.cache_root={tmp_path / 'cache'}", f"hydra.run.dir={run}"]
    kill = ["+callbacks.kill._target_=tests.helpers.registration_helpers.KillAt", "+callbacks.kill.step=2"]
    with pytest.raises(RuntimeError, match="killed at step 2"):
        _train(monkeypatch, *command, *kill)
    assert (run / "csv").is_dir() and not (run / "checkpoints" / "last.ckpt").exists()
    capsys.readouterr()

    assert _train(monkeypatch, *command, "ckpt_path=last") == 0
    output = capsys.readouterr()
    aside = run / "stopped_before_checkpoint_1"
    said = [line for line in (output.out + output.err).splitlines() if "ckpt_path=last: " in line]
    assert len(said) == 1 and said[0].endswith(
        f"ckpt_path=last: no {run / 'checkpoints' / 'last.ckpt'} yet (no checkpoint was written), training starts at "
        f"step 0; the stopped run's {', '.join(n for n in ('csv', 'checkpoints') if (aside / n).exists())} moved to "
        f"{aside}"), said
    assert json.loads((run / "metrics.json").read_text())["global_step"] == 4
    assert (aside / "csv").is_dir() and len(list((run / "csv").glob("version_*"))) == 1  # the new run's logs alone
