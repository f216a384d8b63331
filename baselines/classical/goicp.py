"""Go-ICP (Yang, Li, Campbell & Jia, ICCV 2013 / TPAMI 2016): globally optimal ICP by nested
branch-and-bound over rotations and translations, with a distance transform and local ICP.

Backend: the authors' C++ code as wrapped by PyPI's ``py-goicp`` (GPL-3.0), an *optional* extension built by
``baselines/classical/install_goicp.sh``; without it, constructing :class:`GoICP` raises a ConfigError that
names the script. Conventions, options and measurements: ``docs/methods/goicp.md``.
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import os
import sys
from dataclasses import dataclass

import numpy as np

from baselines.base import Registrator, RegistratorConfig, _positive, _within, require_points
from src.utils.errors import ConfigError
from src.geometry.numpy_rigid import project_to_rotation, rigid_transform

INSTALL_HINT = "bash baselines/classical/install_goicp.sh"


def goicp_available() -> bool:
    """Whether the optional ``py_goicp`` extension can be imported."""
    return importlib.util.find_spec("py_goicp") is not None


@dataclass
class GoICPConfig(RegistratorConfig):
    """Settings of :class:`GoICP` (see the module docstring for why these defaults)."""

    mse_threshold: float = 0.002
    trim_fraction: float = 0.3
    dt_size: int = 100
    dt_expand_factor: float = 2.0
    rotation_half_width: float = math.pi
    translation_half_width: float = 0.5
    quiet: bool = True  # swallow the C++ code's progress prints on stdout

    def __post_init__(self) -> None:
        _positive(self, "mse_threshold", "dt_size", "rotation_half_width", "translation_half_width")
        _within(self, "trim_fraction", interval="[0, 1)")
        if self.dt_expand_factor < 1.0:
            raise ConfigError(f"GoICPConfig.dt_expand_factor must be >= 1, got {self.dt_expand_factor!r}")
        if self.rotation_half_width > math.pi + 1e-9:
            raise ConfigError(
                f"GoICPConfig.rotation_half_width must be <= pi (the rotation ball), got {self.rotation_half_width!r}"
            )


@contextlib.contextmanager
def _silenced_stdout(enabled: bool = True):
    """Redirect file descriptor 1 to /dev/null (the C++ code prints with ``std::cout``)."""
    if not enabled:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        try:
            sys.stdout.flush()
        except Exception:  # pragma: no cover - flushing a closed stream
            pass
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def normalise_pair(src: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Centre each cloud on its centroid and scale both by one factor into [-1, 1]^3.

    Returns ``(src_n, ref_n, c_src, c_ref, scale)`` with ``src = src_n * scale + c_src``.
    """
    c_src = src.mean(axis=0)
    c_ref = ref.mean(axis=0)
    scale = float(max(np.abs(src - c_src).max(), np.abs(ref - c_ref).max()))
    if not np.isfinite(scale) or scale <= 0.0:
        scale = 1.0
    return (src - c_src) / scale, (ref - c_ref) / scale, c_src, c_ref, scale


class GoICP(Registrator):
    """Go-ICP via the optional ``py-goicp`` extension (install with ``install_goicp.sh``)."""

    name = "goicp"
    needs_training = False
    needs_normals = False
    config_cls = GoICPConfig

    def __init__(self, config: GoICPConfig | None = None, **overrides) -> None:
        super().__init__(config, **overrides)
        if not goicp_available():
            raise ConfigError(
                "method 'goicp' needs the optional py-goicp extension, which is not installed; "
                f"build and install it with `{INSTALL_HINT}`"
            )

    def fewest_points(self) -> int:
        """Points a cloud needs: Go-ICP's trimming keeps ``int(N · (1 − trim_fraction))`` of the source's N (at
        least 1), and a rotation needs 3."""
        keep = 1.0 - float(self.config.trim_fraction)
        need = math.ceil(3 / keep)
        return need if int(need * keep) >= 3 else need + 1

    def _refuse_undetermined(self, src: np.ndarray, ref: np.ndarray) -> None:
        """Fewer points than :meth:`fewest_points`."""
        super()._refuse_undetermined(src, ref)
        require_points(self.name, src, ref, self.fewest_points(),
                       f"for Go-ICP's trimming (it keeps int(N · (1 − trim_fraction={self.config.trim_fraction:g})) "
                       "of them, and a rotation needs 3)")

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        import py_goicp

        cfg: GoICPConfig = self.config
        src_n, ref_n, c_src, c_ref, scale = normalise_pair(src, ref)

        solver = py_goicp.GoICP()
        model = [py_goicp.POINT3D(float(x), float(y), float(z)) for x, y, z in ref_n]
        data = [py_goicp.POINT3D(float(x), float(y), float(z)) for x, y, z in src_n]
        solver.loadModelAndData(len(model), model, len(data), data)
        solver.setDTSizeAndFactor(int(cfg.dt_size), float(cfg.dt_expand_factor))

        rot_node = py_goicp.ROTNODE()
        rot_node.a = rot_node.b = rot_node.c = -float(cfg.rotation_half_width)
        rot_node.w = 2.0 * float(cfg.rotation_half_width)
        rot_node.l = 0
        rot_node.lb = 0.0
        rot_node.ub = 0.0
        trans_node = py_goicp.TRANSNODE()
        trans_node.x = trans_node.y = trans_node.z = -float(cfg.translation_half_width)
        trans_node.w = 2.0 * float(cfg.translation_half_width)
        trans_node.lb = 0.0
        trans_node.ub = 0.0
        solver.setInitNodeRot(rot_node)
        solver.setInitNodeTrans(trans_node)

        solver.MSEThresh = float(cfg.mse_threshold)
        solver.trimFraction = float(cfg.trim_fraction)
        solver.doTrim = bool(cfg.trim_fraction > 0.0)

        with _silenced_stdout(cfg.quiet):
            solver.BuildDT()
            solver.Register()

        rot = np.asarray(solver.optimalRotation(), dtype=np.float64)
        trans = np.asarray(solver.optimalTranslation(), dtype=np.float64)
        if rot.shape != (3, 3) or trans.shape != (3,):
            raise RuntimeError(f"Go-ICP returned no solution (rotation {rot.shape}, translation {trans.shape})")
        rot = project_to_rotation(rot)  # single-precision C++ output: remove rounding drift
        return rigid_transform(rot, c_ref - rot @ c_src + scale * trans)
