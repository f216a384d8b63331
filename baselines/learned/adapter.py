"""Learned networks behind the :class:`~baselines.base.Registrator` interface.

:class:`LearnedRegistrator` wraps a checkpoint written by ``src.train``
(:meth:`RegistrationModule.load_from_checkpoint <src.models.module.RegistrationModule>`) and runs
whole batches through the network with torch, on the GPU when one is available (``device=auto``).
One subclass per learned method of :data:`baselines.methods.METHODS` is generated here (named after
its network's class, e.g. ``OMNetRegistrator``) and registered under the method's key; the checkpoint
must hold the method's network (``Method.network``, also ``model.network._target_`` of
``conf/model/<key>.yaml``). ``python -m baselines`` lists them.

>>> from baselines import get_registrator
>>> omnet = get_registrator("omnet", checkpoint="outputs/.../checkpoints/best-1000.ckpt")
>>> T = omnet.register_batch(src, ref)          # (B, 4, 4) in one forward pass
>>> results = run_batches(omnet, pairs)         # like baselines.run_pairs, batched: RegistrationResults

Each method takes ``checkpoint=PATH`` or ``weights=official:<name>`` (published weights imported
by :mod:`baselines.learned.published`, e.g. ``get_registrator("dcp", weights="official:dcp_v1")``, or
the path of such a file); a missing file, an unreadable one, or weights of another network than the
method name says raise :class:`~src.utils.errors.CheckpointError` (one line) when the registrator is
built, so a grid fails before it starts. The weights themselves are loaded lazily
(:meth:`LearnedRegistrator.setup`), so the object stays cheap to build and to pickle.

Without either, a method uses its shipped checkpoint (``checkpoints/*.ckpt``, :func:`shipped_checkpoint`; its
label names it) or, when none is shipped for it, says so. ``fresh_weights=true`` (instead of a checkpoint) builds the network from ``conf/model/<name>.yaml``
with freshly initialised weights — for timing only (:mod:`benchmarks.speed` labels it so); the
estimates of such a network are meaningless.

A network registers each pair in the frame it was trained in (:class:`~baselines.conditioning.TrainingFrame`,
from the card beside its checkpoint, ``<checkpoint>.json``; the data pipeline's frame without one): a pair in
other units or far from the origin is registered in the unit sphere and its estimate mapped back (the same
rotation, the translation in the caller's units); a pair inside (every pair of the protocols) as given. Repeated
points count once; a pair with fewer points than the network takes (``min_points``) or planar where its
features cannot resolve a plane (``planar_blind``) is refused with one line.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from baselines.base import Registrator, RegistratorConfig, refuse_planar, require_points
from baselines.conditioning import Similarity, TrainingFrame
from baselines.methods import Method, get_method, learned_methods, method_of_network
from baselines.result import FIT_THRESHOLD, RegistrationResult
from src.compose import compose_model_config
from src.geometry.clouds import MIN_POINTS, check_cloud
from src.models.pretrained import verify_card
from src.utils.errors import CheckpointError, ConfigError
from src.utils.paths import SHIPPED_DIR

__all__ = ["LEARNED_METHODS", "LearnedConfig", "LearnedRegistrator", "run_batches"]

#: method key -> ``_target_`` of its network, derived from :data:`baselines.methods.METHODS` (for benchmarks.speed).
LEARNED_METHODS: dict[str, str] = {method.key: method.network for method in learned_methods()}
DEVICES = ("auto", "cpu", "cuda")
log = logging.getLogger(__name__)


@dataclass
class LearnedConfig(RegistratorConfig):
    """Settings of a learned method.

    Attributes:
        checkpoint: a ``.ckpt`` written by ``src.train`` for this method's network (required
            unless ``weights`` or ``fresh_weights``).
        weights: published weights instead of a checkpoint: ``official:<name>`` or the path of a
            file of a known layout (:mod:`baselines.learned.published`).
        device: ``auto`` (CUDA if available, else CPU), ``cpu`` or ``cuda``.
        batch_size: pairs per forward pass in :func:`run_batches`.
        fresh_weights: build the network from ``conf/model/<name>.yaml`` with random weights
            (timing only; no checkpoint).
        model_scale: channel-width multiplier for ``fresh_weights`` (1.0 = the paper's network).
        model_overrides: extra Hydra overrides for ``fresh_weights`` (e.g. ``model.network.num_iters=2``).
        seed: seeds the random draws of a network that samples at test (PRNet's Gumbel noise) afresh for each
            forward pass, so a batch's estimates do not depend on what ran before it; the global RNG is left as it was.
    """

    checkpoint: str | None = None
    weights: str | None = None
    device: str = "auto"
    batch_size: int = 64
    fresh_weights: bool = False
    model_scale: float = 1.0
    model_overrides: Sequence[str] = field(default_factory=tuple)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.device not in DEVICES:
            raise ConfigError(f"device must be one of {', '.join(DEVICES)}, got {self.device!r}")
        if int(self.batch_size) < 1:
            raise ConfigError(f"batch_size must be >= 1, got {self.batch_size!r}")
        if not self.model_scale > 0:
            raise ConfigError(f"model_scale must be > 0, got {self.model_scale!r}")
        if self.checkpoint is not None:
            self.checkpoint = str(self.checkpoint)
        if self.weights is not None:
            self.weights = str(self.weights)
        self.model_overrides = tuple(str(o) for o in (self.model_overrides or ()))


def shipped_checkpoint(method: str, target: str, directory: Path | None = None) -> Path:
    """The shipped checkpoint (``checkpoints/<name>.ckpt`` with its ``.json`` card) of a network: one trained
    on real data if any, a model of clean pairs before one fine-tuned on noisy pairs (``gaussian_noise``), else
    the first by name; CheckpointError (naming the fix) when none is shipped."""
    directory = SHIPPED_DIR if directory is None else directory
    cards = {path.with_suffix(".ckpt"): json.loads(path.read_text()) for path in sorted(directory.glob("*.json"))}
    mine = [path for path, card in cards.items() if card["network"]["_target_"] == target and path.is_file()]
    if not mine:
        raise CheckpointError(
            f"method '{method}' needs a checkpoint and none is shipped for it in {directory}: pass checkpoint=PATH "
            f"(a .ckpt written by `python -m src.train model={method}`) or weights=official:<name>"
        )
    chosen = min(mine, key=lambda path: (cards[path]["experiment"]["dataset"] == "synthetic",
                                         cards[path]["experiment"].get("task") == "gaussian_noise", path.name))
    return verify_card(chosen, cards[chosen])


def card_frame(checkpoint: str | None) -> TrainingFrame:
    """The training frame a checkpoint's card records (``<checkpoint>.json``, its ``experiment.pair``: what
    :mod:`src.models.pretrained` exports beside a checkpoint); the data pipeline's (:class:`TrainingFrame`'s
    defaults) for published or fresh weights and a checkpoint without a card."""
    card = Path(checkpoint).with_suffix(".json") if checkpoint else None
    if card is None or not card.is_file():
        return TrainingFrame()
    try:
        pair = json.loads(card.read_text()).get("experiment", {}).get("pair")
    except (ValueError, AttributeError) as exc:
        raise CheckpointError(f"{card} lies beside {checkpoint} but is no checkpoint card ({exc}): move it away, or "
                              "export the checkpoint again (python -m src.models.pretrained export)") from None
    return TrainingFrame.of_pair(pair) if isinstance(pair, dict) else TrainingFrame()


def trained_on(card: dict[str, Any]) -> str:
    """What a shipped checkpoint's card says it was trained on, e.g. ``real_airplane: airplane shapes of
    modelnet40_resampled, TS, PRNet manner, rotations up to 45°, noise σ 0``."""
    experiment, pair = card["experiment"], card["experiment"].get("pair", {})
    categories = experiment.get("splits", {}).get("train", {}).get("categories", "?")
    shapes = ", ".join(categories) if isinstance(categories, list) else categories
    manner = {"prnet": "PRNet", "rpmnet": "RPMNet"}.get(experiment["partial"], experiment["partial"])
    return (f"{experiment['task']}: {shapes} shapes of {experiment['dataset']}, {experiment['sampling'].upper()}, "
            f"{manner} manner, rotations up to {pair.get('rot_mag', '?'):g}°, noise σ {pair.get('noise_sigma', 0):g}")


#: Shipped checkpoints already announced in this process.
_ANNOUNCED: set[Path] = set()


def say_trained_on(method: str, checkpoint: Path) -> None:
    """Once per process and checkpoint, a warning line: the shipped checkpoint ``method`` uses whatever the
    clouds, and what it was trained on (its card)."""
    if checkpoint in _ANNOUNCED:
        return
    _ANNOUNCED.add(checkpoint)
    card = json.loads(checkpoint.with_suffix(".json").read_text())
    log.warning("%s: no checkpoint given, using the shipped %s, trained on %s; for other data train one and pass "
                "checkpoint=PATH", method, checkpoint.name, trained_on(card))


def _used_as(target: str) -> str:
    """``; use it as method '<key>'`` for a registered network ``target`` (else nothing)."""
    method = method_of_network(target)
    return f"; use it as method '{method.key}'" if method else ""


class LearnedRegistrator(Registrator):
    """A trained network (a ``src.train`` checkpoint) as a Registrator; see the module docstring.

    Subclasses set ``name`` and ``network_target``; build them with
    ``get_registrator("<name>", checkpoint=PATH)``.
    """

    name: ClassVar[str] = "learned"
    needs_training: ClassVar[bool] = True
    needs_normals: ClassVar[bool] = False
    point_budget: ClassVar[int | None] = None
    config_cls: ClassVar[type[RegistratorConfig]] = LearnedConfig
    network_target: ClassVar[str] = ""

    def __init__(self, config: LearnedConfig | None = None, **overrides: Any) -> None:
        super().__init__(config, **overrides)
        cfg: LearnedConfig = self.config
        self._module = None
        self._device = None
        self.shipped: str | None = None  # the name of the shipped checkpoint used when none was given
        self.training_frame = TrainingFrame()  # the frame the network was trained in (its card's, below)
        sources = [name for name in ("checkpoint", "weights", "fresh_weights") if getattr(cfg, name)]
        if len(sources) > 1:
            raise ConfigError(f"{self.name}: give one of checkpoint=PATH, weights=official:<name> or fresh_weights=true")
        if cfg.fresh_weights:
            return
        if cfg.weights:
            self._check_weights(cfg.weights)
            return
        if not cfg.checkpoint:
            shipped = shipped_checkpoint(self.name, self.network_target)
            cfg.checkpoint, self.shipped = str(shipped), shipped.stem
            say_trained_on(self.name, shipped)
        from src.run.checkpoint_io import (
            read_checkpoint_network,  # here: keeps `import baselines` light
        )

        found = read_checkpoint_network(cfg.checkpoint)
        if found != self.network_target:
            raise CheckpointError(
                f"checkpoint {cfg.checkpoint} holds a {found} network, not {self.network_target} "
                f"(method '{self.name}'){_used_as(found)}"
            )
        self.training_frame = card_frame(cfg.checkpoint)

    # -- labels ------------------------------------------------------------------------

    def _check_weights(self, spec: str) -> None:
        """Published weights must exist, be intact and fit this method's network (CheckpointError)."""
        from baselines.learned.published import (  # torch: kept out of `import baselines`
            network_config,
            resolve,
        )

        target = network_config(resolve(spec).entry)["_target_"]
        if target != self.network_target:
            raise CheckpointError(
                f"{spec} holds a {target} network, not {self.network_target} (method '{self.name}'){_used_as(target)}"
            )

    @property
    def label(self) -> str:
        """Display name; ``(untrained)`` marks freshly initialised weights, ``(official:<name>)`` published ones."""
        base = get_method(self.name).display
        if self.shipped:
            return f"{base} (shipped: {self.shipped})"
        if self.config.fresh_weights:
            return f"{base} (untrained)"
        return f"{base} ({self.config.weights})" if self.config.weights else base

    # -- device and weights ------------------------------------------------------------

    @property
    def device(self):
        import torch

        if self._device is None:
            wanted = self.config.device
            if wanted == "auto":
                wanted = "cuda" if torch.cuda.is_available() else "cpu"
            elif wanted == "cuda" and not torch.cuda.is_available():
                raise ConfigError(f"{self.name}: device=cuda but CUDA is not available here")
            self._device = torch.device(wanted)
        return self._device

    def _build_fresh(self):
        import hydra

        cfg: LearnedConfig = self.config
        module = hydra.utils.instantiate(compose_model_config(self.name, cfg.model_scale, cfg.model_overrides))
        if module.network_target != self.network_target:  # pragma: no cover - conf/model out of sync
            raise ConfigError(f"conf/model/{self.name}.yaml builds {module.network_target}, expected {self.network_target}")
        return module

    def setup(self) -> None:
        """Load the checkpoint (or the published weights, or build fresh ones) onto the device, in eval
        mode. Idempotent."""
        if self._module is not None:
            return
        if self.config.fresh_weights:
            module = self._build_fresh()
        elif self.config.weights:
            from baselines.learned.published import (
                published_module,  # torch: kept out of `import baselines`
            )

            module = published_module(self.config.weights, expected_target=self.network_target)
        else:
            from src.models.module import RegistrationModule

            module = RegistrationModule.load_from_checkpoint(self.config.checkpoint, map_location="cpu")
        self._module = module.to(self.device).eval()

    @property
    def module(self):
        self.setup()
        return self._module

    @property
    def samples_at_test(self) -> bool:
        """Whether the network's estimates are random draws (then ``seed`` defines them; see LearnedConfig)."""
        return bool(getattr(self.module.network, "samples_at_test", False))

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_module"] = None  # reloaded lazily in the receiving process
        state["_device"] = None
        return state

    # -- registration ------------------------------------------------------------------

    def frame(self, src: np.ndarray, ref: np.ndarray) -> Similarity | None:
        """The similarity into the network's training frame (:attr:`training_frame`), None for a pair inside it."""
        return self.training_frame(src, ref)

    def _refuse_undetermined(self, src: np.ndarray, ref: np.ndarray) -> None:
        """Fewer points than the network takes (its ``min_points``), or a planar cloud where its features cannot
        resolve one (its ``planar_blind``)."""
        network = self.module.network
        require_points(self.name, src, ref, getattr(network, "min_points", MIN_POINTS), "for this network")
        refuse_planar(self.name, getattr(network, "planar_blind", ""), src=src, ref=ref)

    def _forward(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        import torch

        module = self.module
        with torch.random.fork_rng(devices=[self.device] if self.device.type == "cuda" else []), torch.inference_mode():
            torch.manual_seed(self.config.seed)
            points_src = torch.as_tensor(src, dtype=torch.float32, device=self.device)
            points_ref = torch.as_tensor(ref, dtype=torch.float32, device=self.device)
            transforms = module(points_src, points_ref)
            return transforms.detach().double().cpu().numpy()

    def synchronize(self) -> None:
        """Wait for queued GPU work (for timing)."""
        import torch

        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        return self._forward(src[None], ref[None])[0]

    def _register_batch(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Each pair conditioned as :meth:`register` does and checked, then all through the network in one forward
        pass (pair by pair where repeated points left them of different sizes), each estimate mapped back."""
        pairs = [self._conditioned(s, r) for s, r in zip(src, ref)]
        if len({(len(s), len(r)) for s, r, _ in pairs}) == 1:
            estimates = self._forward(np.stack([s for s, _, _ in pairs]), np.stack([r for _, r, _ in pairs]))
        else:
            estimates = np.stack([self._register(s, r) for s, r, _ in pairs])
        return np.stack([undo(estimate) for (_, _, undo), estimate in zip(pairs, estimates)])


def _group_by_shape(pairs: Sequence[tuple[np.ndarray, np.ndarray]], batch_size: int) -> list[list[int]]:
    """Batches of pair indices whose clouds have equal sizes (so they stack), in input order."""
    groups: dict[tuple[int, int], list[int]] = {}
    for index, (src, ref) in enumerate(pairs):
        groups.setdefault((len(src), len(ref)), []).append(index)
    batches = []
    for indices in groups.values():
        batches += [indices[i : i + batch_size] for i in range(0, len(indices), batch_size)]
    return sorted(batches, key=lambda b: b[0])


def _run_batch(registrator: LearnedRegistrator, pairs: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[RegistrationResult]:
    """One batch of checked pairs of equal sizes; pair by pair if the batch raises (to isolate the culprit)."""
    start = time.perf_counter()
    try:
        estimates = registrator._register_batch(np.stack([s for s, _ in pairs]), np.stack([r for _, r in pairs]))
        registrator.synchronize()
    except Exception:  # noqa: BLE001 - retried pair by pair, each failure recorded
        return [registrator.register_result(src, ref) for src, ref in pairs]
    per_pair = (time.perf_counter() - start) / len(pairs)
    return [RegistrationResult.of_estimate(estimate, per_pair).with_fit(src, ref, FIT_THRESHOLD)
            for estimate, (src, ref) in zip(estimates, pairs)]


def run_batches(
    registrator: LearnedRegistrator,
    pairs: Sequence[tuple[Any, Any]],
    batch_size: int | None = None,
    progress: bool = True,
) -> list[RegistrationResult]:
    """Register every pair with a learned method in batches; one
    :class:`~baselines.result.RegistrationResult` per pair, in order.

    The counterpart of :func:`baselines.runner.run_pairs` for networks: pairs of equal sizes are
    stacked into batches of ``batch_size`` (default: the method's ``batch_size``) and run at once;
    a pair's ``seconds`` is its batch's time divided by the batch size. A batch that raises is
    retried pair by pair (:meth:`~baselines.base.Registrator.register_result`), and a pair that still
    raises, or whose estimate is not a finite proper rigid transform, gets the identity with
    ``failed=True`` and a one-line reason. Inputs are checked first
    (:func:`~src.geometry.clouds.check_cloud`: PointCloudError for < 3 points, NaN or a degenerate cloud).
    """
    from tqdm.auto import tqdm

    pairs = [(check_cloud(s, f"pair {i} src"), check_cloud(r, f"pair {i} ref")) for i, (s, r) in enumerate(pairs)]
    batch_size = int(batch_size or registrator.config.batch_size)
    results: list[RegistrationResult | None] = [None] * len(pairs)
    if not pairs:
        return []
    registrator.setup()
    with tqdm(total=len(pairs), disable=not progress, desc=registrator.name, unit="pair", dynamic_ncols=True) as bar:
        for batch in _group_by_shape(pairs, batch_size):
            for i, result in zip(batch, _run_batch(registrator, [pairs[i] for i in batch])):
                results[i] = result
            bar.update(len(batch))
    return results  # type: ignore[return-value]


def _adapter_class(method: Method) -> type[LearnedRegistrator]:
    """The Registrator class of a learned method, named as ``method.registrator`` says."""
    class_name = method.registrator.rpartition(":")[2]
    return type(class_name, (LearnedRegistrator,), {
        "name": method.key,
        "network_target": method.network,
        "__module__": __name__,
        "__qualname__": class_name,
        "__doc__": f"{method.display} ({method.network}) from a src.train checkpoint or published weights; "
                   "see LearnedRegistrator.",
    })


for _method in learned_methods():
    _cls = _adapter_class(_method)
    globals()[_cls.__name__] = _cls
    __all__.append(_cls.__name__)
del _method, _cls
