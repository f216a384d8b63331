#!/usr/bin/env bash
# Install the optional Go-ICP backend (PyPI "py-goicp" 0.0.4, a Cython wrapper of the
# authors' C++ code; GPL-3.0) into the current Python environment.
#
# Its sdist only builds with old build tools (cython<3, autowrap<0.23, setuptools<70, and
# --no-build-isolation), which must not replace this environment's own. So the wheel is
# built in a throw-away virtual environment made from the same interpreter, and only the
# resulting wheel is installed here (--no-deps; its declared autowrap dependency, a build-time
# tool never imported at run time, is removed from the metadata). Nothing else changes here.
#
# Usage:  bash baselines/classical/install_goicp.sh [--force]
#   PYTHON=/path/to/python   interpreter whose environment receives the wheel (default: python3)
#   GOICP_WHEEL_DIR=DIR      also keep a copy of the built wheel in DIR (e.g. a CI cache)
# Needs a C++14 compiler and access to PyPI (or a mirror configured for pip).
set -euo pipefail

PYTHON="${PYTHON:-python3}"
VERSION="0.0.4"
FORCE=0
[[ "${1:-}" == "--force" ]] && FORCE=1

if [[ $FORCE -eq 0 ]] && "$PYTHON" -c "import py_goicp" >/dev/null 2>&1; then
    echo "install_goicp: py_goicp is already importable by $PYTHON (use --force to rebuild)"
    exit 0
fi

if ! command -v "${CXX:-g++}" >/dev/null 2>&1 && ! command -v c++ >/dev/null 2>&1; then
    echo "install_goicp: error: no C++ compiler found (install g++, e.g. apt-get install g++)" >&2
    exit 1
fi

workdir="$(mktemp -d "${TMPDIR:-/tmp}/goicp-build.XXXXXX")"
trap 'rm -rf "$workdir"' EXIT

echo "install_goicp: building py-goicp==$VERSION in a temporary venv ($workdir)"
"$PYTHON" -m venv "$workdir/venv"
venv_py="$workdir/venv/bin/python"
# exact versions this was verified with (any cython<3, autowrap<0.23, setuptools<70 should do)
"$venv_py" -m pip install --quiet --disable-pip-version-check \
    "cython==0.29.37" "autowrap==0.22.11" "setuptools==65.5.0" "wheel==0.48.0"
"$venv_py" -m pip wheel --quiet --disable-pip-version-check \
    --no-build-isolation --no-deps --no-binary py-goicp \
    --wheel-dir "$workdir/wheels" "py-goicp==$VERSION"

built="$(ls "$workdir"/wheels/py_goicp-"$VERSION"-*.whl)"
# The wheel declares "Requires-Dist: autowrap", a build-time tool it never imports; drop that
# line (wheel unpack/pack recomputes RECORD) so `pip check` stays clean without autowrap here.
"$venv_py" -m wheel unpack --dest "$workdir/unpacked" "$built" >/dev/null
sed -i '/^Requires-Dist: autowrap/d' "$workdir"/unpacked/py_goicp-"$VERSION"/py_goicp-"$VERSION".dist-info/METADATA
mkdir -p "$workdir/final"
"$venv_py" -m wheel pack --dest-dir "$workdir/final" "$workdir/unpacked/py_goicp-$VERSION" >/dev/null
wheel="$(ls "$workdir"/final/py_goicp-"$VERSION"-*.whl)"
echo "install_goicp: built $(basename "$wheel")"
if [[ -n "${GOICP_WHEEL_DIR:-}" ]]; then
    mkdir -p "$GOICP_WHEEL_DIR"
    cp "$wheel" "$GOICP_WHEEL_DIR"/
fi

"$PYTHON" -m pip install --quiet --disable-pip-version-check --no-deps --no-index --force-reinstall "$wheel"

# smoke test: register a small rotated cloud
"$PYTHON" - >/dev/null <<'EOF'
import py_goicp

g = py_goicp.GoICP()
pts = [(0.1, 0.2, 0.3), (-0.4, 0.1, 0.2), (0.3, -0.3, -0.1), (0.0, 0.4, -0.3), (-0.2, -0.2, 0.4)]
model = [py_goicp.POINT3D(*p) for p in pts]
data = [py_goicp.POINT3D(x + 0.05, y, z) for x, y, z in pts]
g.loadModelAndData(len(model), model, len(data), data)
g.setDTSizeAndFactor(50, 2.0)
g.BuildDT()
g.Register()
assert len(g.optimalRotation()) == 3 and len(g.optimalTranslation()) == 3
EOF
echo "install_goicp: py_goicp $VERSION installed into $("$PYTHON" -c 'import sys; print(sys.prefix)')"
