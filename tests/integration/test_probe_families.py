"""Families of bad input found by a probe of new-user cases, through the entry points on one tiny trained run:
a test set that overlaps the training shapes, checkpoint cards that claim another file or experiment, a resume
that would train nothing, a second training in a run folder, and one line instead of a traceback."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest
import torch

import src.eval
from src.run.checkpoint_io import read_checkpoint
from src.utils.errors import CheckpointError, ConfigError, DiskError
from src.eval import evaluate
from src.models.pretrained import SHIPPED_DIR, export, find_shipped, verify_card
from src.run.run_dir import refuse_reused_run_dir
from src.train import train
from tests.helpers.registration_helpers import TINY, compose_config

IDENTITY = {"task": "unseen_shapes", "dataset": "synthetic", "sampling": "ts", "partial": "prnet"}


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, str]:
    """A finished tiny run (2 steps) and its cache override."""
    tmp = tmp_path_factory.mktemp("probe")
    cache = f"data.cache_root={tmp / 'cache'}"
    train(compose_config(*TINY, cache, f"output_dir={tmp / 'run'}", "+exp=unseen_shapes", "trainer.max_steps=2",
                         "trainer.val_check_interval=1", "trainer.check_val_every_n_epoch=null",
                         "trainer.limit_val_batches=1", "trainer.limit_test_batches=1"))
    return tmp / "run", cache


def _config(trained: tuple[Path, str], output: Path, *overrides: str):
    return compose_config(*TINY, trained[1], f"output_dir={output}", "+exp=unseen_shapes", *overrides)


def _best(run: Path) -> str:
    return json.loads((run / "metrics.json").read_text())["checkpoint"]


# --- 1. scored data that is not what the record says --------------------------------------------------


def test_the_checkpoint_records_what_it_trained_on_and_eval_refuses_those_shapes(trained, tmp_path):
    run, _ = trained
    record = read_checkpoint(_best(run))["trained_on"]
    assert {k: record[k] for k in IDENTITY} == IDENTITY and record["splits"]["train"]["split"] == "train"
    with pytest.raises(ConfigError, match=r"^\d+ of the \d+ test shapes are shapes .* was trained on \(first: "):
        evaluate(_config(trained, tmp_path / "eval", f"ckpt_path={_best(run)}", "data.splits.test.split=train"))
    assert not (tmp_path / "eval" / "metrics.json").exists()  # was: scored under a normal header


def test_every_evaluation_records_what_it_scored_and_left_out(trained, tmp_path):
    evaluate(_config(trained, tmp_path / "eval", f"ckpt_path={_best(trained[0])}", "trainer.limit_test_batches=1"))
    saved = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert saved["test_overlap_checked"] is True and saved["test_dropped"] == {"pairs": 0}
    assert saved["test_pairs"] == 2 and saved["test_set_pairs"] == 7  # one batch of two, of the seven test pairs


# --- 2. identity by content ------------------------------------------------------------------------------


def test_a_card_that_claims_another_experiment_or_file_is_refused(trained, tmp_path):
    run, _ = trained
    (run / ".hydra").mkdir(exist_ok=True)
    (run / ".hydra" / "overrides.yaml").write_text("- +exp=unseen_shapes\n")
    target = export(run, "tiny", tmp_path)
    assert find_shipped(IDENTITY, tmp_path) == target
    card_path = target.with_suffix(".json")
    card = json.loads(card_path.read_text())
    card_path.write_text(json.dumps(card | {"experiment": card["experiment"] | {"dataset": "modelnet40"}}))
    with pytest.raises(CheckpointError, match=r"^the card tiny.json claims task=unseen_shapes dataset=modelnet40 .* "
                                              r"was trained on task=unseen_shapes dataset=synthetic"):
        find_shipped(IDENTITY | {"dataset": "modelnet40"}, tmp_path)  # was: picked, and evaluated on ModelNet40
    card_path.write_text(json.dumps(card))
    target.write_bytes(target.read_bytes() + b"\0")
    with pytest.raises(CheckpointError, match=r"tiny.ckpt has sha256 \w+…, not the \w+… of its card tiny.json"):
        find_shipped(IDENTITY, tmp_path)


def test_every_shipped_card_describes_its_file():
    for card_path in sorted(SHIPPED_DIR.glob("*.json")):
        assert verify_card(card_path.with_suffix(".ckpt"), json.loads(card_path.read_text())).is_file()


# --- 4. a resume that would train nothing; 5. a second training in one run folder -------------------------


def test_resuming_a_run_past_its_budget_is_refused(trained, tmp_path):
    last = trained[0] / "checkpoints" / "last.ckpt"
    with pytest.raises(ConfigError, match=r"^ckpt_path=.*last.ckpt is at step 2, and trainer.max_steps=1: the resumed "
                                          r"run would train nothing"):
        train(_config(trained, tmp_path / "again", f"ckpt_path={last}", "trainer.max_steps=1"))
    assert not (tmp_path / "again" / "metrics.json").exists()  # was: tested and written as a run


def test_a_second_training_in_a_run_folder_is_refused_and_its_own_resume_is_not(trained, tmp_path):
    run, _ = trained
    before = sorted(p.name for p in run.rglob("*"))
    with pytest.raises(ConfigError, match=r"already holds a run \(csv, checkpoints, metrics.json\): "
                                          r"a second training there would mix.* resume that run with "
                                          rf"hydra.run.dir={re.escape(str(run))} ckpt_path=last$"):
        train(_config(trained, run, "trainer.max_steps=1"))
    assert sorted(p.name for p in run.rglob("*")) == before
    refuse_reused_run_dir(_config(trained, run, f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}"))
    with pytest.raises(ConfigError, match="already holds a run"):
        refuse_reused_run_dir(_config(trained, run, f"ckpt_path={_best(run)}"))


# --- 6. one line, before anything runs ---------------------------------------------------------------------


def test_a_monitor_no_validation_logs_is_refused_before_training(trained, tmp_path):
    with pytest.raises(ConfigError, match=r"^callbacks.checkpoint.monitor=val/nothing is never logged"):
        train(_config(trained, tmp_path / "run", "callbacks.checkpoint.monitor=val/nothing"))
    assert not (tmp_path / "run").exists()  # was: found after the first validation


@pytest.mark.parametrize("entry", ["train", "eval"])
def test_a_fractional_batch_limit_that_keeps_no_batch_is_refused(trained, tmp_path, entry):
    overrides = ["trainer.limit_test_batches=0.001"]
    with pytest.raises(ConfigError, match=r"^trainer.limit_test_batches=0.001 keeps no batch: 0.001 of the 4 test "
                                          r"batches is less than one; use at least 0.25"):
        if entry == "train":
            train(_config(trained, tmp_path / "run", "trainer.max_steps=1", *overrides))
        else:
            evaluate(_config(trained, tmp_path / "run", f"ckpt_path={_best(trained[0])}", *overrides))
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_a_run_folder_or_cache_folder_that_is_a_file_is_one_line(trained, tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    monkeypatch.setattr(sys, "argv", ["src.eval", "+exp=unseen_categories", f"hydra.run.dir={blocker}"])
    with pytest.raises(SystemExit) as info:
        src.eval.main()
    assert info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"error: creating the run folder: {blocker} or a folder above it is a file, not a folder: move the file, or "
        "write elsewhere (OMNET_CACHE_DIR / --cache-root for caches, hydra.run.dir or output_dir for runs)"]
    cfg = compose_config(*TINY, f"data.cache_root={blocker}", f"output_dir={tmp_path / 'eval'}", "+exp=unseen_shapes",
                         f"ckpt_path={_best(trained[0])}")
    with pytest.raises(DiskError, match=f"{blocker} or a folder above it is a file"):
        evaluate(cfg)  # (OMNET_CACHE_DIR=<a file>: the same default cache root)


# --- 7. misleading messages --------------------------------------------------------------------------------


def test_a_checkpoint_folder_or_one_with_nan_weights_is_named(trained, tmp_path):
    with pytest.raises(CheckpointError, match=r"is a folder: pass a .ckpt file in it \(e.g. .*last.ckpt\)"):
        read_checkpoint(trained[0] / "checkpoints")  # was: "does not exist"
    checkpoint = torch.load(_best(trained[0]), map_location="cpu", weights_only=False)
    key = next(k for k, v in checkpoint["state_dict"].items() if v.is_floating_point())
    checkpoint["state_dict"][key] = checkpoint["state_dict"][key].clone().fill_(float("nan"))
    torch.save(checkpoint, tmp_path / "renamed.ckpt")
    with pytest.raises(CheckpointError, match=rf"renamed.ckpt: \d+ of the \d+ values of weight {key} are NaN"):
        read_checkpoint(tmp_path / "renamed.ckpt")  # was: a failure far later, in an SVD
