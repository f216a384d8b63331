"""Disk faults: a full disk while preparing, checkpointing, logging metrics (metrics.csv) or
writing results is one line (what, where), leaves no temporary and keeps what was written; a valid cache on a read-only mount is read; a cache folder
without write permission says so. The real cases run on a small tmpfs (root only, else skipped); the
errno cases are injected at the write layer and run everywhere."""

from __future__ import annotations

import errno
import os
import subprocess
from pathlib import Path

import pytest
import torch

from src.run.checkpoint_io import AtomicCheckpointIO
from src.data.prepare import build_synthetic_cache, prepare
from src.utils.errors import DiskError
from src.utils.files import write_text_atomic

SMALL = {"num_train_per_category": 1, "num_test_per_category": 1, "num_samplings": 2, "num_points": 64}


def _mount(target: Path, *options: str) -> None:
    result = subprocess.run(["mount", *options, str(target)], capture_output=True, text=True)
    if result.returncode:
        pytest.skip(f"cannot mount here ({result.stderr.strip()[:80]})")


@pytest.fixture
def tiny_disk(tmp_path):
    """A 256 kB tmpfs: far too small for any cache or checkpoint."""
    disk = tmp_path / "disk"
    disk.mkdir()
    _mount(disk, "-t", "tmpfs", "-o", "size=256k", "tmpfs")
    yield disk
    subprocess.run(["umount", "--lazy", str(disk)], check=True)  # (a traceback may hold a file open)


@pytest.fixture
def read_only(tmp_path):
    """``make(folder)`` bind-mounts ``folder`` read-only at ``<tmp>/ro`` (what root cannot write either)."""
    mounted = []

    def make(folder: Path) -> Path:
        view = tmp_path / "ro"
        view.mkdir()
        _mount(view, "--bind", str(folder))
        mounted.append(view)
        _mount(view, "-o", "remount,ro,bind", str(folder))
        return view

    yield make
    for view in mounted:
        subprocess.run(["umount", "--lazy", str(view)], check=True)


def test_prepare_on_a_full_disk_is_one_line_and_leaves_no_temporary(resampled_dir, tiny_disk):
    """Died by SIGBUS (a memory-mapped write beyond the free space) leaving an 80 MB temporary for good."""
    for i in range(40):  # shapes big enough to overflow the disk
        (resampled_dir / "airplane" / "airplane_0001.txt").open("a").write("0.1,0.2,0.3,0,0,1\n" * 100)
    with pytest.raises(DiskError, match=rf"^writing the cache modelnet40_resampled: the disk of {tiny_disk} is full, "):
        prepare("modelnet40_resampled", source=resampled_dir, cache_root=tiny_disk)
    assert [p.name for p in tiny_disk.iterdir()] == [".modelnet40_resampled.lock"]


def test_a_checkpoint_on_a_full_disk_is_one_line_and_leaves_no_temporary(tiny_disk):
    """torch.save says only 'unexpected pos' (a RuntimeError): the free space tells."""
    with pytest.raises(DiskError, match=rf"^writing last.ckpt: the disk of {tiny_disk} is full, "):
        AtomicCheckpointIO().save_checkpoint({"weights": torch.zeros(200_000)}, tiny_disk / "last.ckpt")
    assert list(tiny_disk.iterdir()) == []


@pytest.mark.parametrize("code, cause", [(errno.ENOSPC, "is full"), (errno.EDQUOT, "is full"),
                                         (errno.EACCES, "cannot write in")])
def test_write_errors_are_one_line_without_temporaries(tmp_path, monkeypatch, code, cause):
    def failing(fd, offset, length):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(os, "posix_fallocate", failing)  # the cache writer reserves its arrays
    with pytest.raises(DiskError, match=f"^writing the cache synthetic: .*{cause}"):
        build_synthetic_cache(tmp_path, **SMALL)
    assert [p.name for p in tmp_path.iterdir()] == [".synthetic.lock"]

    def denied(path: Path) -> None:
        raise OSError(code, os.strerror(code))

    with pytest.raises(DiskError, match=f"^writing metrics.json: .*{cause}"):
        from src.utils.files import write_atomic

        write_atomic(tmp_path / "metrics.json", denied)
    assert not list(tmp_path.glob(".metrics.json.*"))


