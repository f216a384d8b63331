"""The import contracts of pyproject.toml ([tool.importlinter]): the layers benchmarks > baselines > src
and the layers inside src only point down (an import inside a function counts too), no product module
imports a study (``benchmarks/studies/``), and the modules of a package import each other in no cycle."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.helpers.paths import ROOT

importlinter = pytest.importorskip("importlinter", reason="import-linter (the dev extra) is not installed")
tomllib = pytest.importorskip("tomllib")

PYPROJECT = ROOT / "pyproject.toml"
LINT = "import sys; from importlinter.cli import lint_imports; sys.exit(lint_imports(no_cache=True, no_logo=True))"


def _lint(cwd: Path) -> subprocess.CompletedProcess:
    """``lint-imports`` on the packages below ``cwd``, with the pyproject.toml there."""
    return subprocess.run([sys.executable, "-c", LINT], cwd=cwd, capture_output=True, text=True, timeout=300,
                          env={"PYTHONPATH": str(cwd), "PATH": "/usr/bin:/bin"})


def _config() -> dict:
    return tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]


def test_the_contract_names_the_layers_top_down():
    config = _config()
    assert set(config["root_packages"]) == {"src", "baselines", "benchmarks"}
    layers = [c for c in config["contracts"] if c["type"] == "layers"]
    assert layers[0]["layers"] == ["benchmarks", "baselines", "src"]
    assert not any(c.get("ignore_imports") for c in config["contracts"])


def test_every_package_of_src_has_its_layer():
    """A new subpackage or top-level module of src must be placed in the src layers contract."""
    inner = next(c for c in _config()["contracts"] if c["type"] == "layers" and c["layers"][-1] == "src.utils")
    named = {name.strip() for layer in inner["layers"] for name in layer.split("|")}
    present = {f"src.{p.stem if p.suffix else p.name}" for p in (ROOT / "src").iterdir()
               if (p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").is_file()}
    assert present == named


def test_every_product_package_of_benchmarks_is_forbidden_the_studies():
    """The studies contract lists every product module of benchmarks (a new one would escape it otherwise)."""
    contract = next(c for c in _config()["contracts"] if c.get("forbidden_modules") == ["benchmarks.studies"])
    product = {f"benchmarks.{p.stem if p.suffix else p.name}" for p in (ROOT / "benchmarks").iterdir()
               if ((p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").is_file()) and p.name != "studies"}
    assert product <= set(contract["source_modules"])
    assert {"src", "baselines"} <= set(contract["source_modules"])


def test_the_import_contracts_are_kept():
    result = _lint(ROOT)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "BROKEN" not in result.stdout


def test_an_upward_import_breaks_the_contract(tmp_path):
    """The layers contract, as pyproject.toml states it, on a three-package tree whose src imports baselines
    inside a function."""
    config = _config()
    layers = next(c for c in config["contracts"] if c["type"] == "layers")
    (tmp_path / "pyproject.toml").write_text(
        f"[tool.importlinter]\nroot_packages = {json.dumps(config['root_packages'])}\n\n"
        f"[[tool.importlinter.contracts]]\nname = {json.dumps(layers['name'])}\ntype = \"layers\"\n"
        f"layers = {json.dumps(layers['layers'])}\n")
    modules = {
        "baselines/__init__.py": "import src",
        "benchmarks/__init__.py": "import baselines",
        "src/__init__.py": "def load():\n    from baselines import published  # an upward import, hidden in a function\n",
        "baselines/published.py": "",
    }
    for name, text in modules.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(textwrap.dedent(text))
    result = _lint(tmp_path)
    assert result.returncode != 0
    assert "src is not allowed to import baselines" in result.stdout


def test_the_studies_are_not_installed():
    """``pip install`` ships the product's packages and leaves the studies in the repository."""
    setuptools = pytest.importorskip("setuptools")
    find = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["packages"]["find"]
    found = set(setuptools.find_packages(where=str(ROOT), include=find["include"], exclude=find["exclude"]))
    assert {"src.run", "src.utils", "benchmarks.grid", "benchmarks.tables", "baselines.learned"} <= found
    assert not any(name.startswith("benchmarks.studies") for name in found)
