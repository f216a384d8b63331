"""The authors' rigid CPD (Myronenko's CPD package, MATLAB) run by GNU Octave: the golden reference (``authors.cpd``).

A checkout holding the package's ``core/`` folder (``cpd_register.m``, ``Rigid/cpd_rigid.m``, ``utils/``,
``mex/cpd_P.c``) is read in place: its E-step ``cpd_P.c`` is compiled with ``mkoctfile --mex`` into a temporary
folder (the checkout's prebuilt MATLAB binaries are not used), and every pair is registered by
``cpd_register(X=ref, Y=src, opt)`` with ``opt.method='rigid'``, ``opt.scale=0``, ``opt.normalize=0``
(``cpd_register.m`` turns the scale back on when it normalises), ``opt.rot=1``, no FGT, no plots, and the
iteration settings of :class:`baselines.classical.cpd.CPDConfig`'s documented defaults, written here again. The
result ``T.Y = Y R' + t`` is ``src`` mapped onto ``ref``. Needs ``octave`` and ``mkoctfile`` (Debian:
``apt-get install octave liboctave-dev``).
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
from scipy.io import loadmat, savemat

from src.utils.errors import ConfigError

#: The wrapper's documented defaults (``baselines/classical/cpd.py``): outlier weight, iterations, tolerance on the
#: relative change of the negative log-likelihood; σ² from the data (``opt.sigma2 = 0``).
W, MAX_ITERATIONS, TOLERANCE = 0.9, 150, 1e-5

_SCRIPT = """
addpath('{core}'); addpath('{core}/Rigid'); addpath('{core}/utils'); addpath('{mex}');
load('{pairs}');
opt = struct('method', 'rigid', 'scale', 0, 'normalize', 0, 'rot', 1, 'viz', 0, 'fgt', 0, 'corresp', 0, ...
             'outliers', {w}, 'max_it', {max_it}, 'tol', {tol}, 'sigma2', 0, 'verbosity', 0);
P = size(src, 1); R = zeros(P, 3, 3); t = zeros(P, 3); iter = zeros(P, 1);
for i = 1:P
  T = cpd_register(squeeze(ref(i, :, :)), squeeze(src(i, :, :)), opt);
  R(i, :, :) = T.R; t(i, :) = T.t; iter(i) = T.iter;
end
save('-v7', '{result}', 'R', 't', 'iter');
"""


def _octave() -> tuple[str, str]:
    octave, mkoctfile = shutil.which("octave"), shutil.which("mkoctfile")
    if octave is None or mkoctfile is None:
        raise ConfigError("the CPD golden file runs the authors' MATLAB code in GNU Octave: install octave and "
                          "mkoctfile (Debian: apt-get install octave liboctave-dev)")
    return octave, mkoctfile


def cpd(checkout: Path, pairs: dict[str, np.ndarray]) -> np.ndarray:
    """(P, 4, 4) float64 estimates of the authors' rigid CPD (scale fixed) on ``pairs``."""
    core = checkout / "core"
    missing = [name for name in ("cpd_register.m", "Rigid/cpd_rigid.m", "mex/cpd_P.c") if not (core / name).is_file()]
    if missing:
        raise ConfigError(f"{checkout} is not a checkout of the CPD package: core/{missing[0]} is missing")
    octave, mkoctfile = _octave()
    with tempfile.TemporaryDirectory() as work:
        work_dir = Path(work)
        subprocess.run([mkoctfile, "--mex", "-o", str(work_dir / "cpd_P.mex"), str(core / "mex" / "cpd_P.c")],
                       check=True, capture_output=True)
        savemat(work_dir / "pairs.mat", {k: np.asarray(pairs[k], dtype=np.float64) for k in ("src", "ref")})
        script = _SCRIPT.format(core=core, mex=work_dir, pairs=work_dir / "pairs.mat", result=work_dir / "result.mat",
                                w=W, max_it=MAX_ITERATIONS, tol=TOLERANCE)
        subprocess.run([octave, "--no-gui", "--quiet", "--no-init-file", "--eval", script], check=True,
                       capture_output=True, text=True)
        result = loadmat(work_dir / "result.mat")
    out = np.tile(np.eye(4), (len(pairs["src"]), 1, 1))
    out[:, :3, :3], out[:, :3, 3] = result["R"], result["t"]
    return out
