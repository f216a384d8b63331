"""Evaluate a checkpoint on an experiment's fixed test set and print the metrics table.

    python -m src.eval +exp=unseen_categories data=synthetic   # the shipped checkpoint for it (checkpoints/*.json)
    python -m src.eval +exp=unseen_categories ckpt_path=outputs/.../checkpoints/best-*.ckpt
    python -m src.eval +exp=real_airplane ckpt_path=checkpoints/rpmnet_real_airplane_ts_prnet.ckpt   # model= from the file
    python -m src.eval -m +sweep=overlap ckpt_path=...    # overlap ratio 1.0 -> 0.1 (docs/sweeps.md)
    python -m src.eval model=dcp +exp=dcp_protocol data=modelnet40 weights=official:dcp_v1   # published weights

In float32 unless ``trainer.precision=...`` is given (``trainer.precision=bf16-mixed``: bf16 autocast), whatever
precision trained the checkpoint; ``metrics.json`` records ``test_precision``.

``weights`` (instead of ``ckpt_path``): ``official:<name>`` or a file of a known layout, imported into the
configured model's network class by the function ``weights_importer`` names
(``baselines.learned.published.published_module``: the network's settings come from the weights' registry
entry; the metric convention from the experiment).
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import hydra
import lightning as L
from omegaconf import DictConfig, OmegaConf

from src.config import register_resolvers
from src.models.module import RegistrationModule
from src.models.pretrained import find_shipped, trained_precision
from src.run.batch_limits import refuse_empty_limits
from src.run.checkpoint_io import (
    check_checkpoint,
    read_checkpoint,
    read_checkpoint_network,
)
from src.run.evaluated import checkpoint_weights, evaluated_record
from src.run.failures import job_main
from src.run.memory import refuse_beyond_memory
from src.run.precision import settle_precision
from src.run.recorded import refuse_unread_overrides, refuse_unused_in_eval
from src.run.reporting import report_test_metrics, save_resolved_config
from src.run.trained_on import refuse_test_overlap
from src.run.trainer import build_trainer
from src.utils.errors import CheckpointError, ConfigError
from src.utils.paths import CONF_DIR

register_resolvers()
log = logging.getLogger(__name__)


def load_checkpoint(path: str, cfg: DictConfig) -> RegistrationModule:
    """Load a RegistrationModule checkpoint, checking it holds the configured network and that no
    model override is lost (src/run/recorded.py); the metric convention is the experiment's."""
    refuse_unused_in_eval(cfg, check_checkpoint(path, cfg.model.network._target_), path)
    convention = {"euler_seq": cfg.model.euler_seq} if cfg.model.get("euler_seq") else {}
    return RegistrationModule.load_from_checkpoint(path, map_location="cpu", **convention)


def resolve_checkpoint(cfg: DictConfig) -> str:
    """``ckpt_path``, or else the shipped checkpoint trained for this experiment and network."""
    if cfg.ckpt_path:
        return str(cfg.ckpt_path)
    identity = {"task": cfg.task_name, "dataset": cfg.data.dataset, "sampling": cfg.sampling, "partial": cfg.partial}
    path = find_shipped(identity, network=cfg.model.network._target_)
    card = json.loads(path.with_suffix(".json").read_text())
    log.info("no ckpt_path given: evaluating the shipped checkpoint %s (trained in %s; see %s)", path,
             trained_precision(card), path.with_suffix(".json").name)
    return str(path)


def load_module(cfg: DictConfig) -> tuple[RegistrationModule, str]:
    """The module to evaluate and what it was loaded from (``weights`` or a checkpoint)."""
    if cfg.get("init_weights"):
        raise ConfigError(f"init_weights={cfg.init_weights} is for src.train (a start for training): evaluate the "
                          "checkpoint with ckpt_path=PATH")
    weights = cfg.get("weights")
    if not weights:
        ckpt_path = resolve_checkpoint(cfg)
        return load_checkpoint(ckpt_path, cfg), ckpt_path
    if cfg.ckpt_path:
        raise ConfigError("give either ckpt_path=PATH or weights=official:<name>, not both")
    # Named by the config (as a network by its _target_), not imported: the weights' records and converters
    # are the baselines', a layer above src.
    importer = hydra.utils.get_method(str(cfg.weights_importer))
    module = importer(str(weights), cfg.model, expected_target=cfg.model.network._target_)
    log.info("evaluating published weights %s (network: %s)", weights, module.hparams["network"])
    return module, str(weights)


def evaluate(cfg: DictConfig) -> dict[str, float]:
    refuse_unread_overrides(cfg)
    L.seed_everything(cfg.seed, workers=True, verbose=False)  # a network that samples at test (PRNet) repeats
    module, ckpt_path = load_module(cfg)
    precision = settle_precision(cfg, evaluation=True)  # float32 unless trainer.precision is given
    save_resolved_config(cfg)
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("test")
    refuse_empty_limits(cfg, datamodule, ("test",))
    checkpoint = None if cfg.get("weights") else read_checkpoint(ckpt_path)
    overlap = {"test_overlap_checked": False} if checkpoint is None else refuse_test_overlap(checkpoint, ckpt_path,
                                                                                              datamodule)
    tested = f"{ckpt_path} (published weights)" if checkpoint is None else checkpoint_weights(ckpt_path, checkpoint)
    trainer = build_trainer(cfg, with_checkpoints=False, precision=precision)
    refuse_beyond_memory(module.network, datamodule, trainer, ("test",))
    trainer.test(module, datamodule=datamodule, verbose=False)
    metrics = module.test_results
    report_test_metrics(trainer, cfg, metrics, ckpt_path, tested, test_precision=trainer.precision,
                        **evaluated_record(trainer), **overlap)
    return metrics


def model_of_checkpoint(overrides: list[str], model_dir: Path = CONF_DIR / "model") -> list[str]:
    """``overrides`` with ``model=<name>`` added when ``ckpt_path=`` names a readable checkpoint and no
    ``model=`` is given: the model config (``conf/model/<name>.yaml``) whose network the checkpoint holds, so
    that ``src.eval +exp=E ckpt_path=checkpoints/<method>_....ckpt`` evaluates any method's checkpoint. Anything
    else (no checkpoint, unreadable, no single matching config) is left to :func:`load_checkpoint`'s one-line check."""
    paths = [o.split("=", 1)[1] for o in overrides if o.startswith("ckpt_path=")]
    if len(paths) != 1 or any(o.lstrip("+~").startswith("model=") for o in overrides):
        return overrides
    try:
        target = read_checkpoint_network(paths[0])
    except CheckpointError:
        return overrides
    names = [f.stem for f in sorted(model_dir.glob("*.yaml"))
             if OmegaConf.select(OmegaConf.load(f), "network._target_") == target]
    return [*overrides, f"model={names[0]}"] if len(names) == 1 else overrides


main = job_main(evaluate)

if __name__ == "__main__":
    sys.argv[1:] = model_of_checkpoint(sys.argv[1:])
    main()
