"""Weights published by other projects, imported into this framework's networks.

:data:`PUBLISHED` (the records of ``published.yaml``) names every known file (``official:<name>``): where it lies (``../shared/weights/``,
:func:`src.utils.paths.shared_path`), its sha256, the network it fits (a ``conf/model`` config plus
overrides), the protocol it was trained under (``conf/exp/<protocol>.yaml``), what its authors report
and its license. ``weights=`` accepts such a name or the path of a file of a known layout: a file named as a registered one is
checked against its sha256; another one gets the layout's registry entry's network and is recorded as
unverified (``module.hparams["weights"]["verified"]``).

The file's state dict is mapped onto our network by its layout's converter
(:mod:`baselines.learned.weight_converters`, strict). A file of another layout, an unreadable file, a wrong
checksum or an unknown name raise one-line :class:`~src.utils.errors.CheckpointError` / ConfigError.

    >>> from baselines.learned.published import published_module
    >>> module = published_module("official:dcp_v1")             # a RegistrationModule, eval mode
    >>> get_registrator("dcp", weights="official:dcp_v1")        # the same through the adapter
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from baselines.learned.weight_converters import convert, detect_layout, read_state_dict
from baselines.methods import learned_methods
from src.run.checkpoint_io import check_finite_weights
from src.compose import compose_model_config
from src.data.cache import file_sha256
from src.utils.errors import CheckpointError, ConfigError
from src.utils.paths import shared_path
from src.utils.records import load_records

OFFICIAL = "official:"


@dataclass(frozen=True)
class Published:
    """One published weights file (see the module docstring); ``method`` is the key of the learned method
    (:data:`baselines.methods.METHODS`) whose network they fit (None: not a registration network), and
    ``reported`` holds the authors' numbers for ``protocol`` (metric name → value, as ``reported_source``
    states them)."""

    name: str
    file: str
    sha256: str
    layout: str
    source: str
    license: str
    trained_on: str
    method: str | None = None
    model: str | None = None
    model_overrides: tuple[str, ...] = ()
    protocol: str | None = None
    reported: Mapping[str, float] = field(default_factory=dict)
    reported_source: str = ""

    def __post_init__(self) -> None:
        if self.method is not None and self.method not in {m.key for m in learned_methods()}:
            raise ConfigError(f"published weights {self.name}: {self.method} is not the key of a learned method")


#: The records of ``published.yaml``, by name.
PUBLISHED: dict[str, Published] = {p.name: p for p in load_records(Path(__file__).with_name("published.yaml"), Published)}


# --- resolving names and files ------------------------------------------------------------------------


def weights_sha256(spec: str) -> str:
    """The sha256 that identifies ``weights`` (a grid cell's key): the registry's for ``official:<name>``
    (checked whenever the file is loaded), the file's own for a path."""
    spec = str(spec)
    if spec.startswith(OFFICIAL):
        return registry_entry(spec[len(OFFICIAL):]).sha256
    return file_sha256(Path(spec).expanduser())


@dataclass(frozen=True)
class Resolved:
    """A ``weights`` spec resolved: its registry entry (the layout's for a plain path), the file, the
    converted state dict and whether the file is a registered one (its sha256 checked)."""

    entry: Published
    path: Path
    state: dict[str, Tensor]
    verified: bool = True


def registry_entry(name: str) -> Published:
    if name not in PUBLISHED:
        known = ", ".join(OFFICIAL + n for n in PUBLISHED)
        raise ConfigError(f"unknown published weights '{OFFICIAL}{name}'; known: {known}")
    return PUBLISHED[name]


def _check_sha256(spec: str, path: Path, entry: Published) -> None:
    digest = file_sha256(path)
    if digest != entry.sha256:
        raise CheckpointError(
            f"{spec}: {path} has sha256 {digest[:12]}…, not the published file's {entry.sha256[:12]}…"
        )


def resolve(spec: str) -> Resolved:
    """``official:<name>`` (the shared file), or a path: one named as a registered file is checked
    against its sha256 as well; any other file of a known layout is loaded, marked unverified."""
    spec = str(spec)
    if spec.startswith(OFFICIAL):
        entry = registry_entry(spec[len(OFFICIAL):])
        path = shared_path("weights", entry.file)
        if not path.is_file():
            raise CheckpointError(
                f"{spec}: {path} does not exist (the shared folder is $OMNET_SHARED_DIR or ../shared beside the "
                f"repository; or pass the file's path instead of the name)"
            )
        registered: Published | None = entry
    else:
        path = Path(spec).expanduser()
        registered = next((p for p in PUBLISHED.values() if p.file == path.name), None)
    if registered is not None:
        _check_sha256(spec, path, registered)
    state = read_state_dict(path)
    check_finite_weights(state, path)
    layout = registered.layout if registered is not None else detect_layout(state, path)
    entry = registered or next(p for p in PUBLISHED.values() if p.layout == layout)
    return Resolved(entry, path, convert(state, layout), verified=registered is not None)


def network_config(entry: Published) -> dict[str, Any]:
    """The network config (``_target_`` + arguments) the entry's weights fit (full width)."""
    from omegaconf import OmegaConf

    if entry.model is None:
        raise CheckpointError(
            f"{OFFICIAL}{entry.name} holds PointNet features, not a registration network: use it as "
            f"model.network.feature_init of pointnetlk"
        )
    model = compose_model_config(entry.model, 1.0, entry.model_overrides)
    return OmegaConf.to_container(model.network, resolve=True)


def load_weights(network: nn.Module, state: Mapping[str, Tensor], spec: str) -> None:
    """``network.load_state_dict(state, strict=True)``, a mismatch as one CheckpointError line."""
    try:
        network.load_state_dict(state, strict=True)
    except RuntimeError as err:
        first = str(err).strip().splitlines()
        raise CheckpointError(f"{spec} does not fit {type(network).__name__}: {' '.join(first[:2])}") from None


def published_module(spec: str, model_cfg: Mapping[str, Any] | None = None, expected_target: str | None = None):
    """A :class:`~src.models.module.RegistrationModule` holding the published weights, in eval mode.

    ``model_cfg`` (a ``conf/model`` config: optimiser, metric convention) gets the entry's network; by
    default the entry's own ``conf/model/<model>.yaml``. ``expected_target``: the network class the
    caller needs (CheckpointError naming the right method otherwise).
    """
    import hydra
    from omegaconf import OmegaConf

    resolved = resolve(spec)
    network = network_config(resolved.entry)
    if expected_target is not None and network["_target_"] != expected_target:
        raise CheckpointError(
            f"{spec} holds a {network['_target_']} network, not {expected_target}: use it with method/model "
            f"'{resolved.entry.method}'"
        )
    if model_cfg is None:
        model_cfg = compose_model_config(resolved.entry.model, 1.0, resolved.entry.model_overrides)
    plain = OmegaConf.to_container(model_cfg, resolve=True) if not isinstance(model_cfg, dict) else dict(model_cfg)
    module = hydra.utils.instantiate({**plain, "network": network})
    load_weights(module.network, resolved.state, spec)
    module.hparams["weights"] = {"spec": spec, "file": str(resolved.path), "verified": resolved.verified}
    return module.eval()


def pointnet_features(spec: str, encoder: nn.Module) -> dict[str, Tensor]:
    """PointNetLK's ``feature_init``: the state dict of ``encoder`` (a PointNetEncoder) from published
    PointNet features (``official:learning3d_pointnet_classifier_features`` or such a file) or from a
    ``src.train`` checkpoint of ``model=pointnet_classifier`` (its ``network.encoder``)."""
    spec = str(spec)
    if spec.startswith(OFFICIAL) or not spec.endswith(".ckpt"):
        resolved = resolve(spec)
        state = resolved.state
        if resolved.entry.layout == "learning3d_pointnetlk":
            state = {k[len("encoder."):]: v for k, v in state.items() if k.startswith("encoder.")}
        elif resolved.entry.layout != "learning3d_pointnet":
            raise CheckpointError(f"feature_init {spec} holds no PointNetLK features ({resolved.entry.layout} layout)")
    else:
        path = Path(spec)
        if not path.is_file():
            raise CheckpointError(f"feature_init checkpoint {path} does not exist")
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=False)
            target = ckpt["hyper_parameters"]["network"]["_target_"]
            weights = ckpt["state_dict"]
        except Exception as err:  # noqa: BLE001 - any unreadable or foreign file is the same user error
            raise CheckpointError(f"feature_init {path} is not a src.train checkpoint ({type(err).__name__})") from None
        if target != "baselines.learned.pointnet_classifier.PointNetClassifier":
            raise CheckpointError(f"feature_init {path} holds a {target}, not a pointnet_classifier")
        state = {k[len("network.encoder."):]: v for k, v in weights.items() if k.startswith("network.encoder.")}
    missing = sorted(set(encoder.state_dict()) - set(state))
    if missing or any(state[k].shape != v.shape for k, v in encoder.state_dict().items()):
        raise CheckpointError(f"feature_init {spec} does not fit this PointNetLK's encoder (other widths or layers)")
    return state
