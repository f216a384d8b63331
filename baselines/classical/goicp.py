"""Go-ICP (Yang, Li, Campbell & Jia, ICCV 2013 / TPAMI 2016): globally optimal ICP by
nested branch-and-bound over rotations (angle-axis cube) and translations, with a 3D
distance transform for closest-point distances and local ICP to tighten the upper bound.

Backend: the authors' C++ code as wrapped by PyPI's ``py-goicp`` 0.0.4 (GPL-3.0), an
*optional* extension. Its sdist only builds with old build tools, so
``baselines/classical/install_goicp.sh`` builds the wheel in a throw-away virtual
environment and installs just that wheel here (no build tool in this environment changes).
Without it, constructing :class:`GoICP` raises a ConfigError that names the script.

Conventions. Go-ICP registers a *data* cloud onto a *model* cloud; here data = ``src``,
model = ``ref``, so its optimum ``(R, t)`` already satisfies ``ref ≈ R src + t``. As the
authors require, both clouds are first centred independently (each on its own centroid) and
then scaled by one common factor so that both fit in [-1, 1]^3; the result is mapped back:
``t = c_ref - R c_src + s t'``. The search domain is the full rotation ball (cube
[-π, π]^3, ``rotation_half_width = π``) and the translation cube [-0.5, 0.5]^3 in the
normalised frame (the authors' default; after centring only the centroid shift caused by
partiality remains, which is well inside it).

Defaults and why (measured with ``python -m baselines.classical.sweep goicp --pairs 20
--workers 2 --timeout 60``: 717-point noisy twice-sampled RPMNet-manner pairs of real
airplanes, on a shared 2-core machine):

* ``dt_size = 100``: the distance transform is rebuilt for every pair (the model changes)
  and its cost grows faster than the cube of the size: building it took ~0.3–0.7 s at 100,
  ~2.6 s at 150, ~6.8 s at 200 (the authors' 300: ~12 s). The grid spans twice the model's
  bounding box (``dt_expand_factor = 2``), so a cell is ~0.04 normalised units and a look-up
  is off by at most ~0.035, about the spacing of these clouds; the ICP refinements inside
  Go-ICP use exact KD-tree distances. 200 instead of 100 gave the same errors (mean 56.8°
  vs 57.1°, median 7.75° both) at 25.6 s instead of 1.3 s per pair.
* ``trim_fraction = 0.3``: the clouds are partial (each keeps ~70% of the object), so many
  source points have no counterpart in the reference. Without trimming they dominate the L2
  objective, whose optimum is then often a wrong pose, and the bounds close so slowly that
  pairs run for minutes (one pair with trim 0 / MSE 0.001 ran > 10 min; trim 0 / MSE 0.005
  timed out at 30 s on 6 of 20 pairs and had 25% of pairs under 5°; trim 0.1 / MSE 0.002
  timed out on 10 of 20). 0.3 matches the 70% crops of the RPMNet manner and is
  conservative for the PRNet manner (larger overlap).
* ``mse_threshold = 0.002`` (normalised units; Go-ICP stops once the best error is within
  ``mse_threshold × inliers`` of the lower bound). The authors use 0.001 on clean, fully
  overlapping data; with trim 0.3, 0.001 timed out at 30 s on 8 of 20 pairs. With the
  defaults no pair timed out at 60 s: 1.3 s mean, 0.74 s median, 7.3 s max per pair;
  rotation error mean 57°, median 7.8°, 50% of pairs under 5° (the paper reports 69°–76°
  mean isotropic error for Go-ICP on its RPMNet-manner data: the global optimum of the
  trimmed objective is often a wrong, e.g. flipped, pose on partial airplanes).

Runs a pair in one thread; the C++ code has no time limit, so give
:func:`baselines.runner.run_pairs` a ``timeout_s`` (it kills and replaces the worker).
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import os
import sys
from dataclasses import dataclass

import numpy as np

from baselines.base import Registrator, RegistratorConfig, _positive
from src.errors import ConfigError
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
        if not 0.0 <= self.trim_fraction < 1.0:
            raise ConfigError(f"GoICPConfig.trim_fraction must be in [0, 1), got {self.trim_fraction!r}")
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
