"""What is recorded is what ran: a command-line override an entry point cannot honour is refused in one
line (the key and why), instead of being written into ``config_resolved.yaml`` and ignored.

* ``src.eval`` rebuilds the network from the checkpoint: a ``model.network.*`` or ``model_scale`` override
  that differs from the checkpoint's value cannot take effect (:func:`refuse_unused_in_eval`), and an
  evaluation study labelled by it would print the same numbers under each label. (The metric convention
  ``model.euler_seq`` does take effect: it follows the experiment. Training-only settings, e.g. an override
  list shared with ``src.train``, change no evaluated number and pass.)
* ``src.train`` trains from scratch, from a checkpoint's weights (``init_weights``) or resumes from
  ``ckpt_path`` (not both): ``weights=`` is for ``src.eval``; a
  checkpoint selected on validation (``callbacks.checkpoint.monitor``) needs a validation that runs
  (``trainer.limit_val_batches=0`` turns it off) and a checkpoint kept (``save_top_k=0`` keeps none): else
  the test would run on the last weights, not the selected ones (:func:`refuse_unused_in_train`).
* Both: a data override that the run's pair pipeline does not read (:data:`READ_ONLY_WITH`, e.g.
  ``data.pair.rpmnet_p_keep`` in the PRNet manner, OMNet's ``model.network.topk`` under argmax masks) is
  refused (:func:`refuse_unread_overrides`).
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from src.utils.config_values import plain
from src.utils.errors import ConfigError


def command_overrides() -> list[str]:
    """The command line's overrides of the running Hydra job (none outside one)."""
    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def _scaled_keys(cfg: DictConfig) -> list[str]:
    """The network keys whose value is ``${model_scale}``."""
    raw = OmegaConf.to_container(cfg.model.network, resolve=False)
    return [k for k, v in raw.items() if isinstance(v, str) and "${model_scale}" in v]


def refuse_unused_in_eval(cfg: DictConfig, hparams: Mapping[str, Any], ckpt_path: str,
                          overrides: Sequence[str] | None = None) -> None:
    """ConfigError for the first override of ``src.eval`` that cannot take effect (module docstring)."""
    for override in command_overrides() if overrides is None else overrides:
        key = _key(override)
        if key == "model_scale" or key.startswith("model.network."):
            names = [f"network.{k}" for k in _scaled_keys(cfg)] if key == "model_scale" else [key.removeprefix("model.")]
            for name in names:
                theirs = _select(hparams, name)
                if plain(OmegaConf.select(cfg.model, name, default=None)) != theirs:
                    raise ConfigError(
                        f"{override} cannot take effect: src.eval rebuilds the network from {ckpt_path}, which has "
                        f"model.{name}={theirs}; evaluate a checkpoint trained with it, or drop the override"
                    )


def refuse_unused_in_train(cfg: DictConfig) -> None:
    """ConfigError for ``weights=`` in ``src.train`` (it would be ignored), and for a checkpoint selection on
    validation that cannot select (module docstring)."""
    if cfg.get("weights"):
        raise ConfigError(f"weights={cfg.weights}: src.train does not load published weights (src.eval does): it "
                          "trains from scratch, from a checkpoint's weights (init_weights=PATH), or resumes with "
                          "ckpt_path=<run dir>/checkpoints/last.ckpt")
    if cfg.get("init_weights") and cfg.get("ckpt_path"):
        raise ConfigError(f"init_weights={cfg.init_weights} and ckpt_path={cfg.ckpt_path}: a resumed run keeps its own "
                          "weights; give one of the two")
    checkpoint = (cfg.get("callbacks") or {}).get("checkpoint")
    monitor = checkpoint.get("monitor") if checkpoint is not None else None
    if not monitor:
        return
    refuse_unknown_monitor(str(monitor), str(cfg.model._target_))
    if cfg.trainer.get("fast_dev_run"):  # (fast_dev_run validates one batch whatever the limits)
        return
    limit = cfg.trainer.get("limit_val_batches")
    if limit is not None and not isinstance(limit, bool) and limit == 0:
        raise ConfigError(f"trainer.limit_val_batches={limit} turns validation off, so callbacks.checkpoint (monitor "
                          f"{monitor}) never selects a checkpoint and the test would run on the last weights: "
                          "validate (trainer.limit_val_batches=N, or null: every batch), or keep the last checkpoint "
                          "with callbacks.checkpoint.monitor=null")
    if checkpoint.get("save_top_k") == 0:
        raise ConfigError(f"callbacks.checkpoint.save_top_k=0 keeps no checkpoint selected on {monitor}, so the test "
                          "would run on the last weights: keep one (save_top_k=1, or -1: all), or keep the last "
                          "checkpoint with callbacks.checkpoint.monitor=null")


