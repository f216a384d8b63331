"""benchmarks.grid on a tiny synthetic set-up: the tidy frame, its numbers, resumability, failures, errors."""

import json
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir

import benchmarks.grid.run as grid_run
from benchmarks.grid.cli import main as grid_main
from benchmarks.grid.plan import Cell
from benchmarks.grid.report import report as grid_report
from baselines import get_registrator, register_registrator
from baselines.testing import ToyRegistrator
from benchmarks.tables.render import build_table, fmt
from src.utils.errors import CheckpointError, ConfigError, DatasetError, PointCloudError
from src.metrics import METRIC_NAMES, RegistrationMetrics
from src.pair_sets import TestSet
from src.utils.paths import SHIPPED_DIR
from tests.helpers.markdown import markdown_table
from tests.helpers.paths import CONF as CONF_DIR

CONF = str(CONF_DIR)
TINY_DATA = [
    "data.build.num_train_per_category=2",
    "data.build.num_test_per_category=1",
    "data.build.num_samplings=3",
]
register_registrator("toy", ToyRegistrator)


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("grid_cache")


def grid_cfg(out: Path, cache_root: Path, *overrides: str, data_overrides: tuple[str, ...] = (), tiny: bool = True):
    extra = [*(TINY_DATA if tiny else []), f"data.cache_root={cache_root}", *data_overrides]
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose("benchmark_grid", overrides=[
            "benchmark.methods=[icp,toy]",
            "benchmark.reference=null",  # (tested on its own below)
            "benchmark.experiments=[unseen_shapes]",
            "benchmark.samplings=[ts]",
            "benchmark.partials=[prnet,rpmnet]",
            "benchmark.max_pairs=3",
            "benchmark.overrides=[" + ",".join(f'"{o}"' for o in extra) + "]",
            "+method_options.toy.raise_on=[768]",  # every PRNet-manner pair (768 points) fails, RPMNet's (717) do not
            "workers=0",
            "progress=false",
            "paper=false",
            f"output_dir={out}",
            *overrides,
        ])


def test_default_grid_and_real_airplane_compose():
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("benchmark_grid")
        assert list(cfg.benchmark.methods) == ["icp", "fgr", "goicp", "symmetric_icp", "ransac", "ransac_icp",
                                               "point_to_plane_icp", "gicp", "small_gicp"]
        assert list(cfg.benchmark.experiments) == ["unseen_shapes", "unseen_categories", "gaussian_noise"]
        assert cfg.data.dataset == "synthetic" and cfg.output_dir == "outputs/grid/synthetic"
        real = compose("benchmark_grid", overrides=["+benchmark=real_airplane"])
        assert real.benchmark.name == "real_airplane" and list(real.benchmark.experiments) == ["real_airplane", "real_airplane_noisy", "real_unseen_category"]
        assert list(real.benchmark.partials) == ["prnet"] and list(real.benchmark.samplings) == ["os", "ts"]
        assert real.data.dataset == "modelnet40_resampled" and real.output_dir == "outputs/grid/real_airplane"
        learned = [m for m in real.benchmark.methods if real.method_options[m].get("checkpoint")]
        shipped = {path.name.removesuffix("_real_airplane_ts_prnet.json") for path in SHIPPED_DIR.glob("*_real_airplane_ts_prnet.json")}
        assert {"omnet", "dcp", "rpmnet", "fmr", "deepgmr", "prnet", "pointnetlk"} <= shipped
        assert set(learned) == shipped  # every shipped real-airplane checkpoint has its row, each a file of the repository
        assert all(Path(real.method_options[m].checkpoint).is_file() for m in learned)


def test_modelnet_bathtub_grid_is_the_airplane_grid_on_the_bathtub_stand_ins():
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        airplane = compose("benchmark_grid", overrides=["+benchmark=modelnet_real_airplane"])
        bathtub = compose("benchmark_grid", overrides=["+benchmark=modelnet_real_bathtub"])
    assert list(bathtub.benchmark.experiments) == ["real_bathtub_modelnet", "real_bathtub_modellonet"]
    assert bathtub.benchmark.name == "modelnet_real_bathtub" and bathtub.output_dir == "outputs/grid/modelnet_real_bathtub"
    same = ("methods", "samplings", "partials", "max_pairs", "max_pairs_by_method")
    assert {k: bathtub.benchmark[k] for k in same} == {k: airplane.benchmark[k] for k in same}
    assert bathtub.method_options == airplane.method_options and bathtub.data.dataset == "modelnet40_resampled"


