"""Weights & Biases as a first-class logger (``logger=wandb``; offline by default, ``wandb sync`` uploads later).

Whenever a run has a ``WandbLogger``, :func:`wandb_callbacks` adds :class:`WandbReport`: the resolved config, and
for a test each pair's results as the ``test/pairs`` ``wandb.Table`` (pair id, overlap, errors, time) and the
first pairs as ``wandb.Object3D`` (source, reference, aligned source; OMNet's predicted overlap masks too).
:func:`log_card` logs the run's card (the context and metrics of ``metrics.json``) and finishes the run;
:func:`log_grid` logs a grid's tidy table. :func:`read_offline_run` reads back what an offline run wrote (what the tests check).
"""

from __future__ import annotations

import glob
import json
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
from omegaconf import DictConfig, OmegaConf

from src.utils.errors import ConfigError
from src.metrics import PAIR_ERRORS

#: RGB colours of the clouds of an Object3D: source, reference, aligned source; an OMNet mask's kept / dropped points.
COLOURS = {"source": (228, 26, 28), "reference": (77, 175, 74), "aligned": (55, 126, 184),
           "kept": (255, 127, 0), "dropped": (153, 153, 153)}
PAIR_COLUMNS = ["pair", "overlap", *PAIR_ERRORS[:4], "seconds"]
#: Radius of the overlap fraction, in median point spacings of the reference (as the scan pairs' overlap).
OVERLAP_SPACINGS = 2.0


def wandb_experiment(loggers: Any) -> Any | None:
    """The wandb run of the first ``WandbLogger`` among ``loggers`` (a Trainer's), or None."""
    from lightning.pytorch.loggers import WandbLogger

    return next((logger.experiment for logger in loggers if isinstance(logger, WandbLogger)), None)


def object3d(*clouds: tuple[np.ndarray, tuple[int, int, int] | np.ndarray]) -> Any:
    """One ``wandb.Object3D`` of several clouds (N, 3), each with one colour or a colour per point (N, 3)."""
    import wandb

    rows = [np.hstack([points, np.broadcast_to(np.asarray(colour, dtype=np.float64), points.shape)])
            for points, colour in clouds]
    return wandb.Object3D(np.vstack(rows))


def _mask_colours(mask: np.ndarray) -> np.ndarray:
    return np.where(mask[:, None] > 0.5, COLOURS["kept"], COLOURS["dropped"]).astype(np.float64)


def _overlap(src: np.ndarray, ref: np.ndarray, gt: np.ndarray) -> float:
    """Fraction of the source within OVERLAP_SPACINGS median spacings of the reference, under the ground truth."""
    from src.data.transforms import median_spacing, overlap_fraction
    from src.geometry.numpy_rigid import apply_transform

    return overlap_fraction(apply_transform(gt, src), ref, OVERLAP_SPACINGS * median_spacing(ref))


class WandbReport(L.Callback):
    """The resolved config at the start; a test's per-pair table and its first ``objects`` pairs in 3D at its end."""

    def __init__(self, cfg: DictConfig, objects: int = 4) -> None:
        if objects < 0:
            raise ConfigError(f"wandb objects must be >= 0, got {objects}")
        self.config = OmegaConf.to_container(cfg, resolve=True)
        self.objects = objects
        self.rows: list[list[float]] = []
        self.clouds: dict[str, Any] = {}
        self._start = 0.0

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        run = wandb_experiment(trainer.loggers)
        if run is not None and trainer.is_global_zero:
            run.config.update(self.config, allow_val_change=True)

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.rows, self.clouds = [], {}

    def on_test_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0) -> None:
        self._start = time.perf_counter()

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        if outputs is None or not trainer.is_global_zero:
            return
        from src.metrics import pair_errors
        from src.geometry.numpy_rigid import apply_transform

        seconds = (time.perf_counter() - self._start) / len(batch["points_src"])
        pred = outputs["transforms"][-1].detach().float()
        errors = {k: v.cpu().numpy() for k, v in pair_errors(pred, batch["transform_gt"], pl_module.hparams["euler_seq"]).items()}
        src, ref = batch["points_src"].cpu().numpy(), batch["points_ref"].cpu().numpy()
        gt, pred = batch["transform_gt"].cpu().numpy().astype(np.float64), pred.cpu().numpy().astype(np.float64)
        masks = outputs.get("masks") or None
        for i, pair in enumerate(batch["idx"].tolist()):
            overlap = float(batch["overlap"][i]) if "overlap" in batch else _overlap(src[i], ref[i], gt[i])
            self.rows.append([pair, overlap, float(errors["rot_deg"][i]), float(errors["trans_norm"][i]),
                              float(np.abs(errors["euler_err"][i]).mean()), float(np.abs(errors["trans_err"][i]).mean()),
                              seconds])
            if len(self.clouds) < self.objects:
                aligned = apply_transform(pred[i], src[i])
                self.clouds[f"test/objects/pair_{pair}"] = object3d(
                    (src[i], COLOURS["source"]), (ref[i], COLOURS["reference"]), (aligned, COLOURS["aligned"]))
                if masks:
                    mask_src, mask_ref = (m[i].detach().float().cpu().numpy() for m in masks[-1])
                    self.clouds[f"test/overlap_masks/pair_{pair}"] = object3d(
                        (aligned, _mask_colours(mask_src)), (ref[i], _mask_colours(mask_ref)))

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        run = wandb_experiment(trainer.loggers)
        if run is None or not trainer.is_global_zero:
            return
        import wandb

        run.log({"test/pairs": wandb.Table(columns=PAIR_COLUMNS, data=self.rows), **self.clouds})


