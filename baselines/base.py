"""One interface for every registration method in the comparison grid.

A :class:`Registrator` estimates the rigid transform ``T`` (4x4, float64) with
``ref ≈ R @ src + t`` for a source cloud ``src`` (N, 3) and a reference cloud ``ref`` (M, 3).
Classical methods (ICP, FGR, Symmetric ICP, Go-ICP) implement :meth:`Registrator._register`;
learned networks get adapters that wrap a checkpoint behind the same interface, set
``needs_training = True`` and usually override :meth:`Registrator._register_batch` to run a
whole batch on the GPU at once.

Input checking lives here, in one place (:func:`check_cloud`, :func:`check_batch`), so every
method rejects empty, NaN or wrongly shaped clouds with the same one-line
:class:`~src.errors.PointCloudError`.

Methods are looked up by name with :func:`get_registrator`; a method registers itself with
:func:`register_registrator`, either eagerly (a class) or lazily (``"module:Class"``, so that
``import baselines`` does not import Open3D, torch or an optional extension).
"""

from __future__ import annotations

import dataclasses
import importlib
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from src.errors import ConfigError, PointCloudError

__all__ = [
    "MIN_POINTS",
    "Registrator",
    "RegistratorConfig",
    "available_registrators",
    "check_batch",
    "check_cloud",
    "get_registrator",
    "project_to_rotation",
    "register_registrator",
    "resolve_registrator",
    "rigid_transform",
    "transform_problem",
]

#: Fewest points a cloud may have: a rigid transform is not determined by fewer than 3.
MIN_POINTS = 3


# --------------------------------------------------------------------------------------
# Input and output checks
# --------------------------------------------------------------------------------------


def _as_float64(points: Any, name: str) -> np.ndarray:
    try:
        return np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PointCloudError(f"{name}: cannot be read as an array of numbers ({exc})") from None


def check_cloud(points: Any, name: str = "points") -> np.ndarray:
    """Return ``points`` as a C-contiguous float64 ``(N, 3)`` array or raise PointCloudError."""
    arr = _as_float64(points, name)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise PointCloudError(f"{name}: expected an (N, 3) array of points, got shape {tuple(arr.shape)}")
    if arr.shape[0] < MIN_POINTS:
        raise PointCloudError(f"{name}: needs at least {MIN_POINTS} points, got {arr.shape[0]}")
    bad = ~np.isfinite(arr)
    if bad.any():
        n_bad = int(bad.any(axis=1).sum())
        raise PointCloudError(
            f"{name}: {n_bad} of {arr.shape[0]} points have NaN or infinite coordinates"
        )
    return np.ascontiguousarray(arr)


def check_batch(points: Any, name: str = "points") -> np.ndarray:
    """Return ``points`` as a float64 ``(B, N, 3)`` array or raise PointCloudError."""
    arr = _as_float64(points, name)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise PointCloudError(
            f"{name}: expected a (B, N, 3) batch of point clouds, got shape {tuple(arr.shape)}"
        )
    if arr.shape[0] == 0:
        raise PointCloudError(f"{name}: the batch is empty (B = 0)")
    for b in range(arr.shape[0]):
        check_cloud(arr[b], f"{name}[{b}]")
    return np.ascontiguousarray(arr)


def rigid_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Assemble a 4x4 float64 homogeneous transform from ``R`` (3, 3) and ``t`` (3,)."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return out


def project_to_rotation(matrix: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (Frobenius norm) to a 3x3 matrix, via SVD with det = +1."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def transform_problem(transform: Any, atol: float = 1e-4) -> str | None:
    """Why ``transform`` is not a proper rigid 4x4 transform, or ``None`` if it is.

    Checks the shape, finiteness, the bottom row ``[0, 0, 0, 1]``, ``R^T R = I`` and
    ``det R = +1`` (all to ``atol``).
    """
    try:
        arr = np.asarray(transform, dtype=np.float64)
    except (TypeError, ValueError):
        return f"estimate is not numeric ({type(transform).__name__})"
    if arr.shape != (4, 4):
        return f"estimate has shape {tuple(arr.shape)}, expected (4, 4)"
    if not np.isfinite(arr).all():
        return "estimate contains NaN or infinite entries"
    if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
        return f"estimate's bottom row is {np.round(arr[3], 6).tolist()}, expected [0, 0, 0, 1]"
    rot = arr[:3, :3]
    ortho = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if ortho > atol:
        return f"estimate's rotation is not orthonormal (max |R^T R - I| = {ortho:.2e})"
    det = float(np.linalg.det(rot))
    if abs(det - 1.0) > atol:
        return f"estimate's rotation has det {det:+.4f}, expected +1 (a reflection)"
    return None


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
    """

    name: ClassVar[str] = "registrator"
    needs_training: ClassVar[bool] = False
    needs_normals: ClassVar[bool] = False
    config_cls: ClassVar[type[RegistratorConfig]] = RegistratorConfig

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
        bad inputs. The result is returned as float64 as the method produced it; use
        :func:`transform_problem` (the runner does) to reject non-rigid estimates.
        """
        src_arr = check_cloud(src, "src")
        ref_arr = check_cloud(ref, "ref")
        return _as_transform(self._register(src_arr, ref_arr))

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
        """Register a checked batch; the default loops over :meth:`_register`.

        Learned adapters override this to run the batch through the network at once.
        """
        return np.stack([_as_transform(self._register(s, r)) for s, r in zip(src, ref)])

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

#: name -> Registrator subclass, or "module:Class" imported on first use.
LEARNED_DISPLAY_NAMES: dict[str, str] = {
    "omnet": "OMNet", "dcp": "DCP", "prnet": "PRNet", "rpmnet": "RPMNet", "idam": "IDAM",
    "pointnetlk": "PointNetLK", "fmr": "FMR", "deepgmr": "DeepGMR",
}
"""Learned networks, entering the grid through adapters around ``src.train`` checkpoints."""

_REGISTRY: dict[str, type[Registrator] | str] = {
    "icp": "baselines.classical.icp:ICP",
    "fgr": "baselines.classical.fgr:FGR",
    "symmetric_icp": "baselines.classical.symmetric_icp:SymmetricICP",
    "goicp": "baselines.classical.goicp:GoICP",
    "identity": "baselines.classical.identity:Identity",
    **{name: f"baselines.learned.adapter:{display}Registrator" for name, display in LEARNED_DISPLAY_NAMES.items()},
}
_ALIASES: dict[str, str] = {"go_icp": "goicp", "symicp": "symmetric_icp", "sym_icp": "symmetric_icp"}


def _normalise(name: str) -> str:
    return str(name).strip().lower().replace("-", "_").replace(" ", "_")


def register_registrator(name: str, target: type[Registrator] | str | None = None):
    """Add a method to the registry; usable as a class decorator.

    ``target`` is a Registrator subclass or a lazy ``"package.module:Class"`` path (imported
    by :func:`get_registrator` on first use). Learned adapters register the same way, e.g.
    ``register_registrator("omnet", "baselines.learned.omnet:OMNetRegistrator")``.
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
    """The Registrator class registered under ``name`` (ConfigError if unknown)."""
    key = _normalise(name)
    key = _ALIASES.get(key, key)
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