def _by_hand(cache_root: Path, partial: str, method_pred) -> dict[str, float]:
    """The same pairs through src's own data path, registered here, scored with RegistrationMetrics."""
    import hydra

    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("config", overrides=["+exp=unseen_shapes", "sampling=ts", f"partial={partial}", "data=synthetic",
                                           *TINY_DATA, f"data.cache_root={cache_root}"])
    dm = hydra.utils.instantiate(cfg.data)
    dm.setup("test")
    metric = RegistrationMetrics("zyx" if partial == "prnet" else "xyz")
    for i in range(3):
        s = dm.datasets["test"][i]
        pred = torch.tensor(np.asarray(method_pred(s["points_src"].numpy(), s["points_ref"].numpy())), dtype=torch.float64)
        metric.update(pred[None], s["transform_gt"][None], s["points_src"][None], s["points_ref"][None])
    return metric.compute()


def test_grid_tidy_frame_matches_metrics_by_hand_and_flags_failures(tmp_path, cache_root):
    result = grid_run.run_grid(grid_cfg(tmp_path / "out", cache_root))
    tidy = result.tidy
    for column in ("method", "experiment", "sampling", "partial", "metric", "value", "n_pairs", "n_failed", "seconds"):
        assert column in tidy.columns
    assert set(tidy["method"]) == {"ICP", "toy"} and set(tidy["partial"]) == {"prnet", "rpmnet"}
    assert set(tidy["metric"]) == set(METRIC_NAMES) and len(tidy) == 4 * len(METRIC_NAMES)
    assert (tidy["n_pairs"] == 3).all() and (tidy["dataset"] == "synthetic").all()

    icp = get_registrator("icp")
    for partial in ("prnet", "rpmnet"):
        expected = _by_hand(cache_root, partial, icp.register)
        got = tidy[(tidy["method"] == "ICP") & (tidy["partial"] == partial)].set_index("metric")["value"]
        for name, value in expected.items():
            assert got[name] == pytest.approx(value, rel=1e-6, abs=1e-9), (partial, name)
    # toy: RPMNet-manner pairs registered by centroid translation, PRNet-manner pairs all failed -> identity
    toy = tidy[tidy["method"] == "toy"]
    ok = toy[toy["partial"] == "rpmnet"].set_index("metric")["value"]
    expected = _by_hand(cache_root, "rpmnet", ToyRegistrator().register)
    assert all(ok[k] == pytest.approx(v, rel=1e-6, abs=1e-9) for k, v in expected.items())
    failed = toy[toy["partial"] == "prnet"]
    assert (failed["n_failed"] == 3).all() and (toy[toy["partial"] == "rpmnet"]["n_failed"] == 0).all()
    identity = _by_hand(cache_root, "prnet", lambda s, r: np.eye(4))
    assert failed.set_index("metric")["value"]["Error(R)"] == pytest.approx(identity["Error(R)"], rel=1e-9)

    pairs = pd.read_parquet(tmp_path / "out" / "pairs.parquet")
    assert len(pairs) == 12 and {"pair", "transform", "seconds", "failed", "reason", "Error(R)", "Error(t)"} <= set(pairs.columns)
    bad = pairs[pairs["failed"]]
    assert len(bad) == 3 and set(bad["method"]) == {"toy"} and bad["reason"].str.contains("toy failure").all()
    assert all(np.allclose(np.reshape(t, (4, 4)), np.eye(4)) for t in bad["transform"])
    assert sorted(pairs[pairs["method"] == "icp"]["pair"]) == [0, 0, 1, 1, 2, 2]
    assert (tmp_path / "out" / "results.parquet").is_file() and (tmp_path / "out" / "results.csv").is_file()
    assert (tmp_path / "out" / "table.md").is_file() is False  # written by report(), not run_grid
    grid_report(result, grid_cfg(tmp_path / "out", cache_root))
    assert (tmp_path / "out" / "table.tex").is_file()
    _, written = markdown_table((tmp_path / "out" / "table.md").read_text())
    table = build_table(result.tidy, "table1")  # the grid's tidy frame in the paper's layout (no paper rows here)
    assert written["Method"].tolist() == [name for block in table.blocks
                                          for name in [f"***{block.label}***", *(row.label for row in block.rows)]]
    body = [cells for cells in written.values.tolist() if not cells[0].startswith("***")]
    for cells, row in zip(body, [row for block in table.blocks for row in block.rows]):  # bold/underline aside
        assert [re.sub(r"^\*\*(.*)\*\*$|^<u>(.*)</u>$", r"\1\2", cell) for cell in cells[1:]] == [
            fmt(value, metric) for value, (metric, _) in zip(row.values, table.columns)]
    icp = tidy[(tidy["method"] == "ICP") & (tidy["partial"] == "prnet")].set_index("metric")["value"]
    column = 1 + table.columns.index(("Error(R)", "TS"))
    assert body[0][0] == "ICP" and body[0][column] == f"**{fmt(icp['Error(R)'], 'Error(R)')}**"  # the tidy number, best


