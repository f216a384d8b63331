"""The method registry (baselines/methods.yaml, baselines/methods.py): every record composes, registers a pair, appears in the
tables in the paper's order with its display name, and is what the grid, the paper matching, the
adapters and the published weights derive from."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import benchmarks.grid.plan  # noqa: F401 - stores the grid's primary config
from baselines import get_registrator, resolve_registrator
from baselines.learned.adapter import LearnedRegistrator
from baselines.learned.published import PUBLISHED, Published
from baselines.methods import METHODS, display_name, find_method, get_method, markdown_table, paper_rank
from baselines.result import inlier_fit
from baselines.testing import euler_transform, make_pair
from benchmarks.tables.paper import method_key
from benchmarks.tables.render import build_table
from src.compose import compose_model_config
from src.utils.errors import ConfigError
from src.utils.paths import shared_path
from tests.helpers.paths import CONF as CONF_DIR

CONF = str(CONF_DIR)
PAPER_DIR = shared_path("reference", "paper_tables")
TRUTH = euler_transform((10.0, -8.0, 6.0), (0.1, -0.05, 0.08))
LEARNED = [m for m in METHODS if m.kind == "learned"]


@pytest.mark.parametrize("method", [pytest.param(m, marks=[pytest.mark.goicp] if m.key == "goicp" else [])
                                    for m in METHODS], ids=[m.key for m in METHODS])
def test_every_method_composes_and_registers_a_pair(method):
    cls = resolve_registrator(method.key)
    assert cls.name == method.key and f"{cls.__module__}:{cls.__name__}" == method.registrator
    if method.kind == "classical":
        src, ref = make_pair(TRUTH, 300, seed=1)
        try:
            registrator = get_registrator(method.key)
        except ConfigError as err:  # an optional pip package not installed (small_gicp, probreg); Go-ICP: its marker
            pytest.skip(str(err))
    else:
        model = compose_model_config(method.key, 0.125)  # conf/model/<key>.yaml
        assert model.network._target_ == method.network == cls.network_target and issubclass(cls, LearnedRegistrator)
        src, ref = make_pair(TRUTH, 100, seed=1, twice_sampled=True)
        registrator = get_registrator(method.key, fresh_weights=True, model_scale=0.125, device="cpu")
        assert registrator.label == f"{method.display} (untrained)"
    result = registrator.register_result(src, ref)
    assert not result.failed, result.reason
    assert result.transform.shape == (4, 4) and 0.0 <= result.fitness <= 1.0 and result.inlier_rmse >= 0.0
    if method.kind == "classical":  # a real registration: never further from the reference than where it started
        assert result.fitness >= inlier_fit(src, ref, np.eye(4), 0.05)[0]


def _tidy(names) -> pd.DataFrame:
    return pd.DataFrame([dict(method=name, experiment="unseen_shapes", sampling=s, partial="prnet", metric="Error(R)",
                              value=1.0 + i) for i, name in enumerate(names) for s in ("OS", "TS")])


def test_every_method_appears_in_the_tables_in_the_papers_order():
    rows = build_table(_tidy(reversed([m.display for m in METHODS])), "table1", metrics=["Error(R)"]).blocks[0].rows
    labels = [row.label for row in rows]
    assert sorted(labels) == sorted(m.display for m in METHODS)
    assert labels[0] == get_method("identity").display and rows[0].reference  # the reference first, never ranked
    labels = labels[1:]
    ranked = [get_method(label) for label in labels]
    positions = [m.table1 for m in ranked if m.table1 is not None]
    assert positions == sorted(positions) and ranked[-1].ours and sum(m.ours for m in METHODS) == 1
    unpublished = [label for label, m in zip(labels, ranked) if m.table1 is None and not m.ours]
    assert unpublished == sorted(unpublished, key=str.lower)
    assert labels.index(unpublished[0]) == len(positions)  # after the paper's baselines, before its own method


@pytest.mark.shared_data("reference/paper_tables")
def test_the_registry_orders_methods_as_the_papers_own_tables_do():
    for path in sorted(PAPER_DIR.glob("*.csv")):
        names = list(dict.fromkeys(pd.read_csv(path)["method"]))
        known = [n for n in names if find_method(n) is not None]
        table = "speed" if "speed" in path.name else "table1"
        assert known == sorted(known, key=lambda n: paper_rank(n, table)), path.name


def test_the_registry_prints_as_a_markdown_table():
    rows = markdown_table().splitlines()[2:]
    assert [row.split(" | ")[:3] for row in rows] == [[f"| `{m.key}`", m.display, m.kind] for m in METHODS]
    assert all(m.code in row for m, row in zip(METHODS, rows))


def test_names_keys_and_aliases():
    for method in METHODS:  # each name denotes its own method only
        for name in (method.key, method.display, *method.aliases, method.display.upper()):
            assert find_method(name) is method and method_key(name) == method.key and display_name(name) == method.display
    assert method_key("Ours") == "omnet" and resolve_registrator("Go-ICP").name == "goicp"
    assert display_name("toy") == "toy" and find_method("sparse_icp") is None and paper_rank("toy") == (1, 0)
    with pytest.raises(ValueError, match="table must be one of"):
        paper_rank("icp", "table9")
    with pytest.raises(ConfigError, match="unknown method 'sparse_icp'; known: icp, fgr"):
        get_method("sparse_icp")
    revisited = get_method("pointnetlk_revisited")  # the class name follows the network, not the display name
    assert revisited.display == "PointNetLK-Revisited" and revisited.registrator.endswith(":PointNetLKRevisitedRegistrator")


def test_the_grid_config_comes_from_the_registry():
    learned = [m.key for m in LEARNED]
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("benchmark_grid", overrides=[f"method_options.{key}.checkpoint=/x/{key}.ckpt" for key in learned])
    assert list(cfg.benchmark.methods) == [m.key for m in METHODS if m.default_grid]
    assert list(cfg.method_options) == [m.key for m in METHODS]
    for method in METHODS:
        expected = {"checkpoint": f"/x/{method.key}.ckpt", "weights": None} if method.kind == "learned" else {}
        assert OmegaConf.to_container(cfg.method_options[method.key]) == expected


def test_published_weights_name_their_method():
    linked = [entry for entry in PUBLISHED.values() if entry.method is not None]
    assert linked
    for entry in linked:
        network = compose_model_config(entry.model, 1.0, entry.model_overrides).network._target_
        assert network == get_method(entry.method).network
    with pytest.raises(ConfigError, match="published weights x: icp is not the key of a learned method"):
        Published(name="x", file="x", sha256="0", layout="dcp", source="", license="", trained_on="", method="icp")


@pytest.mark.shared_data("reference/omnet-paper.tex")
def test_the_registry_cites_omnet_by_the_papers_authors():
    """It cited "Xu, Liu, Ye, Zhang, Zeng & Liu"."""
    tex = shared_path("reference", "omnet-paper.tex").read_text()
    block = re.search(r"\\author\{(.*?)\\\\\s*\\\\", tex, re.S).group(1)
    block = re.sub(r"\\thanks\{[^}]*\}|\$[^$]*\$|\\hspace\{[^}]*\}", "", block)
    authors = [name.strip() for name in block.splitlines() if name.strip()]
    assert len(authors) == 5
    cited = get_method("omnet").paper.split(", OMNet:")[0]
    assert cited == ", ".join(authors[:-1]) + f" & {authors[-1]}"
