"""logger=wandb, offline: a training and an evaluation run on tiny synthetic data, and a grid's table, read back from
what the offline runs wrote (config, card, per-pair table, 3D objects, the multirun's group)."""

from __future__ import annotations

import json

import pandas as pd
import pytest
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from src.config import sweep_group
from src.run.wandb_logging import COLOURS, PAIR_COLUMNS, log_grid, read_offline_run
from tests.helpers.registration_helpers import compose_config, tiny_config

pytest.importorskip("wandb", reason="wandb not installed: pip install wandb (or pip install -e '.[dev]')")


@pytest.fixture(autouse=True)
def offline(monkeypatch, tmp_path):
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_CACHE_DIR", str(tmp_path / "wandb_cache"))
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "wandb_config"))


@pytest.fixture
def multirun(tmp_path):
    """A Hydra multirun's job (HydraConfig set as Hydra sets it), reset afterwards."""
    hydra_cfg = compose_config("hydra.mode=MULTIRUN", f"hydra.sweep.dir={tmp_path / 'sweep'}", hydra_cfg=True)
    HydraConfig.instance().set_config(hydra_cfg)
    yield str(tmp_path / "sweep")
    HydraConfig.instance().cfg = None


def _only_run(output_dir):
    runs = sorted((output_dir / "wandb").glob("offline-run-*"))
    assert len(runs) == 1, runs
    return read_offline_run(runs[0])


def _check_test_logs(run, output_dir, n_pairs: int, n_points: int) -> None:
    card = json.loads((output_dir / "metrics.json").read_text())
    assert run.summary["card"] == card  # the run's card: context and metrics, as metrics.json
    assert run.config["task_name"] == "unseen_shapes" and run.config["data"]["dataset"] == "synthetic"
    assert run.config["output_dir"] == str(output_dir)  # the resolved config, not its interpolations
    (table,) = run.media("table", "test/pairs")
    assert table["columns"] == PAIR_COLUMNS and len(table["data"]) == n_pairs and "test/pairs" in run.logged
    assert sorted(row[0] for row in table["data"]) == list(range(n_pairs))
    assert all(0.0 <= row[1] <= 1.0 and row[2] >= 0 and row[6] > 0 for row in table["data"])
    mean_error = sum(row[2] for row in table["data"]) / n_pairs
    assert mean_error == pytest.approx(card["metrics"]["Error(R)"], rel=1e-4)
    objects = run.media("object3D", "test/objects/pair_0")
    assert len(objects) == 1 and "test/objects/pair_0" in run.logged
    points = objects[0]  # rows x, y, z, r, g, b
    assert len(points) == 3 * n_points  # source, reference, aligned source
    colours = {tuple(p[3:6]) for p in points}
    assert colours == {COLOURS["source"], COLOURS["reference"], COLOURS["aligned"]}
    (masks,) = run.media("object3D", "test/overlap_masks/pair_0")  # OMNet's predicted overlap masks
    assert len(masks) == 2 * n_points and {tuple(p[3:6]) for p in masks} <= {COLOURS["kept"], COLOURS["dropped"]}


def test_training_and_evaluation_runs_log_config_card_pairs_and_objects(tmp_path, multirun):
    from src.eval import evaluate
    from src.train import train

    overrides = ["+exp=unseen_shapes", "logger=wandb", "trainer.limit_test_batches=2", "data.eval_batch_size=2"]
    train(tiny_config(tmp_path, *overrides, "trainer.max_steps=2", "trainer.limit_val_batches=1",
                      "trainer.limit_train_batches=2"))
    trained = _only_run(tmp_path / "run")
    assert trained.group == multirun  # a multirun's jobs share its sweep as their group
    _check_test_logs(trained, tmp_path / "run", n_pairs=4, n_points=768)
    assert any(key.startswith("val/") for key in trained.logged)  # the training's metrics

    checkpoint = sorted((tmp_path / "run" / "checkpoints").glob("best-*.ckpt"))[0]
    evaluate(tiny_config(tmp_path, *overrides, f"ckpt_path={checkpoint}", f"output_dir={tmp_path / 'eval'}"))
    evaluated = _only_run(tmp_path / "eval")
    _check_test_logs(evaluated, tmp_path / "eval", n_pairs=4, n_points=768)
    assert evaluated.summary["card"]["checkpoint"] == str(checkpoint)


def test_a_single_run_has_no_group():
    assert sweep_group() is None
    assert OmegaConf.create({"group": "${wandb_group:}"}).group is None


def test_a_grid_logs_its_tidy_table(tmp_path):
    tidy = pd.DataFrame({"method": ["icp", "fgr"], "metric": ["Error(R)", "Error(R)"], "value": [1.5, 0.5]})
    cfg = OmegaConf.create({"benchmark": {"name": "toy"}, "output_dir": str(tmp_path),
                            "wandb": {"enabled": True, "group": "table1", "mode": "offline"}})
    log_grid(cfg, tidy)
    run = _only_run(tmp_path)
    assert run.group == "table1" and run.config["benchmark"] == {"name": "toy"}
    (table,) = run.media("table", "grid/results")
    assert table["columns"] == list(tidy.columns) and table["data"] == tidy.values.tolist()
    log_grid(OmegaConf.create({**cfg, "wandb": {"enabled": False}, "output_dir": str(tmp_path / "off")}), tidy)
    assert not (tmp_path / "off").exists()
