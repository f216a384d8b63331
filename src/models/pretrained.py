"""Shipped checkpoints: export a training run's best checkpoint, and find the one for an experiment.

    python -m src.models.pretrained export outputs/ship_periter --name omnet_unseen_categories_synthetic_ts \
        --evaluation stanford=outputs/ship_stanford/metrics.json

writes ``checkpoints/<name>.ckpt`` (weights and the network config only: no optimiser state, so it
loads with ``RegistrationModule.load_from_checkpoint``) and ``checkpoints/<name>.json`` (what it is,
how it was trained, its test metrics and any further evaluations). ``python -m src.eval`` without
``ckpt_path`` uses the shipped checkpoint whose experiment (task, dataset, sampling, partial manner)
and network match the config, once :func:`verify_card` has checked the card against the file: its sha256,
and the experiment the checkpoint itself records (``trained_on``, :mod:`src.run.trained_on`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch
import yaml

from src.data.cache import file_sha256
from src.metrics import ERROR_R, ERROR_T, VAL_ERROR_R, VAL_ERROR_T
from src.models.module import RegistrationModule
from src.run.reporting import read_csv_logs
from src.run.trained_on import IDENTITY_KEYS, trained_on_record
from src.run.trained_on import KEY as TRAINED_ON
from src.utils.errors import CheckpointError
from src.utils.paths import SHIPPED_DIR, without_folder

#: :func:`trained_precision` of a card that does not record its training precision.
UNRECORDED = "unrecorded"


def find_shipped(identity: dict[str, str], directory: Path = SHIPPED_DIR, network: str | None = None) -> Path:
    """The shipped checkpoint trained for ``identity`` (task, dataset, sampling, partial) and, when given, for
    the ``network`` (its ``_target_``): each learned method ships its own checkpoint for the same experiment."""
    cards = {path: json.loads(path.read_text()) for path in sorted(directory.glob("*.json"))}

    def describe(card_identity: dict[str, str], target: str | None) -> str:
        return " ".join(f"{k}={card_identity[k]}" for k in IDENTITY_KEYS) + (f" network={target}" if target else "")

    for path, card in cards.items():
        if all(card["experiment"][k] == identity[k] for k in IDENTITY_KEYS) and network in (None, card["network"]["_target_"]):
            return verify_card(path.with_suffix(".ckpt"), card)
    available = [describe(card["experiment"], card["network"]["_target_"] if network else None) for card in cards.values()]
    raise CheckpointError(
        f"no shipped checkpoint for {describe(identity, network)} (shipped: {'; '.join(available) or 'none'}): "
        "train one with `python -m src.train` and pass ckpt_path=PATH"
    )


def trained_precision(card: dict[str, Any]) -> str:
    """The precision the card's checkpoint was trained in (Lightning's name, ``training.precision``: every shipped
    card records it), :data:`UNRECORDED` for a card without it. Evaluation runs in float32 whatever it is."""
    return str(card.get("training", {}).get("precision") or UNRECORDED)


def verify_card(ckpt: Path, card: dict[str, Any]) -> Path:
    """``ckpt`` once its ``card`` is shown to describe it (CheckpointError otherwise): the file's sha256 is the
    card's, and the experiment the checkpoint records (``trained_on``) is the one the card claims."""
    if not ckpt.is_file():
        raise CheckpointError(f"{ckpt.with_suffix('.json')} describes {ckpt}, which does not exist")
    digest = file_sha256(ckpt)
    if digest != card.get("sha256"):
        raise CheckpointError(f"{ckpt} has sha256 {digest[:12]}…, not the {str(card.get('sha256'))[:12]}… of its card "
                              f"{ckpt.with_suffix('.json').name}: the file or the card was changed; restore both, or "
                              "export the checkpoint again (python -m src.models.pretrained export)")
    recorded = torch.load(ckpt, map_location="cpu", weights_only=False, mmap=True).get(TRAINED_ON) or {}
    claimed = {k: card["experiment"].get(k) for k in IDENTITY_KEYS}
    found = {k: recorded.get(k) for k in IDENTITY_KEYS}
    if claimed != found:
        raise CheckpointError(f"the card {ckpt.with_suffix('.json').name} claims {_identity(claimed)}, but {ckpt} was "
                              f"trained on {_identity(found) if recorded else 'an unrecorded experiment'}: the weights "
                              "decide; restore the card, or export the checkpoint again")
    return ckpt


def _identity(identity: dict[str, Any]) -> str:
    return " ".join(f"{k}={v}" for k, v in identity.items())


def _validation_curve(run_dir: Path) -> list[dict[str, float]]:
    """Validation Error(R)/Error(t) per validated step, from the CSV logger."""
    frame = read_csv_logs(run_dir)
    if VAL_ERROR_R not in frame:
        return []
    rows = frame.dropna(subset=[VAL_ERROR_R])
    return [{"step": int(r["step"]), ERROR_R: round(float(r[VAL_ERROR_R]), 3),
             ERROR_T: round(float(r[VAL_ERROR_T]), 4)} for _, r in rows.iterrows()]


