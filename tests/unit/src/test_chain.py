"""src.run.chain: one run continued in its own folder across time-limited calls (a stand-in trainer,
tests/helpers/fake_trainer.py; the real src.train under the chain: tests/integration/test_reproduce_docs.py)."""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time

import pytest
import torch

from src.run.chain import RESUMABLE, Chain, main, submit
from src.utils.errors import ConfigError
from tests.helpers.paths import ROOT

FAKE = (sys.executable, "-m", "tests.helpers.fake_trainer")


@pytest.fixture(autouse=True)
def _repository_root(monkeypatch):
    monkeypatch.chdir(ROOT)  # the stand-in is run as a module of the repository
    monkeypatch.setenv("PYTHONPATH", str(ROOT))


def _chain(run, *overrides, minutes=None):
    return Chain(run, ["steps=400", "step_s=0.05", *overrides], minutes, FAKE)


def _calls(run):
    return (run / "calls.txt").read_text().splitlines()


def test_a_time_limit_stops_the_run_and_the_same_command_continues_it_in_place(tmp_path, capsys):
    run = tmp_path / "run"
    assert _chain(run, minutes=0.1)() == RESUMABLE
    assert "run the same command again" in capsys.readouterr().err
    first = json.loads((run / "chain.json").read_text())["calls"][0]
    assert first["exit"] == 143 and first["from_step"] == 0 and 0 < first["to_step"] < 400 and first["max_steps"] == 400
    assert first["stopped_by"] == "the time limit (--minutes 0.1)"

    assert _chain(run)() == 0
    record = json.loads((run / "chain.json").read_text())
    assert record["done"] and [c["exit"] for c in record["calls"]] == [143, 0]
    assert record["calls"][1]["from_step"] == first["to_step"] and record["calls"][1]["to_step"] == 400
    resumed = _calls(run)[1].split()
    assert f"hydra.run.dir={run}" in resumed and resumed[-1] == "ckpt_path=last" == _calls(run)[0].split()[-1]

    capsys.readouterr()
    assert _chain(run)() == 0  # done: nothing runs again
    assert "is done (2 calls); nothing to run" in capsys.readouterr().out and len(_calls(run)) == 2


def test_a_failed_call_keeps_its_exit_status_and_is_not_done(tmp_path):
    run = tmp_path / "run"
    assert _chain(run, "fail=1")() == 1
    record = json.loads((run / "chain.json").read_text())
    assert not record["done"] and record["calls"][0]["exit"] == 1 and record["calls"][0]["stopped_by"] is None


def test_a_folder_of_other_overrides_and_the_chains_own_keys_are_refused(tmp_path, capsys):
    run = tmp_path / "run"
    assert _chain(run, "fail=1")() == 1
    with pytest.raises(ConfigError, match="holds a run of other overrides"):
        _chain(run, "fail=0")()
    for override in (f"hydra.run.dir={tmp_path}", "ckpt_path=x.ckpt", "+ckpt_path=x.ckpt", "-m"):
        with pytest.raises(ConfigError, match="the chain sets hydra.run.dir and ckpt_path itself"):
            _chain(run, override)
    assert main([str(run), "--minutes", "0", "--", "steps=1"]) == 2
    assert capsys.readouterr().err.strip() == "error: --minutes must be a positive number, got 0.0"
    other = str(tmp_path / "other")
    assert main([other, "--submit", "--", "steps=1"]) == 2
    assert capsys.readouterr().err.strip() == "error: --submit needs --minutes (the job's time limit)"
    assert main([other, "--submit", "--minutes", "5", "--slurm", "slurm_partition", "--", "steps=1"]) == 2
    assert "--slurm slurm_partition: expected KEY=VALUE" in capsys.readouterr().err


def test_a_submitted_chain_runs_as_a_job_and_records_its_call(tmp_path):
    """submitit's local executor (a process, as a SLURM job would be): the chain is pickled, run, recorded."""
    run = tmp_path / "run"
    job = submit(Chain(run, ["steps=5", "step_s=0.01"], 5.0, FAKE), {}, "local", 2)
    assert job.result() == 0
    record = json.loads((run / "chain.json").read_text())
    assert record["done"] and [c["to_step"] for c in record["calls"]] == [5]
    assert (run / ".submitit").is_dir()


def test_submitits_checkpoint_stops_the_training_at_a_step_and_requeues_the_same_chain(tmp_path):
    """At a job's time limit submitit calls ``checkpoint`` from its SIGUSR2 handler, while the chain waits; the
    training (which ignores SIGUSR2, whose default action would kill it) is stopped at a step, the call recorded,
    and the chain requeued; the requeued chain continues the run."""
    run = tmp_path / "run"
    chain = _chain(run)

    class Requeued(Exception):
        pass

    def handler(signum, frame):  # as submitit's: checkpoint, then leave the job
        raise Requeued(chain.checkpoint())

    def signal_when_training():
        while not (run / "training").exists():
            time.sleep(0.02)
        os.kill(chain._process.pid, signal.SIGUSR2)  # SLURM signals every process of the job
        time.sleep(0.3)
        os.kill(os.getpid(), signal.SIGUSR2)

    previous = signal.signal(signal.SIGUSR2, handler)
    try:
        threading.Thread(target=signal_when_training, daemon=True).start()
        with pytest.raises(Requeued) as requeued:
            chain()
    finally:
        signal.signal(signal.SIGUSR2, previous)
    record = json.loads((run / "chain.json").read_text())
    assert record["calls"][0]["exit"] == 143 and record["calls"][0]["stopped_by"] == "the job's time limit"
    step = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["global_step"]
    assert 0 < step == record["calls"][0]["to_step"] < 400
    delayed = requeued.value.args[0]
    assert delayed.function == chain and delayed.function is not chain
    assert delayed.result() == 0 and json.loads((run / "chain.json").read_text())["done"]
