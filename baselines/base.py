"""One interface for every registration method in the comparison grid.

A :class:`Registrator` estimates the rigid transform ``T`` (4x4, float64) with
``ref ≈ R @ src + t`` for a source cloud ``src`` (N, 3) and a reference cloud ``ref`` (M, 3):
:meth:`Registrator.register` returns ``T``, :meth:`Registrator.register_result` a
:class:`~baselines.result.RegistrationResult` (``T``, time, failure and its reason, inlier fit).
Classical methods (ICP, FGR, Symmetric ICP, Go-ICP) implement :meth:`Registrator._register`;
learned networks get adapters that wrap a checkpoint behind the same interface, set
``needs_training = True`` and usually override :meth:`Registrator._register_batch` to run a
whole batch on the GPU at once.

Every method checks its input with :func:`~src.geometry.clouds.check_cloud` and
:func:`~src.geometry.clouds.check_batch` (which the datasets use too), so each rejects empty, NaN, wrongly
shaped or degenerate clouds (all points on one line, fewer than 3 distinct points) with the same one-line
:class:`~src.errors.PointCloudError`.

Conditioning lives here too, for every method registering through :meth:`Registrator.register`
(or the default :meth:`Registrator._register_batch`), so that no single call gives a wrong result
or runs unbounded on input far from what the methods are tuned for:

* **Working frame.** The classical methods' options are absolute distances and radii tuned for
  unit-sphere objects (the paper's protocols: clouds of radius 0.17–1.41 about their centroids,
  within 2.3 of the origin, measured on the synthetic and real-airplane test sets). A pair whose
  radius (farthest point from its cloud's centroid, the larger of the two) lies outside
  :data:`WORKING_RADIUS`, or with a point farther than :data:`WORKING_REACH` from the origin, is
  registered in the working frame instead — centred on the mean of its two centroids and scaled
  by the power of two that brings its radius into [0.71, 1.41) — and the estimate mapped back.
  Pairs inside the frame (every pair of the protocols) are registered exactly as given.
  ``normalise_frame = False`` turns this off for a method.
* **Point budget.** A method registers at most ``point_budget`` points per cloud
  (:data:`POINT_BUDGET` by default): larger clouds are voxel down-sampled, both with one voxel size,
  the smallest (in steps of 2^(1/4)) that brings each to the budget; the estimate is a rigid
  transform of the whole clouds, so it applies to the full clouds unchanged (the runner's per-pair
  timeout stays the last guard). ``point_budget = None`` turns it off.

Methods are looked up by name with :func:`get_registrator`: every record of
:data:`baselines.methods.METHODS` is registered lazily (``"module:Class"``, so that ``import baselines``
does not import Open3D, torch or an optional extension); :func:`register_registrator` adds others.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from baselines.methods import METHODS, find_method
from baselines.result import FIT_THRESHOLD, RegistrationResult, check_threshold, one_line
from src.errors import ConfigError, PointCloudError
from src.geometry.clouds import MIN_POINTS, check_batch, check_cloud

__all__ = [
    "MIN_POINTS",
    "POINT_BUDGET",
    "WORKING_RADIUS",
    "WORKING_REACH",
    "Registrator",
    "RegistratorConfig",
    "available_registrators",
    "check_batch",
    "check_cloud",
    "get_registrator",
    "register_registrator",
    "resolve_registrator",
]

#: Pair radii (farthest point from its cloud's centroid, larger cloud) the methods are tuned for.
WORKING_RADIUS = (0.125, 2.0)
#: Farthest distance from the origin of a point of a pair inside the working frame.
WORKING_REACH = 4.0
#: Most points per cloud a method registers by default: at 10k points one core of the 2-core test
#: machine took ~1 s for FGR, ~0.4 s ICP, ~0.3 s Symmetric ICP, ~2 s Go-ICP (FGR at 20k: ~10 s).
POINT_BUDGET = 10_000


# --------------------------------------------------------------------------------------
# Conditioning: the working frame and the point budget (see the module docstring)
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Similarity:
    """``x -> (x - centre) / scale``, taking a pair into the working frame."""

    centre: np.ndarray
    scale: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) / self.scale

    def map_back(self, transform: np.ndarray) -> np.ndarray:
        """``transform`` (estimated in the working frame) in the input's coordinates."""
        out = transform.copy()
        out[:3, 3] = self.centre - transform[:3, :3] @ self.centre + self.scale * transform[:3, 3]
        return out


