"""The CSV logger of every run (``conf/logger/csv.yaml``): Lightning's CSVLogger, its files written atomically.

``metrics.csv`` and ``hparams.yaml`` are written whole to a temporary beside them, then renamed
(:func:`src.utils.files.write_atomic`): a full disk or a folder without write permission is one
:class:`~src.utils.errors.DiskError` line naming the file and its folder (Lightning's writer gave a traceback,
and a header rewrite on a full disk could truncate the rows already written), the file keeps the rows
written before, and the rows not written stay pending for the next save. Checkpoints are not touched.
Local folders only (the run's ``output_dir``).
"""

from __future__ import annotations

import csv
import logging
from pathlib import Path
from typing import Any

from lightning.fabric.loggers.logger import rank_zero_experiment
from lightning.pytorch.core.saving import save_hparams_to_yaml
from lightning.pytorch.loggers import CSVLogger as LightningCSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter

from src.utils.errors import DiskError
from src.utils.files import disk_errors, write_atomic

log = logging.getLogger(__name__)


def _read_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of a CSV file written before (none if there is none)."""
    if not path.is_file():
        return []
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def _write_rows(path: Path, fieldnames: list[str], rows: list[dict[str, Any]]) -> None:
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fieldnames)
        writer.writeheader()
        writer.writerows(rows)


class AtomicExperimentWriter(ExperimentWriter):
    """Lightning's ExperimentWriter whose ``save`` and ``log_hparams`` write whole files atomically; the
    DiskError of a failed save is kept in ``disk_error`` (its pending rows in ``metrics``)."""

    disk_error: DiskError | None = None

    def save(self) -> None:
        """Write the rows written before and the pending ones to ``metrics.csv`` (one header for all keys)."""
        if not self.metrics:
            return
        self._record_new_keys()
        path = Path(self.metrics_file_path)
        rows = _read_rows(path) + self.metrics
        try:
            write_atomic(path, lambda tmp: _write_rows(tmp, self.metrics_keys, rows))
        except DiskError as err:
            self.disk_error = err
            raise
        self.metrics = []

    def log_hparams(self, params: dict[str, Any]) -> None:
        """Record hparams and write ``hparams.yaml`` atomically."""
        self.hparams.update(params)
        write_atomic(Path(self.log_dir) / self.NAME_HPARAMS_FILE, lambda tmp: save_hparams_to_yaml(tmp, self.hparams))


class CSVLogger(LightningCSVLogger):
    """Lightning's CSVLogger writing through :class:`AtomicExperimentWriter` (module docstring)."""

    @property
    @rank_zero_experiment
    def experiment(self) -> AtomicExperimentWriter:
        if self._experiment is not None:
            return self._experiment
        with disk_errors("creating the CSV log folder", Path(self.root_dir).parent):
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = AtomicExperimentWriter(log_dir=self.log_dir)
        return self._experiment

    def finalize(self, status: str) -> None:
        """Save the pending rows; when the run already fails, a disk error here does not mask its error (the
        disk error that stopped the run is that error; another is logged)."""
        if status == "success":
            super().finalize(status)
            return
        first = self._experiment.disk_error if isinstance(self._experiment, AtomicExperimentWriter) else None
        try:
            super().finalize(status)
        except DiskError as err:
            if first is None:
                log.error("metrics.csv not saved: %s", err)