#: Logged during training by every module (losses, the training clock): a checkpoint may be selected on them too.
_TRAINING_LOGS = ("train/", "train_loss", "time/")


def refuse_unknown_monitor(monitor: str, module_target: str) -> None:
    """ConfigError, before training, for a ``callbacks.checkpoint.monitor`` that the module (its class's
    ``VALIDATION_METRICS``) never logs: Lightning would find out only after the first validation."""
    try:
        known = getattr(hydra.utils.get_class(module_target), "VALIDATION_METRICS", None)
    except Exception:  # noqa: BLE001 - an unknown module: its instantiation names the problem
        return
    if known is None or monitor in known or monitor.startswith(_TRAINING_LOGS):
        return
    close = difflib.get_close_matches(monitor, known, n=3)
    hint = f"did you mean {', '.join(close)}? " if close else ""
    raise ConfigError(f"callbacks.checkpoint.monitor={monitor} is never logged, so no checkpoint could be selected on it: "
                      f"{hint}a validation logs {', '.join(known)} (or null: keep the last checkpoint)")


def refuse_resume_past_budget(cfg: DictConfig, checkpoint: Mapping[str, Any]) -> None:
    """ConfigError when the checkpoint to resume (``ckpt_path``) is already at or past ``trainer.max_steps``:
    the resumed run would train nothing, then test and write metrics as a new run."""
    step, max_steps = int(checkpoint.get("global_step", 0)), cfg.trainer.get("max_steps")
    if max_steps is None or max_steps == -1 or step < max_steps:
        return
    raise ConfigError(f"ckpt_path={cfg.ckpt_path} is at step {step}, and trainer.max_steps={max_steps}: the resumed "
                      "run would train nothing; raise trainer.max_steps to train on, or evaluate the checkpoint with "
                      "src.eval")


@dataclass(frozen=True)
class ReadOnlyWith:
    """A key that is read only when the setting ``by`` has one of ``values`` (``unless``: none of them)."""

    by: str
    values: tuple[Any, ...]
    unless: bool = False

    def reads(self, value: Any) -> bool:
        return (value in self.values) != self.unless

    def describe(self) -> str:
        shown = "|".join(map(str, self.values))
        return f"{self.by} other than {shown}" if self.unless else f"{self.by}={shown}"


_PRNET, _RPMNET = ReadOnlyWith("data.pair.partial", ("prnet",)), ReadOnlyWith("data.pair.partial", ("rpmnet",))
_EULER, _TWIST = ReadOnlyWith("data.pair.perturbation", ("euler",)), ReadOnlyWith("data.pair.perturbation", ("twist",))

#: Keys of the pair pipeline (src/data/transforms.py, src/data/perturbations.py) and when it reads them.
READ_ONLY_WITH: dict[str, ReadOnlyWith] = {
    "data.pair.prnet_num_keep": _PRNET,
    "data.pair.rpmnet_p_keep": _RPMNET,
    "data.pair.rpmnet_num_points": _RPMNET,
    "data.pair.rpmnet_resample_points": _RPMNET,
    "data.pair.rot_mag": _EULER,
    "data.pair.trans_mag": _EULER,
    "data.pair.twist_mag": _TWIST,
    "data.pair.twist_random_mag": _TWIST,
    "data.pair.unit_cube": _TWIST,
    "data.pair.noise_clip": ReadOnlyWith("data.pair.noise_sigma", (0,), unless=True),
    "sampling": ReadOnlyWith("data.dataset", ("scan_pairs",), unless=True),  # two real scans: no sampling
    "model.network.topk": ReadOnlyWith("model.network.mask_mode", ("topk",)),  # (OMNet: argmax masks take no k)
}


def refuse_unread_overrides(cfg: DictConfig, overrides: Sequence[str] | None = None) -> None:
    """ConfigError for the first command-line override of :data:`READ_ONLY_WITH` that the run's setting
    leaves unread (e.g. ``data.pair.rpmnet_p_keep=0.5`` with ``partial=prnet``); a setting the config does
    not have (another data module) decides nothing."""
    for override in command_overrides() if overrides is None else overrides:
        rule = READ_ONLY_WITH.get(_key(override))
        if rule is None or override.startswith("~"):
            continue
        setting = OmegaConf.select(cfg, rule.by, default=None)
        if setting is not None and not rule.reads(setting):
            raise ConfigError(f"{override} cannot take effect: it is read only with {rule.describe()}, and this run "
                              f"has {rule.by}={setting}; drop the override or change {rule.by}")


def _select(tree: Mapping[str, Any], dotted: str) -> Any:
    node: Any = tree
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, Mapping) else None
    return node