def _farthest(points: np.ndarray, centre: np.ndarray | float = 0.0) -> float:
    """Distance from ``centre`` of the farthest of ``points``."""
    offsets = points - centre
    return math.sqrt(float(np.einsum("ij,ij->i", offsets, offsets).max()))


def pair_radius(src: np.ndarray, ref: np.ndarray) -> float:
    """Distance from its cloud's centroid of the farthest point, the larger of the two clouds."""
    return max(_farthest(c, c.mean(axis=0)) for c in (src, ref))


def working_frame(src: np.ndarray, ref: np.ndarray) -> Similarity | None:
    """The similarity taking a checked pair into the working frame, or None if it lies inside."""
    radius = pair_radius(src, ref)
    reach = max(_farthest(src), _farthest(ref))
    if WORKING_RADIUS[0] <= radius <= WORKING_RADIUS[1] and reach <= WORKING_REACH:
        return None
    return Similarity(0.5 * (src.mean(axis=0) + ref.mean(axis=0)), float(2.0 ** round(math.log2(radius))))


def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """Each point's voxel (cube of side ``voxel``) as one integer."""
    keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    return np.ravel_multi_index(tuple(keys.T), tuple(keys.max(axis=0) + 1))


def voxel_down_sample(points: np.ndarray, voxel: float) -> np.ndarray:
    """The centroid of the points of each occupied voxel (Open3D's ``voxel_down_sample`` rule)."""
    _, inverse, counts = np.unique(_voxel_keys(points, voxel), return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, weights=points[:, k], minlength=len(counts)) for k in range(3)], axis=1)
    return sums / counts[:, None]


#: Ratio of neighbouring voxel sizes tried by :func:`budget_voxel_size` (~1.4x in a surface's voxel count).
_VOXEL_STEP = 2.0**0.25


def _fits(clouds: Sequence[np.ndarray], voxel: float, budget: int) -> bool:
    return max(len(np.unique(_voxel_keys(c, voxel))) for c in clouds) <= budget


def budget_voxel_size(clouds: Sequence[np.ndarray], budget: int) -> float:
    """The smallest voxel size at which each cloud occupies at most ``budget`` voxels, on a ladder
    of ratio ``_VOXEL_STEP`` from the guess for a surface (``extent / sqrt(budget)``), not below
    ``extent / budget``. The ladder is walked on a fixed random subset of ``4 x budget`` points
    per cloud (fast at any size), then the full clouds confirm the size (or enlarge it)."""
    extent = max(float(np.ptp(c, axis=0).max()) for c in clouds)
    rng = np.random.default_rng(0)
    subsets = [c[rng.choice(len(c), 4 * budget, replace=False)] if len(c) > 4 * budget else c for c in clouds]
    voxel = extent / math.sqrt(budget)
    while not _fits(subsets, voxel, budget):  # ends: one voxel holds a cloud once voxel > extent
        voxel *= _VOXEL_STEP
    while voxel / _VOXEL_STEP >= extent / budget and _fits(subsets, voxel / _VOXEL_STEP, budget):
        voxel /= _VOXEL_STEP
    while not _fits(clouds, voxel, budget):
        voxel *= _VOXEL_STEP
    return voxel


