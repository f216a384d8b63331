"""The interface of every registration method in the comparison grid: :class:`Registrator` and the base of
its settings, :class:`RegistratorConfig`.

A Registrator estimates the rigid transform ``T`` (4x4, float64) with ``ref ≈ R @ src + t`` for a source
cloud (N, 3) and a reference cloud (M, 3): :meth:`~Registrator.register` returns ``T``,
:meth:`~Registrator.register_result` a :class:`~baselines.result.RegistrationResult`. Classical methods
implement :meth:`~Registrator._register`; learned adapters (:mod:`baselines.learned.adapter`) override
:meth:`~Registrator._register_batch`. Inputs are checked by :func:`~src.geometry.clouds.check_cloud` and
conditioned by :mod:`baselines.conditioning` (each point once, in the method's frame, within its point budget),
then refused where they cannot determine the method's rotation (:meth:`~Registrator._refuse_undetermined`); methods
are looked up by name in :mod:`baselines.registry`.
More: ``docs/methods/base.md``.
"""

from __future__ import annotations

import dataclasses
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from baselines.conditioning import POINT_BUDGET, Similarity, condition, working_frame
from baselines.result import FIT_THRESHOLD, RegistrationResult, check_threshold, one_line, transform_problem
from src.utils.errors import ConfigError, PointCloudError, RegistrationError
from src.geometry.clouds import check_batch, check_cloud

__all__ = ["Registrator", "RegistratorConfig", "is_planar", "refuse_planar", "require_found", "require_points"]

#: Relative size under which a centred cloud's third singular value counts as zero (all points on one plane): 16
#: float32 epsilons, so that a plane stored in float32 is a plane.
PLANAR_RTOL = 16 * float(np.finfo(np.float32).eps)
#: Fewest correspondences (inliers) a solver's answer must rest on to determine a rotation.
MIN_CORRESPONDENCES = 3


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



def _within(cfg: RegistratorConfig, *names: str, interval: str) -> None:
    """Raise ConfigError unless each named field of ``cfg`` lies in ``interval``, written as in maths:
    ``"(0, 1]"``, ``"[0, 1)"``, ``"(1, inf)"``."""
    low, high = (float(bound) for bound in interval[1:-1].split(","))
    for name in names:
        value = getattr(cfg, name)
        above = value >= low if interval[0] == "[" else value > low
        below = value <= high if interval[-1] == "]" else value < high
        if not (above and below):
            raise ConfigError(f"{type(cfg).__qualname__}.{name} must be in {interval}, got {value!r}")


def require_points(method: str, src: np.ndarray, ref: np.ndarray, need: int, why: str) -> None:
    """PointCloudError unless each cloud of a conditioned pair (its points each once) has ``need`` points; ``why``
    completes "each cloud needs at least <need> points ...", e.g. ``"for this network"``."""
    fewest = min(len(src), len(ref))
    if fewest < need:
        raise PointCloudError(f"{method}: each cloud needs at least {need} points {why}, got {fewest}")


def require_found(method: str, solver: str, kept: int, at_start: bool = True) -> None:
    """RegistrationError when ``solver`` found nothing: its answer rests on fewer than :data:`MIN_CORRESPONDENCES`
    correspondences (the libraries then return the identity, or a pose nothing determines). A local solver found
    nothing only if its answer is still its start (``at_start``): one that moved, then lost its correspondences,
    returns the pose it diverged to, its estimate."""
    if at_start and kept < MIN_CORRESPONDENCES:
        raise RegistrationError(f"{method}: found no transform: {solver} ended with {kept} correspondences, a rotation "
                                f"needs {MIN_CORRESPONDENCES}: the clouds share too little for it; try another method")


def is_planar(points: np.ndarray) -> bool:
    """Whether all ``points`` lie on one plane, to :data:`PLANAR_RTOL` of the cloud's extent."""
    singular = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(singular[2] <= PLANAR_RTOL * singular[0])


