"""src.run.quiet: Lightning's advice on log_every_n_steps is dropped for a step budget only, where it does not apply;
the pair-set class is not collected by pytest."""

from __future__ import annotations

import warnings

import lightning as L
import pytest
from lightning.pytorch.demos.boring_classes import BoringModel

from src.pair_sets import TestSet
from src.run.quiet import quiet_step_budget


def _fit_warnings(max_steps: int, max_epochs: int) -> list[str]:
    """The warnings of a short fit (4 batches an epoch, logging every 50 steps) after :func:`quiet_step_budget`."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_step_budget({"max_steps": max_steps, "max_epochs": max_epochs})
        L.Trainer(max_steps=max_steps, max_epochs=max_epochs, limit_train_batches=4, limit_val_batches=0,
                  accelerator="cpu", enable_progress_bar=False, enable_model_summary=False,
                  enable_checkpointing=False, log_every_n_steps=50, default_root_dir=None).fit(BoringModel())
    return [str(w.message) for w in caught]


@pytest.mark.parametrize("max_steps, max_epochs, shown", [(6, -1, False), (-1, 2, True)])
def test_the_logging_interval_advice_only_for_an_epoch_budget(tmp_path, monkeypatch, max_steps, max_epochs, shown):
    monkeypatch.chdir(tmp_path)  # Lightning's default logger writes lightning_logs/ here
    said = any("smaller than the logging interval" in m for m in _fit_warnings(max_steps, max_epochs))
    assert said == shown


def test_the_pair_set_class_is_not_a_test_class():
    assert TestSet.__test__ is False
