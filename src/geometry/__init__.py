"""Rigid-body geometry.

* Batched torch quaternions, SE(3) and Euler angles (:mod:`.quaternion`, :mod:`.se3`), whose names this
  package exports.
* Their NumPy counterparts for one transform at a time (:mod:`.numpy_rigid`), and the point-cloud input
  checks (:mod:`.clouds`): neither imports torch.

The torch names are loaded on first use (PEP 562), so that NumPy-only code (the pair transforms, the
classical baselines and their worker processes) imports :mod:`.numpy_rigid` without importing torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "quaternion": (
        "matrix_to_quat", "quat_canonical", "quat_conjugate", "quat_multiply", "quat_normalize", "quat_rotate",
        "quat_to_matrix",
    ),
    "se3": (
        "EULER_SEQUENCES", "euler_to_matrix", "matrix_to_euler", "rotation_angle", "se3_apply", "se3_compose",
        "se3_from_quat", "se3_from_rt", "se3_identity", "se3_inverse",
    ),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_MODULE_OF)


def __getattr__(name: str) -> Any:
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