def test_a_valid_cache_on_a_read_only_mount_is_read_and_a_rebuild_says_why(tmp_path, read_only):
    build_synthetic_cache(tmp_path / "cache", **SMALL)
    view = read_only(tmp_path / "cache")
    cache = build_synthetic_cache(view, **SMALL)  # took a lock file beside it: OSError (read-only file system)
    assert cache.split("train").points.shape[1:] == (2, 64, 3)
    with pytest.raises(DiskError, match=rf"^locking the cache synthetic to build it: cannot write in {view} "
                                        r"\(Read-only file system\): make it writable"):
        build_synthetic_cache(view, **{**SMALL, "num_points": 32})  # another build: it must write


def test_text_writes_name_the_file_and_folder(tmp_path, read_only):
    (tmp_path / "out").mkdir()
    view = read_only(tmp_path / "out")
    with pytest.raises(DiskError, match=rf"^writing config_resolved.yaml: cannot write in {view} "):
        write_text_atomic(view / "config_resolved.yaml", "x")


def _fill(disk: Path) -> None:
    """Write a filler file until the disk is full."""
    with open(disk / "filler", "wb", buffering=0) as handle, pytest.raises(OSError) as info:
        while True:
            handle.write(b"\0" * 4096)
    assert info.value.errno == errno.ENOSPC


def test_metrics_csv_on_a_full_disk_is_one_line_and_keeps_its_rows(tiny_disk):
    """Lightning's writer gave a traceback, and a new column's header rewrite truncated the rows on a full disk."""
    from src.run.csv_logging import CSVLogger

    logger = CSVLogger(tiny_disk, name="csv")
    logger.log_metrics({"train/loss": 1.0}, step=0)
    logger.save()
    log_dir = Path(logger.log_dir)
    written = (log_dir / "metrics.csv").read_text()
    _fill(tiny_disk)
    logger.log_metrics({"train/loss": 0.5, "val/score": 2.0, "note": "x" * 8192}, step=1)  # a new column
    with pytest.raises(DiskError, match=rf"^writing metrics.csv: the disk of {log_dir} is full, "):
        logger.save()
    assert (log_dir / "metrics.csv").read_text() == written and sorted(p.name for p in log_dir.iterdir()) == ["metrics.csv"]
    (tiny_disk / "filler").unlink()
    logger.finalize("success")  # the pending rows were kept
    assert (log_dir / "metrics.csv").read_text().splitlines()[0] == "note,step,train/loss,val/score"


def test_a_full_disk_while_training_logs_is_one_line_and_keeps_the_checkpoints(tmp_path, monkeypatch, capsys):
    """The disk fills during training: the CSV log's third save fails (ENOSPC) after last.ckpt is written."""
    import csv

    import src.train
    from tests.helpers.registration_helpers import TINY, compose_config

    run = tmp_path / "run"
    cfg = compose_config(*TINY, f"data.cache_root={tmp_path / 'cache'}", f"output_dir={run}", "+exp=unseen_shapes",
                         "trainer.max_steps=6", "test_after_fit=false", "trainer.log_every_n_steps=1",
                         "trainer.limit_val_batches=1", "trainer.val_check_interval=2",
                         "trainer.check_val_every_n_epoch=null", "callbacks.periodic_checkpoint.train_time_interval=null",
                         "+callbacks.periodic_checkpoint.every_n_train_steps=1")
    saves, writerows = [], csv.DictWriter.writerows

    def filling(self, rows):
        saves.append(1)
        if len(saves) > 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return writerows(self, rows)

    monkeypatch.setattr(csv.DictWriter, "writerows", filling)
    with pytest.raises(SystemExit) as info:
        src.train.main.__wrapped__(cfg)
    log_dir = run / "csv" / "version_0"
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: writing metrics.csv: the disk of {log_dir} is full"), err
    monkeypatch.undo()
    assert len(list(csv.DictReader((log_dir / "metrics.csv").open()))) >= 2  # the rows written before
    assert not list(log_dir.glob(".*.tmp")) and (run / "failure.json").is_file()
    checkpoint = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert checkpoint["global_step"] >= 1
