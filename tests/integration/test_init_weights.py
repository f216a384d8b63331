"""``init_weights=PATH``: training starts from a checkpoint's weights (fresh optimiser and schedule)."""

from __future__ import annotations

import json

import pytest
import torch

from src.utils.errors import CheckpointError, ConfigError
from src.train import train
from tests.helpers.registration_helpers import RESUME_RUN, last_weights, tiny_config


@pytest.fixture(scope="module")
def start(tmp_path_factory):
    """A 2-step run whose last.ckpt is the start of the runs below."""
    tmp = tmp_path_factory.mktemp("init")
    train(tiny_config(tmp, *RESUME_RUN, "trainer.max_steps=2", f"output_dir={tmp / 'start'}"))
    return tmp, tmp / "start" / "checkpoints" / "last.ckpt"


def test_training_starts_from_the_checkpoints_weights(start):
    """With lr 0 the weights stay the start's; the run counts its own steps from 0 and records its start."""
    tmp, ckpt = start
    run = tmp / "from_start"
    train(tiny_config(tmp, *RESUME_RUN, "trainer.max_steps=2", "model.lr=0.0", "test_after_fit=true",
                      f"init_weights={ckpt}", f"output_dir={run}"))
    started, ended = torch.load(ckpt, weights_only=False), last_weights(run)
    parameters = {name for name, _ in started["state_dict"].items() if "running_" not in name and "num_batches" not in name}
    assert all(torch.equal(started["state_dict"][name], ended[name]) for name in parameters)
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == 2
    assert json.loads((run / "metrics.json").read_text())["initialised_from"] == str(ckpt)


def test_a_fresh_run_differs_from_the_start(start):
    """The check above can fail: a run without init_weights (same seed) does not hold the start's weights."""
    tmp, ckpt = start
    run = tmp / "fresh"
    train(tiny_config(tmp, *RESUME_RUN, "trainer.max_steps=2", "model.lr=0.0", f"output_dir={run}"))
    started, ended = torch.load(ckpt, weights_only=False)["state_dict"], last_weights(run)
    assert any(not torch.equal(started[k], ended[k]) for k in started if "running_" not in k and "num_batches" not in k)


def test_init_weights_with_ckpt_path_is_refused(start):
    tmp, ckpt = start
    with pytest.raises(ConfigError, match="a resumed run keeps its own weights; give one of the two"):
        train(tiny_config(tmp, *RESUME_RUN, f"init_weights={ckpt}", f"ckpt_path={ckpt}", f"output_dir={tmp / 'both'}"))


def test_init_weights_of_another_architecture_is_refused_before_training(start):
    tmp, ckpt = start
    with pytest.raises(CheckpointError, match="holds another architecture than the config .*start a new run without it"):
        train(tiny_config(tmp, *RESUME_RUN, "model.network.num_iters=2", f"init_weights={ckpt}",
                          f"output_dir={tmp / 'other'}"))
    assert not (tmp / "other" / "checkpoints").exists()


def test_eval_refuses_init_weights(start):
    from src.eval import evaluate

    tmp, ckpt = start
    with pytest.raises(ConfigError, match="init_weights=.* is for src.train"):
        evaluate(tiny_config(tmp, "+exp=unseen_shapes", f"init_weights={ckpt}", f"ckpt_path={ckpt}"))


def test_each_validation_logs_the_process_mm_rate(start):
    """The yardstick of a CPU hour on a shared machine (src.run.callbacks.TrainingClock)."""
    from src.run.reporting import read_csv_logs

    tmp, _ = start
    rates = read_csv_logs(tmp / "start")["time/mm_gflops"].dropna()
    assert len(rates) >= 1 and (rates > 0).all()