def refuse_planar(method: str, why: str, **clouds: np.ndarray) -> None:
    """PointCloudError if one of the named ``clouds`` has all its points on one plane, for a method that cannot
    resolve such a cloud (``why``; ``""``: it can, nothing is refused)."""
    for name, cloud in clouds.items():
        if why and is_planar(cloud):
            raise PointCloudError(f"{method}: the {name} cloud's {len(cloud)} points all lie on one plane, where "
                                  f"{why}; register it with a method that resolves planar clouds (icp, gicp, cpd)")


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
        point_budget: most points per cloud handed to :meth:`_register` (None: no limit);
            set it on an instance to change it for that instance.
        planar_blind: why the method cannot determine the rotation of a cloud whose points all lie on one plane
            (``""``: it can); such a cloud is then refused.
    """

    name: ClassVar[str] = "registrator"
    needs_training: ClassVar[bool] = False
    needs_normals: ClassVar[bool] = False
    config_cls: ClassVar[type[RegistratorConfig]] = RegistratorConfig
    point_budget: ClassVar[int | None] = POINT_BUDGET
    planar_blind: ClassVar[str] = ""

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
        bad inputs and for a pair that cannot determine this method's rotation (:meth:`_refuse_undetermined`), and
        RegistrationError where the method found no transform or its estimate is no rigid transform (NaN, a
        reflection: :func:`~baselines.result.transform_problem`). Registers each point once, in the method's frame
        (:meth:`frame`) and within the point budget (:mod:`baselines.conditioning`); the result is returned as
        float64 as the method produced it (mapped back to the input's frame); :meth:`register_result` (which the
        runners use) reports such failures in its result instead, with the time and the inlier fit.
        """
        return self._rigid(self._register_conditioned(check_cloud(src, "src"), check_cloud(ref, "ref")))

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
        for index, estimate in enumerate(out):
            self._rigid(estimate, f" of pair {index}")
        return out

    def setup(self) -> None:
        """Prepare for registering (import heavy libraries, load a checkpoint, ...).

        Called once per worker process by :func:`baselines.runner.run_pairs` before the
        first pair, so one-off costs are not counted in a pair's time. Must be idempotent;
        :meth:`register` works without it (it just pays the cost on the first call).
        """

    def frame(self, src: np.ndarray, ref: np.ndarray) -> Similarity | None:
        """The similarity taking a checked pair (its points each once) into the frame this method registers in,
        None when it registers the pair as given: the working frame (:func:`~baselines.conditioning.working_frame`)."""
        return working_frame(src, ref)

    # -- for subclasses ----------------------------------------------------------------

    @abstractmethod
    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Register one checked pair (float64, (N, 3) and (M, 3)); return a 4x4 transform."""

    def _register_batch(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Register a checked batch; the default registers pair by pair as :meth:`register` does.

        Learned adapters override this to run the batch through the network at once.
        """
        return np.stack([self._register_conditioned(s, r) for s, r in zip(src, ref)])

    def _rigid(self, estimate: np.ndarray, which: str = "") -> np.ndarray:
        """``estimate``, or RegistrationError where it is no proper rigid transform."""
        problem = transform_problem(estimate)
        if problem is not None:
            raise RegistrationError(f"{self.name}: the estimate{which} is no rigid transform ({problem}): the pair is "
                                    "outside what this method handles (far outliers, too few points?); check the "
                                    "clouds, or try another method")
        return estimate

    def _refuse_undetermined(self, src: np.ndarray, ref: np.ndarray) -> None:
        """Raise PointCloudError where a conditioned pair cannot determine a rotation by this method, beyond
        :func:`~src.geometry.clouds.check_cloud`'s 3 points not on one line: here a planar cloud when
        :attr:`planar_blind`; methods add what they need (more points, normals)."""
        refuse_planar(self.name, self.planar_blind, src=src, ref=ref)

    def _conditioned(self, src: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, Callable]:
        """A checked pair conditioned (:func:`~baselines.conditioning.condition`: each point once, in :meth:`frame`,
        within the point budget) and found able to determine the rotation, with the ``undo`` of its estimate."""
        src, ref, undo = condition(src, ref, frame=self.frame, budget=self.point_budget)
        self._refuse_undetermined(src, ref)
        return src, ref, undo

    def _register_conditioned(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """:meth:`_register` of a checked pair, :meth:`_conditioned`."""
        src, ref, undo = self._conditioned(src, ref)
        return undo(_as_transform(self._register(src, ref)))

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
