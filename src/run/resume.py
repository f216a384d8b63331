"""Resuming a run in its own folder, and the command that does it.

* ``ckpt_path=last`` resumes the run dir's own ``checkpoints/last.ckpt`` (with ``hydra.run.dir=<run dir>``,
  or every job of a multirun with ``hydra.sweep.dir=<sweep dir>``); a run dir without one starts at step 0 (one
  line says so; the logs and checkpoints of a run stopped there before its first ``last.ckpt`` are moved into
  ``stopped_before_checkpoint_<n>/`` in it), and a run that already trained its ``max_steps`` and was tested
  (its ``metrics.json``) is left as it is. A run resumed in its own folder keeps its checkpoints' tracking (the
  best checkpoint and its score), which Lightning drops when the checkpoint folder changed.
* :func:`resume_command` is the exact command that does it for the running Hydra job, printed when a signal
  stops a run (:mod:`src.run.signals`, :mod:`src.run.failures`).
"""

from __future__ import annotations

import itertools
import json
import logging
import re
import shlex
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from src.utils.files import disk_errors

log = logging.getLogger(__name__)

#: ``ckpt_path=last``: the run dir's own ``checkpoints/last.ckpt``.
LAST = "last"
PROGRAM = "python -m src.train"
#: Overrides the resume command sets itself (a sweep's own choice of them is replaced).
REPLACED = ("ckpt_path", "hydra.run.dir", "hydra.sweep.dir", "hydra.mode")
#: Overrides that only start a run: a resumed run goes on from its own weights (src.train refuses ``init_weights``
#: beside ``ckpt_path``).
STARTS_ONLY = ("init_weights",)


def own_last_checkpoint(run_dir: Path) -> Path:
    """Where a run in ``run_dir`` keeps its ``last.ckpt`` (``conf/callbacks/default.yaml``)."""
    return run_dir / "checkpoints" / "last.ckpt"


def best_checkpoint(run_dir: Path) -> Path | None:
    """The checkpoint a run in ``run_dir`` selected: the one ``src.train`` tested (``metrics.json``), else the newest
    ``checkpoints/best-*.ckpt``; None when it has neither."""
    metrics = run_dir / "metrics.json"
    if metrics.is_file():
        recorded = json.loads(metrics.read_text()).get("checkpoint")
        if recorded and Path(recorded).is_file():
            return Path(recorded)
    found = sorted((run_dir / "checkpoints").glob("best-*.ckpt"), key=lambda p: p.stat().st_mtime)
    return found[-1] if found else None


def finished_record(cfg: DictConfig) -> Path | None:
    """For ``ckpt_path=last``: the run dir's ``metrics.json`` when the run there trained ``trainer.max_steps``
    and was tested (nothing to resume), else None."""
    record = Path(cfg.output_dir) / "metrics.json"
    if cfg.get("ckpt_path") != LAST or not record.is_file():
        return None
    steps = json.loads(record.read_text()).get("global_step")
    max_steps = cfg.trainer.get("max_steps")
    return record if steps is not None and max_steps is not None and 0 < max_steps <= steps else None


#: What a run stopped before its first ``last.ckpt`` leaves in its folder, moved aside by ``ckpt_path=last``.
STOPPED_RUN_FILES = ("csv", "checkpoints")
#: The folder (in the run dir, numbered) they are moved into.
STOPPED_BEFORE_CHECKPOINT = "stopped_before_checkpoint"


def resolve_ckpt_path(cfg: DictConfig) -> str | None:
    """``cfg.ckpt_path`` with ``last`` resolved to the run dir's own ``last.ckpt``; None when it has none: the run
    starts at step 0, and what a run stopped there before its first ``last.ckpt`` left is moved aside (kept, out of
    the new run's logs), so that the folder takes the new run."""
    if cfg.get("ckpt_path") != LAST:
        return cfg.get("ckpt_path")
    run_dir = Path(cfg.output_dir)
    last = own_last_checkpoint(run_dir)
    if last.is_file():
        return str(last)
    moved = _set_aside(run_dir)
    kept = f"; the stopped run's {', '.join(p.name for p in moved)} moved to {moved[0].parent}" if moved else ""
    log.info("ckpt_path=last: no %s yet (no checkpoint was written), training starts at step 0%s", last, kept)
    return None