def test_rerun_reuses_finished_cells(tmp_path, cache_root, monkeypatch):
    cfg = grid_cfg(tmp_path / "out", cache_root, "benchmark.methods=[toy]", "benchmark.partials=[rpmnet]")
    first = grid_run.run_grid(cfg)
    assert (first.computed, first.reused) == (1, 0)
    cell_files = sorted((tmp_path / "out" / "cells").iterdir())
    mtimes = {p: p.stat().st_mtime_ns for p in cell_files}

    calls = []
    real_register = grid_run.register_cells
    monkeypatch.setattr(grid_run, "register_cells", lambda cells, c: calls.extend(x.key for x in cells) or real_register(cells, c))
    second = grid_run.run_grid(cfg)
    assert (second.computed, second.reused) == (0, 1) and calls == []
    assert {p: p.stat().st_mtime_ns for p in cell_files} == mtimes
    pd.testing.assert_frame_equal(first.tidy, second.tidy)

    # anything that defines a cell (here: the number of pairs) makes a new cell; the old one stays
    third = grid_run.run_grid(grid_cfg(tmp_path / "out", cache_root, "benchmark.methods=[toy]", "benchmark.partials=[rpmnet]",
                                   "benchmark.max_pairs=2"))
    assert (third.computed, third.reused) == (1, 0) and calls == ["toy/unseen_shapes/ts/rpmnet"]
    assert len(list((tmp_path / "out" / "cells").glob("*.json"))) == 2
    # an interrupted cell (parquet without its JSON) is recomputed
    json_file = next(p for p in cell_files if p.suffix == ".json")
    json_file.unlink()
    fourth = grid_run.run_grid(cfg)
    assert (fourth.computed, fourth.reused) == (1, 0)
    assert json.loads(json_file.read_text())["complete"] is True


def test_an_interrupted_call_resumes_from_the_pairs_it_saved(tmp_path, cache_root, monkeypatch, capsys):
    """A long call (Go-ICP: an hour a cell) interrupted near its end registered every pair again."""
    whole = grid_run.run_grid(grid_cfg(tmp_path / "whole", cache_root, "benchmark.methods=[toy]"))
    cfg = grid_cfg(tmp_path / "out", cache_root, "benchmark.methods=[toy]", "save_every_s=1e-9")
    monkeypatch.setattr(grid_run, "FIRST_CHUNK_PAIRS", 1)
    registered, real_register = [], grid_run.register

    def register_until(limit):
        def fake(registrator, pairs, *args):
            if len(registered) + len(pairs) > limit:
                raise KeyboardInterrupt
            registered.extend(pairs)
            return real_register(registrator, pairs, *args)
        return fake

    monkeypatch.setattr(grid_run, "register", register_until(4))
    with pytest.raises(KeyboardInterrupt):
        grid_run.run_grid(cfg)
    cells = tmp_path / "out" / "cells"
    saved = sorted(len(pd.read_parquet(p)) for p in cells.glob("*.partial.parquet"))
    assert saved == [1, 3] and not list(cells.glob("*.json"))  # 3 pairs of the first cell, 1 of the second

    registered.clear()
    monkeypatch.setattr(grid_run, "register", register_until(2))
    resumed = grid_run.run_grid(cfg)
    assert len(registered) == 2 and resumed.computed == 2 and not list(cells.glob("*.partial.parquet"))
    kept = ["method", "experiment", "partial", "pair", "transform", "failed", "reason", "Error(R)"]
    pd.testing.assert_frame_equal(whole.pairs[kept], resumed.pairs[kept])
    assert resumed.pairs["failed"].sum() == 3  # the toy's failures (PRNet manner) came back from the saved pairs

    # a damaged progress file is one warning line, its pairs registered again
    monkeypatch.setattr(grid_run, "register", register_until(10))
    summary = next(cells.glob("*.json"))
    summary.unlink()
    summary.with_suffix(".partial.parquet").write_bytes(b"not parquet")
    capsys.readouterr()
    registered.clear()
    grid_run.run_grid(cfg)
    assert len(registered) == 3 and "is damaged" in capsys.readouterr().err


