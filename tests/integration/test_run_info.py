"""A first run's messages: the headline command without ModelNet40, the start line and the time estimate,
quiet output, and the test record (pairs, dataset, split, categories from the data)."""

import json
import os
import re
import subprocess
import sys
from types import SimpleNamespace

import pytest

import hydra
from src.config import loader_workers
from src.run.info import TrainingForecast, format_duration
from src.run.evaluated import PairCounter, evaluated_record
from tests.helpers.registration_helpers import TINY, compose_config

PAPER_EXPERIMENTS = ("unseen_shapes", "unseen_categories", "gaussian_noise")


def _run(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "src.train", *args], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}, cwd=cwd)


@pytest.mark.parametrize("exp", PAPER_EXPERIMENTS)
def test_paper_experiments_compose_modelnet40_unless_another_dataset_is_chosen(exp):
    assert compose_config(f"+exp={exp}").data.dataset == "modelnet40"
    assert compose_config(f"+exp={exp}", "data=synthetic").data.dataset == "synthetic"
    assert compose_config("data=synthetic", f"+exp={exp}").data.dataset == "synthetic"


def test_the_headline_command_without_modelnet40_stops_in_one_line_with_both_ways_forward(tmp_path):
    result = _run("+exp=unseen_categories", f"data.cache_root={tmp_path / 'none'}", f"hydra.run.dir={tmp_path / 'run'}")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "ModelNet40" in lines[0] and "not prepared under" in lines[0]
    assert "`python -m src.data.prepare modelnet40 --source PATH/ModelNet40.zip`" in lines[0]
    assert f"`python -m src.train +exp=unseen_categories data.cache_root={tmp_path / 'none'} data=synthetic " \
           "recipe=omnet_cpu`" in lines[0]
    assert not (tmp_path / "run" / "checkpoints").exists()  # refused before anything was built


def test_a_first_run_prints_what_it_does_its_estimate_and_its_results_once(tmp_path):
    """The start line, the estimate after the first steps, one metrics table and where it is; none of
    Lightning's tips, environment notes, limit_* notes, model summary or its internal deprecation."""
    result = _run(*TINY, "+exp=unseen_shapes", f"data.cache_root={tmp_path / 'cache'}", f"hydra.run.dir={tmp_path / 'run'}",
                  "trainer.max_steps=3", "callbacks.forecast.after_steps=1", "trainer.limit_val_batches=1",
                  "trainer.limit_test_batches=1")
    out = result.stdout + result.stderr
    assert result.returncode == 0, out
    assert "train: synthetic data (SYNTHETIC procedural shapes, not ModelNet40), 14 training shapes | OMNet " in out
    assert re.search(r"\| precision (32-true|bf16-mixed) \(.+\) \| run dir ", out)  # the choice and why (src/run/precision.py)
    assert "3 steps x batch 2 on cpu" in out and "s/step measured over steps 2-2: the remaining 1 steps take ~" in out
    assert out.count("Test metrics (unseen_shapes protocol, ts, prnet; 2 of 7 pairs of synthetic data, split test: ") == 1
    assert f"wrote {tmp_path / 'run' / 'metrics.json'}" in out
    for noise in ("Tip:", "GPU available", "Seed set", "was configured so", "LeafSpec", "Trainable params",
                  "DataLoader 0", "does not have many workers"):
        assert noise not in out, noise
    record = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert (record["test_pairs"], record["test_dataset"], record["test_split"], record["test_shapes"]) == \
        (2, "synthetic", "test", 2)
    half1 = json.loads((tmp_path / "cache" / "synthetic" / "manifest.json").read_text())["halves"]["1"]
    assert record["test_categories"] and set(record["test_categories"]) <= set(half1)


def test_a_record_labels_what_was_evaluated_not_the_experiment(merged_root):
    """Bathtubs evaluated through +exp=real_airplane are bathtubs, all of them (not the carve-out's size)."""
    cfg = compose_config(f"data.cache_root={merged_root}", "data.num_workers=0", "output_dir=unused", "+exp=real_airplane",
                         "test_size=1", "val_size=1", "~data.splits.test", "+data.splits.test={split: train, categories: [bathtub]}")
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("test")
    counter = PairCounter()
    counter.pairs = len(datamodule.datasets["test"])
    record = evaluated_record(SimpleNamespace(callbacks=[counter], datamodule=datamodule))
    assert record == {"test_pairs": 4, "test_set_pairs": 4, "test_dropped": {"pairs": 0},
                      "test_dataset": "modelnet40_resampled", "test_split": "train", "test_categories": ["bathtub"],
                      "test_shapes": 4}


def _trainer(total: int, step: int, device: str = "cpu"):
    return SimpleNamespace(estimated_stepping_batches=total, global_step=step,
                           strategy=SimpleNamespace(root_device=SimpleNamespace(type=device)))


def test_the_estimate_of_a_paper_scale_cpu_schedule_says_how_long_and_how_to_size_it():
    forecast, omnet = TrainingForecast(after_steps=10), SimpleNamespace(network=type("OMNet", (), {})())
    line = forecast.forecast(_trainer(260_000, 11), omnet, 20.0)
    assert "20.00 s/step measured over steps 2-11: the remaining 259,989 steps take ~60 days" in line
    assert "260,000 steps would take ~60 days on this CPU" in line and "`recipe=omnet_cpu trainer.max_steps=N`" in line
    other = SimpleNamespace(network=type("DCP", (), {})())
    assert "add `trainer.max_steps=N data.batch_size=N`" in forecast.forecast(_trainer(260_000, 11), other, 20.0)
    assert "\n" not in forecast.forecast(_trainer(3_000, 11), omnet, 1.5)  # a CPU-sized run: no advice
    assert "\n" not in forecast.forecast(_trainer(260_000, 11, "cuda"), omnet, 0.2)


def test_a_run_without_a_step_limit_is_told_what_stops_it():
    """max_steps=-1 and max_epochs=-1 (a run stopped by time or a signal: benchmarks.studies.gpu_study.study): the estimate
    crashed on Lightning's infinite step count (OverflowError)."""
    omnet = SimpleNamespace(network=type("OMNet", (), {})())
    line = TrainingForecast(after_steps=10).forecast(_trainer(float("inf"), 11), omnet, 0.5)
    assert line == ("train: 0.50 s/step measured over steps 2-11: no step limit (trainer.max_steps=-1, "
                    "trainer.max_epochs=-1): training runs until trainer.max_time, callbacks.clock.budget_cpu_hours "
                    "or a signal stops it")


@pytest.mark.parametrize("seconds, text", [(42, "42 s"), (150, "2.5 min"), (7200, "2.0 h"), (86400 * 49, "49 days"),
                                           (86400 * 1000, "2.7 years")])
def test_durations_read_in_the_unit_of_their_size(seconds, text):
    assert format_duration(seconds) == text


@pytest.mark.parametrize("cores, most, workers", [(1, 4, 0), (2, 4, 1), (2, 2, 1), (16, 4, 4)])
def test_loader_workers_leave_one_core_to_training(monkeypatch, cores, most, workers):
    monkeypatch.setattr("src.config.usable_cores", lambda: cores)
    assert loader_workers(most) == workers