def _set_aside(run_dir: Path) -> list[Path]:
    """Move the :data:`STOPPED_RUN_FILES` in ``run_dir`` into a new ``stopped_before_checkpoint_<n>``; their paths."""
    found = [run_dir / name for name in STOPPED_RUN_FILES if (run_dir / name).exists()]
    if not found:
        return []
    folder = next(f for n in itertools.count(1) if not (f := run_dir / f"{STOPPED_BEFORE_CHECKPOINT}_{n}").exists())
    with disk_errors("moving aside a run stopped before its first checkpoint", run_dir):
        folder.mkdir()
        return [path.rename(folder / path.name) for path in found]


@contextmanager
def resuming_in_place(ckpt_path: str | None, output_dir: str | Path) -> Iterator[None]:
    """Within the block, Lightning's warning that the checkpoint folder is not empty is not shown when the
    checkpoint resumed lies in that folder (the run's own checkpoints, kept and tracked on purpose)."""
    folder = own_last_checkpoint(Path(output_dir)).parent
    with warnings.catch_warnings():
        if ckpt_path is not None and Path(ckpt_path).resolve().parent == folder.resolve():
            warnings.filterwarnings("ignore", message=f"Checkpoint directory {re.escape(str(folder))} exists and is not empty")
        yield


def _shown(path: Path) -> str:
    """``path`` relative to the working directory when inside it (as a user types it), else absolute."""
    path = path.resolve()
    try:
        return str(path.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def resumed_overrides(overrides: Sequence[str]) -> list[str]:
    """``overrides`` less those that only start a run (:data:`STARTS_ONLY`): what resuming it takes beside its
    ``ckpt_path``."""
    return [o for o in overrides if _key(o) not in STARTS_ONLY]


def _kept(overrides: Sequence[str]) -> list[str]:
    return [o for o in resumed_overrides(overrides) if _key(o) not in REPLACED]


def run_command(overrides: Sequence[str], run_dir: Path, checkpoint: Path) -> str:
    """``python -m src.train`` with ``overrides`` resuming the run in ``run_dir`` from ``checkpoint``."""
    tail = [*_kept(overrides), f"hydra.run.dir={_shown(run_dir)}", f"ckpt_path={_shown(checkpoint)}"]
    return f"{PROGRAM} {shlex.join(tail)}"


def sweep_command(overrides: Sequence[str], sweep_dir: Path) -> str:
    """``python -m src.train -m`` with the sweep's ``overrides`` resuming every job of ``sweep_dir`` in its folder."""
    tail = ["-m", *_kept(overrides), f"hydra.sweep.dir={_shown(sweep_dir)}", f"ckpt_path={LAST}"]
    return f"{PROGRAM} {shlex.join(tail)}"


def resume_command(checkpoint: str | Path) -> str | None:
    """The command that resumes the running Hydra job in its own folder from ``checkpoint``: the job's
    overrides, its run dir and the checkpoint; in a multirun, the sweep's overrides (its ``multirun.yaml``)
    with its sweep dir and ``ckpt_path=last`` (a job of a multirun that recorded none: the job alone, in its
    folder). None outside a Hydra job."""
    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.get()
    recorded = Path(hc.sweep.dir) / "multirun.yaml"
    if hc.mode == RunMode.MULTIRUN and recorded.is_file():
        sweep = OmegaConf.load(recorded).hydra.overrides
        return sweep_command([*sweep.hydra, *sweep.task], Path(hc.sweep.dir))
    return run_command([*hc.overrides.hydra, *hc.overrides.task], Path(hc.runtime.output_dir), Path(checkpoint))
