"""What is recorded is what ran: a command-line override an entry point cannot honour is refused in one
line (the key and why), instead of being written into ``config_resolved.yaml`` and ignored.

* ``src.eval`` rebuilds the network from the checkpoint: a ``model.network.*`` or ``model_scale`` override
  that differs from the checkpoint's value cannot take effect (:func:`refuse_unused_in_eval`), and an
  evaluation study labelled by it would print the same numbers under each label. (The metric convention
  ``model.euler_seq`` does take effect: it follows the experiment. Training-only settings, e.g. an override
  list shared with ``src.train``, change no evaluated number and pass.)
* ``src.train`` trains from scratch or resumes from ``ckpt_path``: ``weights=`` is for ``src.eval``
  (:func:`refuse_unused_in_train`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError

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
                if _plain(OmegaConf.select(cfg.model, name, default=None)) != theirs:
                    raise ConfigError(
                        f"{override} cannot take effect: src.eval rebuilds the network from {ckpt_path}, which has "
                        f"model.{name}={theirs}; evaluate a checkpoint trained with it, or drop the override"
                    )


def refuse_unused_in_train(cfg: DictConfig) -> None:
    """ConfigError for ``weights=`` in ``src.train`` (it would be ignored)."""
    if cfg.get("weights"):
        raise ConfigError(f"weights={cfg.weights}: src.train does not load weights (src.eval does): it trains from "
                          "scratch, or resumes with ckpt_path=<run dir>/checkpoints/last.ckpt")


def _select(tree: Mapping[str, Any], dotted: str) -> Any:
    node: Any = tree
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, Mapping) else None
    return node


def _plain(value: Any) -> Any:
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