def _overrides(run_dir: Path) -> list[str] | None:
    """The run's command-line overrides as Hydra recorded them."""
    path = run_dir / ".hydra" / "overrides.yaml"
    return yaml.safe_load(path.read_text()) if path.is_file() else None


def run_experiment(run_dir: Path, results: dict[str, Any]) -> str:
    """The ``+exp=<name>`` the run was composed with (its task_name may be a label), else the task."""
    for item in _overrides(run_dir) or []:
        if item.startswith(("+exp=", "exp=")):
            return item.split("=", 1)[1]
    return results["task"]


def stored_weights(state_dict: dict[str, Any], half: bool) -> dict[str, Any]:
    """The weights as written: floating-point tensors in float16 when ``half`` (loading casts them back to the
    module's float32), the others as they are."""
    return {k: v.half() if half and v.is_floating_point() else v for k, v in state_dict.items()}


def export(run_dir: Path, name: str, out_dir: Path = SHIPPED_DIR, evaluations: dict[str, Path] | None = None,
           note: str = "", half: bool = False) -> Path:
    """Write ``<out_dir>/<name>.ckpt`` and ``.json`` from a finished ``src.train`` run directory (``half``: the
    weights in float16, half the file; the card's ``weights_dtype`` says which)."""
    results = json.loads((run_dir / "metrics.json").read_text())
    config = yaml.safe_load((run_dir / "config_resolved.yaml").read_text())
    source = Path(results["checkpoint"])
    if not source.is_file():
        raise CheckpointError(f"the run's best checkpoint {source} does not exist")
    full = torch.load(source, map_location="cpu", weights_only=False)
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"{name}.ckpt"
    hyper_parameters = json.loads(_portable(json.dumps(full["hyper_parameters"]), run_dir))  # e.g. feature_init
    identity = {k: results[k] for k in IDENTITY_KEYS} | {"task": run_experiment(run_dir, results)}
    trained_on = trained_on_record(identity, config["data"]["splits"], config["data"].get("remove_axisymmetric", True))
    torch.save({"state_dict": stored_weights(full["state_dict"], half), "hyper_parameters": hyper_parameters,
                "pytorch-lightning_version": full["pytorch-lightning_version"], TRAINED_ON: trained_on}, target)
    network = hyper_parameters["network"]
    card: dict[str, Any] = {
        "name": name,
        "file": target.name,
        "sha256": file_sha256(target),
        "size_mb": round(target.stat().st_size / 2**20, 2),
        "weights_dtype": "float16" if half else "float32",
        "note": note,
        "experiment": identity | {"splits": config["data"]["splits"], "pair": config["data"]["pair"]},
        "network": network,
        "parameters": sum(p.numel() for p in RegistrationModule.load_from_checkpoint(target).parameters()),
        "training": {
            "step_of_checkpoint": int(full["global_step"]),
            "steps_run": results.get("global_step"),
            "fit_seconds_last_process": results.get("fit_seconds"),
            "resumed_from": results.get("resumed_from"),
            "batch_size": config["data"]["batch_size"],
            "optimizer": {k: hyper_parameters[k] for k in ("lr", "weight_decay", "scheduler")},
            "precision": config["trainer"]["precision"],  # as the run settled it (src/run/precision.py)
            "accelerator": config["trainer"]["accelerator"],
            "seed": config["seed"],
            "command": None if _overrides(run_dir) is None else " ".join(["python -m src.train", *_overrides(run_dir)]),
            "validation": _validation_curve(run_dir),
        },
        "metrics": {"test": results["metrics"]}
        | {key: json.loads(path.read_text())["metrics"] for key, path in (evaluations or {}).items()},
    }
    target.with_suffix(".json").write_text(_portable(json.dumps(card, indent=2), run_dir) + "\n")
    return target


def _portable(text: str, run_dir: Path) -> str:
    """``text`` with the run directory's absolute path (resumed_from, ckpt_path in the command) written as
    ``<run dir>``, and its parent's (a sibling stage's checkpoint, e.g. PointNetLK's classifier) as ``<run dir>/..``:
    a card names no path of the machine it was exported on."""
    text = without_folder(text, run_dir, "<run dir>")
    return without_folder(text, run_dir.parent, "<run dir>/..")  # what is left of it: a sibling's path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    exp = sub.add_parser("export", help="export a run's best checkpoint with its card")
    exp.add_argument("run_dir", type=Path)
    exp.add_argument("--name", required=True)
    exp.add_argument("--out-dir", type=Path, default=SHIPPED_DIR)
    exp.add_argument("--evaluation", action="append", default=[], metavar="KEY=METRICS_JSON",
                     help="metrics.json of a src.eval run of this checkpoint, stored under KEY")
    exp.add_argument("--note", default="")
    exp.add_argument("--half", action="store_true", help="store the weights in float16 (loaded as float32)")
    args = parser.parse_args(argv)
    evaluations = dict(item.split("=", 1) for item in args.evaluation)
    target = export(args.run_dir, args.name, args.out_dir, {k: Path(v) for k, v in evaluations.items()}, args.note,
                    args.half)
    print(f"wrote {target} and {target.with_suffix('.json').name}")


if __name__ == "__main__":
    main()