def test_damaged_cell_file_is_recomputed_with_a_warning(tmp_path, cache_root, capsys):
    cfg = grid_cfg(tmp_path / "out", cache_root, "benchmark.methods=[toy]", "benchmark.partials=[rpmnet]")
    first = grid_run.run_grid(cfg)
    parquet = next((tmp_path / "out" / "cells").glob("*.parquet"))
    parquet.write_bytes(parquet.read_bytes()[: parquet.stat().st_size // 2])  # e.g. a disk filled up mid-copy
    capsys.readouterr()
    second = grid_run.run_grid(cfg)
    assert (second.computed, second.reused) == (1, 0)
    warning = capsys.readouterr().err.strip().splitlines()
    assert len(warning) == 1 and warning[0].startswith("warning: cell toy/unseen_shapes/ts/rpmnet: ")
    assert parquet.name in warning[0] and "recomputing it" in warning[0]
    timing = ["seconds", "seconds_per_pair"]
    pd.testing.assert_frame_equal(first.tidy.drop(columns=timing), second.tidy.drop(columns=timing))
    assert len(pd.read_parquet(parquet)) == 3


def test_a_grid_of_the_users_methods_keeps_the_identity_row(tmp_path, cache_root):
    cfg = grid_cfg(tmp_path / "out", cache_root, "benchmark.methods=[toy]", "benchmark.partials=[rpmnet]",
                   "benchmark.reference=identity")
    result = grid_run.run_grid(cfg)
    assert sorted(c["method"] for c in result.cells) == ["identity", "toy"]
    identity = result.tidy[(result.tidy["method_id"] == "identity") & (result.tidy["metric"] == "Error(R)")]["value"]
    assert float(identity.iloc[0]) == pytest.approx(_by_hand(cache_root, "rpmnet", lambda s, r: np.eye(4))["Error(R)"])


def test_exclude_and_per_method_limits(tmp_path, cache_root):
    cfg = grid_cfg(tmp_path / "out", cache_root, "benchmark.exclude=[toy/*/*/prnet]", "+benchmark.max_pairs_by_method.icp=2")
    result = grid_run.run_grid(cfg)
    cells = {(c["method"], c["partial"]): c["n_pairs"] for c in result.cells}
    assert cells == {("icp", "prnet"): 2, ("icp", "rpmnet"): 2, ("toy", "rpmnet"): 3}


def test_clear_errors(tmp_path, cache_root):
    with pytest.raises(ConfigError, match="unknown registration method 'nosuch'; available: .*icp"):
        grid_run.run_grid(grid_cfg(tmp_path, cache_root, "benchmark.methods=[icp,nosuch]"))
    with pytest.raises(ConfigError, match="unknown experiment 'unseen_planets'; available: .*unseen_shapes"):
        grid_run.run_grid(grid_cfg(tmp_path, cache_root, "benchmark.experiments=[unseen_planets]"))
    with pytest.raises(CheckpointError, match="needs a checkpoint: set method_options.omnet.checkpoint"):
        grid_run.run_grid(grid_cfg(tmp_path, cache_root, "benchmark.methods=[omnet]"))
    with pytest.raises(CheckpointError, match="does not exist"):
        grid_run.run_grid(grid_cfg(tmp_path, cache_root, "benchmark.methods=[omnet]", f"method_options.omnet.checkpoint={tmp_path}/x.ckpt"))
    with pytest.raises(DatasetError, match="src.data.prepare modelnet40"):
        grid_run.run_grid(grid_cfg(tmp_path, cache_root, "data=modelnet40", tiny=False))
    with pytest.raises(ConfigError, match=r"data.pair.prnet_num_keep=2 is invalid: it must be an integer >= 3"):
        grid_run.run_grid(grid_cfg(tmp_path, cache_root, "benchmark.partials=[prnet]", data_overrides=("data.pair.prnet_num_keep=2",)))
    with pytest.raises(ConfigError, match=r"data.pair.noise_sigma=-1 is invalid: it must be a number >= 0"):
        grid_run.run_grid(grid_cfg(tmp_path, cache_root, data_overrides=("data.pair.noise_sigma=-1",)))
    assert not (tmp_path / "cells").exists()  # nothing ran


def test_degenerate_test_pair_is_named():
    sample = {"points_src": torch.ones(5, 3), "points_ref": torch.rand(5, 3), "transform_gt": torch.eye(4)}
    test_set = TestSet("unseen_shapes", "ts", "prnet", None, [sample], {})
    with pytest.raises(PointCloudError, match="unseen_shapes/ts/prnet, pair 0: points_src: degenerate cloud"):
        test_set.pairs(1)


def test_command_line_error_is_one_line(tmp_path, monkeypatch, capsys):
    """The Hydra app itself (run in-process: a subprocess costs ~15 s of imports on a loaded 2-core box)."""
    monkeypatch.setenv("OMNET_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(sys, "argv", ["benchmarks.grid", "benchmark.methods=[icp,nosuch]", f"output_dir={tmp_path}"])
    with pytest.raises(SystemExit) as exit_info:
        grid_main()
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith("error: unknown registration method 'nosuch'; available:")


def test_pending_cells_share_one_call_per_method_up_to_pairs_per_call():
    a, b = object(), object()
    cells = [Cell("icp", None, a, n, {}, f"{i}", Path(".")) for i, n in enumerate((50, 50, 50))]
    cells.insert(1, Cell("fgr", None, b, 10, {}, "x", Path(".")))
    calls = grid_run._calls(cells, 120)
    assert [[c.digest for c in call] for call in calls] == [["0", "1"], ["2"], ["x"]]
    assert len(grid_run._calls(cells, None)) == 2


def _edit_summary(path: Path, edit) -> None:
    summary = json.loads(path.read_text())
    edit(summary)
    path.write_text(json.dumps(summary, indent=2))


def _edit_pairs(path: Path) -> None:
    frame = pd.read_parquet(path)
    frame["Error(R)"] = 0.0  # a better number, rewritten as a valid parquet file
    frame.to_parquet(path, index=False)


@pytest.mark.parametrize(("change", "problem"), [
    (lambda cell: _edit_summary(cell.with_suffix(".json"), lambda s: s["metrics"].update({"Error(R)": 0.0})),
     "{json} was changed after it was written (its numbers do not match the checksum written with them)"),
    (lambda cell: _edit_pairs(cell.with_suffix(".parquet")),
     "{parquet} was changed after it was written (its sha256 is not the one {json} records)"),
    (lambda cell: _edit_summary(cell.with_suffix(".json"), lambda s: s.pop("checksum")),
     "{json} cannot be verified (written without a checksum, by an earlier version)"),
], ids=["summary_edited", "pairs_rewritten", "no_checksum"])
def test_a_cell_whose_files_do_not_prove_intact_is_recomputed(tmp_path, cache_root, capsys, change, problem):
    """A finished cell's file changed after it was written was reused, its number ranked."""
    cfg = grid_cfg(tmp_path / "out", cache_root, "benchmark.methods=[toy]", "benchmark.partials=[rpmnet]")
    first = grid_run.run_grid(cfg)
    cell = next((tmp_path / "out" / "cells").glob("*.json")).with_suffix("")
    change(cell)
    capsys.readouterr()
    second = grid_run.run_grid(cfg)
    assert (second.computed, second.reused) == (1, 0)
    shown = problem.format(json=cell.with_suffix(".json").name, parquet=cell.with_suffix(".parquet").name)
    assert capsys.readouterr().err.splitlines() == [
        f"warning: cell toy/unseen_shapes/ts/rpmnet: {shown}; recomputing it"]
    timing = ["seconds", "seconds_per_pair"]
    pd.testing.assert_frame_equal(first.tidy.drop(columns=timing), second.tidy.drop(columns=timing))
    assert (grid_run.run_grid(cfg).computed, capsys.readouterr().err) == (0, "")  # the recomputed cell proves intact