def within_budget(src: np.ndarray, ref: np.ndarray, budget: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The pair as given, or voxel down-sampled with one voxel size if a cloud has more than ``budget`` points."""
    if budget is None or max(len(src), len(ref)) <= budget:
        return src, ref
    voxel = budget_voxel_size((src, ref), budget)
    return voxel_down_sample(src, voxel), voxel_down_sample(ref, voxel)


# --------------------------------------------------------------------------------------
# The interface
# --------------------------------------------------------------------------------------


@dataclass
class RegistratorConfig:
    """Base class of every method's settings. Subclasses add fields with documented defaults
    and may validate them in ``__post_init__`` (raising :class:`ConfigError`)."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _positive(cfg: RegistratorConfig, *names: str, allow_zero: bool = False) -> None:
    """Raise ConfigError unless each named field of ``cfg`` is > 0 (or >= 0)."""
    for name in names:
        value = getattr(cfg, name)
        ok = value >= 0 if allow_zero else value > 0
        if not ok:
            bound = ">= 0" if allow_zero else "> 0"
            raise ConfigError(f"{type(cfg).__qualname__}.{name} must be {bound}, got {value!r}")


class Registrator(ABC):
    """A rigid registration method: ``register(src, ref) -> T`` with ``ref ≈ R src + t``.

    Subclasses set the class attributes and implement :meth:`_register` (one pair, inputs
    already checked, float64). Instances must be picklable: :func:`baselines.runner.run_pairs`
    sends them to worker processes, so keep heavy native objects (Open3D clouds, Go-ICP
    handles) local to a call, or rebuild them lazily (e.g. a checkpoint loaded on first use).

    Attributes:
        name: registry name, e.g. ``"icp"``.
        needs_training: ``True`` for learned methods (adapters wrap a trained checkpoint).
        needs_normals: ``True`` if the method uses surface normals. Classical methods here
            estimate them themselves from the clouds as received (see each method).
        config_cls: the dataclass holding the method's settings.
        normalise_frame: register pairs outside the working frame in it (module docstring).
        point_budget: most points per cloud handed to :meth:`_register` (None: no limit);
            set it on an instance to change it for that instance.
    """

    name: ClassVar[str] = "registrator"
    needs_training: ClassVar[bool] = False
    needs_normals: ClassVar[bool] = False
    config_cls: ClassVar[type[RegistratorConfig]] = RegistratorConfig
    normalise_frame: ClassVar[bool] = True
    point_budget: ClassVar[int | None] = POINT_BUDGET

    def __init__(self, config: RegistratorConfig | None = None, **overrides: Any) -> None:
        if config is None:
            config = _build_config(self.config_cls, self.name, overrides)
        else:
            if not isinstance(config, self.config_cls):
                raise ConfigError(
                    f"{self.name}: config must be a {self.config_cls.__qualname__}, "
                    f"got {type(config).__qualname__}"
                )
            if overrides:
                config = _build_config(self.config_cls, self.name, {**config.to_dict(), **overrides})
        self.config = config

    # -- public API --------------------------------------------------------------------

    def register(self, src: Any, ref: Any) -> np.ndarray:
        """Estimate ``T`` (4, 4) with ``ref ≈ T[:3, :3] @ src + T[:3, 3]``.

        ``src`` is (N, 3) and ``ref`` (M, 3); N and M may differ. Raises PointCloudError for
        bad inputs. Registers in the working frame and within the point budget (module
        docstring); the result is returned as float64 as the method produced it (mapped back
        to the input's frame); :meth:`register_result` (which the runners use) also rejects
        non-rigid estimates and reports the time, failures and the inlier fit.
        """
        return self._register_conditioned(check_cloud(src, "src"), check_cloud(ref, "ref"))

    def register_result(
        self, src: Any, ref: Any, threshold: float | None = FIT_THRESHOLD, timeout_s: float | None = None
    ) -> RegistrationResult:
        """Register one pair as :meth:`register` does and report how it went.

        The same input checks (PointCloudError for bad clouds) and :meth:`setup` errors raise; a
        method that raises, or whose estimate is not a finite proper rigid 4x4, gives a failed
        :class:`~baselines.result.RegistrationResult` (the identity, with the reason) instead.
        ``threshold``: inlier distance of ``fitness`` / ``inlier_rmse``, in the clouds' units
        (default :data:`~baselines.result.FIT_THRESHOLD` = 0.05; None: not evaluated).
        ``timeout_s``: a call that took longer counts as timed out (a call in this process cannot be
        interrupted; :func:`~baselines.runner.run_pairs` kills a worker past it).
        """
        check_threshold(threshold)
        src, ref = check_cloud(src, "src"), check_cloud(ref, "ref")
        self.setup()
        start = time.perf_counter()
        try:
            estimate = self._register_conditioned(src, ref)
        except Exception as exc:  # noqa: BLE001 - the method failed: recorded, not raised
            return RegistrationResult.failure(one_line(exc), time.perf_counter() - start)
        result = RegistrationResult.of_estimate(estimate, time.perf_counter() - start, timeout_s)
        return result.with_fit(src, ref, threshold)

    def register_batch(self, src: Any, ref: Any) -> np.ndarray:
        """Register ``B`` pairs: ``src`` (B, N, 3), ``ref`` (B, M, 3) -> (B, 4, 4)."""
        src_arr = check_batch(src, "src")
        ref_arr = check_batch(ref, "ref")
        if src_arr.shape[0] != ref_arr.shape[0]:
            raise PointCloudError(
                f"src and ref batches differ in size: {src_arr.shape[0]} vs {ref_arr.shape[0]}"
            )
        out = np.asarray(self._register_batch(src_arr, ref_arr), dtype=np.float64)
        if out.shape != (src_arr.shape[0], 4, 4):
            raise RuntimeError(
                f"{self.name}: _register_batch returned shape {out.shape}, "
                f"expected ({src_arr.shape[0]}, 4, 4)"
            )
        return out

    def setup(self) -> None:
        """Prepare for registering (import heavy libraries, load a checkpoint, ...).

        Called once per worker process by :func:`baselines.runner.run_pairs` before the
        first pair, so one-off costs are not counted in a pair's time. Must be idempotent;
        :meth:`register` works without it (it just pays the cost on the first call).
        """

    # -- for subclasses ----------------------------------------------------------------

    @abstractmethod
    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Register one checked pair (float64, (N, 3) and (M, 3)); return a 4x4 transform."""

    def _register_batch(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Register a checked batch; the default registers pair by pair as :meth:`register` does.

        Learned adapters override this to run the batch through the network at once.
        """
        return np.stack([self._register_conditioned(s, r) for s, r in zip(src, ref)])

    def _register_conditioned(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """:meth:`_register` of a checked pair in the working frame, within the point budget."""
        frame = working_frame(src, ref) if self.normalise_frame else None
        if frame is not None:
            src, ref = frame.apply(src), frame.apply(ref)
        transform = _as_transform(self._register(*within_budget(src, ref, self.point_budget)))
        return transform if frame is None else frame.map_back(transform)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.config!r})"


