"""src.train / src.eval through Hydra on tiny synthetic data, and their one-line errors."""

import json
import os
import subprocess
import sys

import pytest
import torch

from src.utils.errors import CheckpointError
from src.eval import evaluate
from src.train import train
from tests.helpers.registration_helpers import tiny_config


@pytest.mark.parametrize("exp", ["unseen_shapes", "unseen_categories", "gaussian_noise"])
def test_experiment_configs_compose(tmp_path, exp):
    cfg = tiny_config(tmp_path, f"+exp={exp}")
    assert cfg.task_name == exp and cfg.data.dataset == "synthetic"
    assert cfg.model.euler_seq == "zyx"
    assert cfg.data.splits.test.categories == ("half2" if exp == "unseen_categories" else "half1")


def test_rpmnet_manner_switches_the_euler_convention(tmp_path):
    cfg = tiny_config(tmp_path, "+exp=unseen_categories", "partial=rpmnet", "sampling=os")
    assert cfg.model.euler_seq == "xyz" and cfg.data.pair.partial == "rpmnet" and cfg.data.pair.sampling == "os"


def test_fast_dev_run_trains_tests_and_evaluates(tmp_path):
    cfg = tiny_config(tmp_path, "+exp=unseen_categories", "trainer.fast_dev_run=true")
    metrics = train(cfg)
    assert set(metrics) >= {"RMSE(R)", "Error(R)", "Error(t)", "score"}
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["dataset"] == "synthetic" and saved["metrics"]["Error(R)"] == pytest.approx(metrics["Error(R)"])
    assert (tmp_path / "run" / "config_resolved.yaml").is_file()


def test_train_writes_checkpoint_that_eval_reads(tmp_path):
    cfg = tiny_config(tmp_path, "+exp=unseen_shapes", "trainer.max_steps=2", "trainer.limit_val_batches=1",
                      "trainer.limit_test_batches=1", "trainer.limit_train_batches=2")
    train(cfg)
    ckpts = sorted((tmp_path / "run" / "checkpoints").glob("best-*.ckpt"))
    assert ckpts, "no best checkpoint written"
    eval_cfg = tiny_config(tmp_path, "+exp=unseen_shapes", f"ckpt_path={ckpts[0]}", "trainer.limit_test_batches=1",
                           f"output_dir={tmp_path / 'eval'}")
    metrics = evaluate(eval_cfg)
    assert metrics["Error(R)"] >= 0 and (tmp_path / "eval" / "metrics.csv").is_file()
    saved = json.loads((tmp_path / "eval" / "metrics.json").read_text())  # what it evaluated: 1 batch of 2 pairs
    assert (saved["test_pairs"], saved["test_dataset"], saved["test_split"]) == (2, "synthetic", "test")


def _run(*args: str, env_extra: dict | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, **(env_extra or {})}
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env, timeout=300)


def test_missing_modelnet_cache_is_one_clear_line(tmp_path):
    result = _run("-m", "src.train", "+exp=unseen_categories", "data=modelnet40", f"data.cache_root={tmp_path}",
                  f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode == 2
    error = result.stderr.strip().splitlines()[-1]
    assert error.startswith("error: ") and "src.data.prepare" in error and "data=synthetic" in error


def test_unknown_experiment_and_key_are_reported(tmp_path):
    result = _run("-m", "src.train", "+exp=unseen_planets", f"hydra.run.dir={tmp_path}")
    lines = result.stderr.strip().splitlines()  # one line, exit 2 (Hydra's report and exit 1 before)
    assert result.returncode == 2 and len(lines) == 1
    assert lines[0].startswith("error: exp=unseen_planets: no such config in group exp; choose one of: ")
    assert "unseen_categories" in lines[0]  # the available experiments
    result = _run("-m", "src.train", "data.bogus_key=1", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 2 and result.stderr.startswith("error: data.bogus_key is not a key of data: ")


def test_eval_rejects_missing_and_foreign_checkpoints(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        evaluate(tiny_config(tmp_path, f"ckpt_path={tmp_path / 'none.ckpt'}"))
    foreign = tmp_path / "foreign.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": {"network": {"_target_": "baselines.learned.dcp.DCP"}}}, foreign)
    with pytest.raises(CheckpointError, match="holds a baselines.learned.dcp.DCP network"):
        evaluate(tiny_config(tmp_path, f"ckpt_path={foreign}"))
    junk = tmp_path / "junk.ckpt"
    junk.write_text("not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable PyTorch checkpoint"):
        evaluate(tiny_config(tmp_path, f"ckpt_path={junk}"))