def wandb_callbacks(cfg: DictConfig, loggers: list) -> list[L.Callback]:
    """``[WandbReport]`` when ``loggers`` hold a WandbLogger, else none."""
    from lightning.pytorch.loggers import WandbLogger

    if not any(isinstance(logger, WandbLogger) for logger in loggers):
        return []
    return [WandbReport(cfg)]


def log_card(trainer: L.Trainer, card: dict[str, Any]) -> None:
    """The run's card (what ``metrics.json`` holds) as ``card`` in the wandb summary, when the run logs to wandb;
    then the run is finished (written out; a later run in the same process starts its own)."""
    run = wandb_experiment(trainer.loggers)
    if run is not None:
        run.summary["card"] = card
        run.finish()


def log_grid(cfg: DictConfig, tidy: Any) -> None:
    """A grid's tidy table (``results.csv``) as ``grid/results`` of one wandb run, when ``wandb.enabled``;
    the run's config is the grid's resolved config and it joins the grid's ``wandb.group``."""
    options = cfg.get("wandb") or {}
    if not options.get("enabled"):
        return
    import wandb

    run = wandb.init(project=options.get("project", "omnet-registration"), name=f"grid/{cfg.benchmark.name}",
                     group=options.get("group"), dir=str(cfg.output_dir), mode=options.get("mode", "offline"),
                     config=OmegaConf.to_container(cfg, resolve=True), job_type="grid")
    run.log({"grid/results": wandb.Table(dataframe=tidy.astype({c: str for c in tidy.select_dtypes("object")}))})
    run.finish()


# --- reading an offline run back ------------------------------------------------------------------------------


@dataclass
class OfflineRun:
    """What an offline run wrote: its config, group, summary, logged keys and its media files (JSON)."""

    path: Path
    config: dict[str, Any] = field(default_factory=dict)
    group: str = ""
    summary: dict[str, Any] = field(default_factory=dict)
    logged: set[str] = field(default_factory=set)

    def media(self, kind: str, key: str) -> list[dict[str, Any]]:
        """The JSON files of ``kind`` (``table``, ``object3D``) logged under ``key``, in the order written."""
        pattern = str(self.path / "files" / "media" / kind / f"{key}_*.json")
        return [json.loads(Path(f).read_text()) for f in sorted(glob.glob(pattern), key=lambda f: Path(f).stat().st_mtime)]


#: The run file's framing (W&B's LevelDB-style log): a 7-byte file header, then 32 KiB blocks of records, each
#: with a 7-byte header (CRC-32, length, type: 1 full, 2 first, 3 middle, 4 last).
_BLOCK, _HEADER = 32768, 7


def _records(data: bytes) -> list[bytes]:
    records, chunks, pos = [], [], _HEADER
    while pos + _HEADER <= len(data):
        left = _BLOCK - pos % _BLOCK
        if left < _HEADER:
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", data[pos:pos + _HEADER])
        if kind == 0 and length == 0:  # the zero padding at a block's end
            pos += left
            continue
        chunks.append(data[pos + _HEADER:pos + _HEADER + length])
        pos += _HEADER + length
        if kind in (1, 4):
            records.append(b"".join(chunks))
            chunks = []
    return records


def _finished_records(path: Path, wait_s: float) -> list[Any]:
    """The records of the run file in ``path`` once its ``exit`` record is there (wandb writes it out after
    ``finish()`` returns, from its service process), waiting up to ``wait_s`` seconds."""
    from wandb.proto import wandb_internal_pb2 as pb

    deadline = time.monotonic() + wait_s
    while True:
        files = sorted(path.glob("run-*.wandb"))
        records = [pb.Record.FromString(data) for data in _records(files[0].read_bytes())] if files else []
        if any(record.WhichOneof("record_type") == "exit" for record in records):
            return records
        if time.monotonic() > deadline:
            raise ConfigError(f"{path} holds no finished wandb run (no run-*.wandb file with an exit record "
                              f"after {wait_s:g} s): not an offline run folder, or its run is still open")
        time.sleep(0.2)


def read_offline_run(run_dir: str | Path, wait_s: float = 30.0) -> OfflineRun:
    """Parse a finished offline run folder (``wandb/offline-run-*``): its ``run-*.wandb`` records and media files."""
    run = OfflineRun(Path(run_dir))
    for record in _finished_records(run.path, wait_s):
        kind = record.WhichOneof("record_type")
        if kind == "run":
            run.group = record.run.run_group or run.group  # later run records may leave it empty
            run.config.update({i.key: json.loads(i.value_json) for i in record.run.config.update})
        elif kind == "config":
            run.config.update({i.key: json.loads(i.value_json) for i in record.config.update})
        elif kind == "summary":
            run.summary.update({i.key: json.loads(i.value_json) for i in record.summary.update if i.key})
        elif kind == "history":
            run.logged.update(i.key or i.nested_key[0] for i in record.history.item)  # a medium's key, not its fields
    return run