def _as_transform(value: Any) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (4, 4):
        raise RuntimeError(f"registration returned shape {arr.shape}, expected (4, 4)")
    return arr


def _build_config(
    config_cls: type[RegistratorConfig], method: str, values: dict[str, Any]
) -> RegistratorConfig:
    fields = {f.name for f in dataclasses.fields(config_cls)}
    unknown = sorted(set(values) - fields)
    if unknown:
        valid = ", ".join(sorted(fields)) or "(none)"
        raise ConfigError(f"unknown option(s) {', '.join(unknown)} for method '{method}'; valid: {valid}")
    try:
        return config_cls(**values)
    except TypeError as exc:  # e.g. a required field missing
        raise ConfigError(f"bad options for method '{method}': {exc}") from None


# --------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------

#: name -> Registrator subclass, or "module:Class" imported on first use: every record of
#: :data:`baselines.methods.METHODS`, and what :func:`register_registrator` adds.
_REGISTRY: dict[str, type[Registrator] | str] = {method.key: method.registrator for method in METHODS}


def _normalise(name: str) -> str:
    return str(name).strip().lower().replace("-", "_").replace(" ", "_")


def register_registrator(name: str, target: type[Registrator] | str | None = None):
    """Add a method outside :data:`baselines.methods.METHODS` (a test's, a plug-in's) to the registry;
    usable as a class decorator.

    ``target`` is a Registrator subclass or a lazy ``"package.module:Class"`` path (imported
    by :func:`get_registrator` on first use), e.g.
    ``register_registrator("toy", "baselines.testing:ToyRegistrator")``.
    """
    key = _normalise(name)

    def _add(obj: type[Registrator] | str) -> type[Registrator] | str:
        _REGISTRY[key] = obj
        return obj

    if target is None:
        return _add
    return _add(target)


def available_registrators() -> list[str]:
    """Registered method names, sorted."""
    return sorted(_REGISTRY)


def resolve_registrator(name: str) -> type[Registrator]:
    """The Registrator class registered under ``name`` (ConfigError if unknown): a method's key,
    display name or alias (:func:`baselines.methods.find_method`), or a name given to
    :func:`register_registrator`."""
    method = find_method(name)
    key = method.key if method is not None else _normalise(name)
    if key not in _REGISTRY:
        raise ConfigError(
            f"unknown registration method '{name}'; available: {', '.join(available_registrators())}"
        )
    target = _REGISTRY[key]
    if isinstance(target, str):
        module_name, _, attr = target.partition(":")
        module = importlib.import_module(module_name)
        target = getattr(module, attr)
        _REGISTRY[key] = target
    return target


def get_registrator(name: str, config: RegistratorConfig | None = None, **cfg: Any) -> Registrator:
    """Build the method registered under ``name`` with its config overridden by ``cfg``.

    Unknown names and unknown config keys raise ConfigError naming the valid choices.
    """
    return resolve_registrator(name)(config, **cfg)
