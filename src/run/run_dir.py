"""One training run per run folder: a second training given the folder of another (``hydra.run.dir`` or
``output_dir``) is refused before it writes anything, instead of mixing its checkpoints, logs and metrics
with the first run's (the first run's final state would be lost). Resuming the run in its own folder
(``hydra.run.dir=<run dir> ckpt_path=last``) is the one way back in.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from src.run.resume import own_last_checkpoint
from src.utils.errors import ConfigError

#: What a run that trained leaves in its folder (a run refused before training leaves none of them: it may be
#: rerun there): its logs (from the first step), checkpoints and test metrics.
RUN_MARKERS = ("csv", "checkpoints", "metrics.json")


def refuse_reused_run_dir(cfg: DictConfig) -> None:
    """ConfigError when ``cfg.output_dir`` holds another run's files, unless ``ckpt_path`` resumes that run
    from its own ``checkpoints/last.ckpt``."""
    folder = Path(cfg.output_dir)
    found = [name for name in RUN_MARKERS if (folder / name).exists()]
    if not found:
        return
    own_last = own_last_checkpoint(folder)
    if cfg.get("ckpt_path") and Path(cfg.ckpt_path).resolve() == own_last.resolve():
        return
    raise ConfigError(f"{folder} already holds a run ({', '.join(found)}): a second training there would mix its files "
                      f"with that run's; give a new folder (hydra.run.dir=...), or resume that run with "
                      f"hydra.run.dir={folder} ckpt_path=last")
