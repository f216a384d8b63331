"""Reading and writing ``src.train`` checkpoints safely.

* :func:`read_checkpoint` / :func:`check_checkpoint` — the one check of a checkpoint given by the
  user (``src.train ckpt_path=`` to resume, ``src.eval ckpt_path=`` to evaluate, a learned method's
  ``checkpoint=``): it exists, is a readable PyTorch file, was written by ``src.train`` and holds
  the configured network (and, to resume, the training state). Each problem is one
  :class:`~src.utils.errors.CheckpointError` line.
* :class:`AtomicCheckpointIO` — Lightning's checkpoint writer, but staging each file beside its
  target (:mod:`src.utils.files`): Lightning's own writer stages it in the system temporary folder,
  where every kill during a save left a partial file behind.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from omegaconf import DictConfig

from src.utils.errors import CheckpointError
from src.utils.files import write_atomic


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint written by ``src.train`` (memory-mapped where the format allows); CheckpointError
    if the file is missing, unreadable (truncated, another kind of file) or holds no network config."""
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"checkpoint {path} is a folder: pass a .ckpt file in it (e.g. {path / 'last.ckpt'})")
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        try:
            checkpoint = torch.load(path, map_location="cpu", weights_only=False, mmap=True)
        except RuntimeError:  # old (non-zip) serialisation cannot be memory-mapped
            checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # noqa: BLE001 - any unreadable file is the same user error
        raise CheckpointError(
            f"{path} is not a readable PyTorch checkpoint ({type(err).__name__}: truncated or another kind of file); "
            "pass a .ckpt written by src.train"
        ) from err
    hparams = checkpoint.get("hyper_parameters") if isinstance(checkpoint, dict) else None
    if not isinstance(hparams, dict) or not (hparams.get("network") or {}).get("_target_"):
        raise CheckpointError(f"{path} was not written by src.train (no network config inside)")
    check_finite_weights(checkpoint.get("state_dict") or {}, path)
    return checkpoint


def check_finite_weights(state_dict: dict[str, Any], path: str | Path) -> None:
    """CheckpointError naming the first weight tensor with NaN or infinite values (a corrupted file, or a
    diverged run's): it would fail much later, e.g. in an SVD, or give NaN results."""
    for key, value in state_dict.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            bad = int((~torch.isfinite(value)).sum())
            raise CheckpointError(f"{path}: {bad} of the {value.numel()} values of weight {key} are NaN or infinite: "
                                  "the file is corrupted (or from a diverged run); use an intact copy")


def read_checkpoint_network(path: str | Path) -> str:
    """The ``_target_`` of the network stored in a ``src.train`` checkpoint (CheckpointError as
    :func:`read_checkpoint`)."""
    return str(read_checkpoint(path)["hyper_parameters"]["network"]["_target_"])


def check_checkpoint(path: str | Path, expected_target: str, resume: bool = False,
                     model: DictConfig | None = None) -> dict[str, Any]:
    """The checkpoint's hyper-parameters, after :func:`read_checkpoint` and checking it holds an
    ``expected_target`` network (and, with ``resume``, the optimiser and loop states resuming needs,
    and, given the ``model`` config, its architecture: :func:`check_architecture`)."""
    checkpoint = read_checkpoint(path)
    hparams = checkpoint["hyper_parameters"]
    found = hparams["network"]["_target_"]
    if found != expected_target:
        raise CheckpointError(
            f"{path} holds a {found} network but the config asks for {expected_target}: pass model=<its model>"
        )
    if resume and "optimizer_states" not in checkpoint:
        raise CheckpointError(
            f"{path} holds weights only, no training state to resume: resume from a run's checkpoints/last.ckpt, "
            "or evaluate it with src.eval"
        )
    if model is not None:
        check_architecture(path, checkpoint, model)
    return hparams


def _shapes(state_dict: dict[str, Any]) -> dict[str, tuple[int, ...]]:
    return {key.replace("._orig_mod.", "."): tuple(value.shape) for key, value in state_dict.items()}


def check_architecture(path: str | Path, checkpoint: dict[str, Any], model: DictConfig) -> None:
    """CheckpointError when the ``model`` config builds parameters of other names or shapes than the
    checkpoint holds (another width, shared weights, number of iterations): one line comparing the
    checkpoint's network hyper-parameters with the config's. The config's module is built on the
    ``meta`` device (no memory, no weights); a config that cannot be built there is left to training."""
    try:
        with torch.device("meta"):
            module = hydra.utils.instantiate(model)
    except Exception:  # noqa: BLE001 - the real build names the problem
        return
    expected, found = _shapes(module.state_dict()), _shapes(checkpoint["state_dict"])
    if expected == found:
        return
    theirs, ours = checkpoint["hyper_parameters"]["network"], dict(module.hparams["network"])
    differing = [k for k in sorted(set(theirs) | set(ours)) if k != "_target_" and theirs.get(k) != ours.get(k)]
    if differing:
        compared = (f"checkpoint {', '.join(f'{k}={theirs.get(k)}' for k in differing)}; "
                    f"config {', '.join(f'{k}={ours.get(k)}' for k in differing)}")
    else:
        key = next(k for k in sorted(set(expected) | set(found)) if expected.get(k) != found.get(k))
        compared = f"{key}: checkpoint {found.get(key)}, config {expected.get(key)}"
    raise CheckpointError(
        f"{path} holds another architecture than the config (model.network: {compared}): train with the "
        "checkpoint's settings, or start a new run without it"
    )


class AtomicCheckpointIO(TorchCheckpointIO):
    """``torch.save`` to ``.<name>.<pid>.tmp`` beside the target, flushed, then renamed over it."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, lambda tmp: torch.save(checkpoint, tmp))
