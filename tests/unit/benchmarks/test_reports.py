"""benchmarks.tables.paper / tables / plots / collect on hand-made frames (no training; a few seconds).

The paper-table fixture holds made-up numbers in the paper's CSV format; the real tables are only
read (if present) to check that they load."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from benchmarks.collect import collect
from benchmarks.grid.report import report
from benchmarks.grid.run import run_grid
from benchmarks.tables.latex_check import check_latex, count_columns, tabular_rows, tabulars
from benchmarks.tables.paper import attach_paper, load_paper_tables, method_key, protocol_mismatch
from benchmarks.plots.sweep import FIGURES, NO_PAPER_NUMBERS, figure_data, make_figures, main as plots_main
from benchmarks.tables.render import build_table, fmt, main as tables_main, to_latex, to_markdown
from src.utils.paths import REPO_ROOT, shared_path
from tests.helpers.markdown import markdown_table, markdown_tables
from tests.helpers.scan_helpers import write_scan_set

METRICS = ("RMSE(R)", "MAE(R)", "RMSE(t)", "MAE(t)", "Error(R)", "Error(t)")
REAL_PAPER_DIR = shared_path("reference", "paper_tables")


@pytest.fixture
def paper_dir(tmp_path) -> Path:
    """Two fake paper tables in the paper's tidy format (values invented for the test)."""
    folder = tmp_path / "paper"
    folder.mkdir()
    rows = []
    for experiment in ("unseen_shapes", "gaussian_noise"):
        for method in ("ICP", "OMNet"):
            for sampling in ("OS", "TS"):
                for k, metric in enumerate(METRICS):
                    rows.append(("main_prnet_partial", experiment, method, sampling, metric, 2.0 + k))
    pd.DataFrame(rows, columns=["table", "experiment", "method", "sampling", "metric", "value"]).to_csv(folder / "t1.csv", index=False)
    rows = [("ablation", "unseen_shapes_noise", name, "TS", metric, 4.0)
            for name in ("B", "B+M+ML+F+C", "Top-k, k=100", "$\\lambda$=0.5") for metric in METRICS]
    pd.DataFrame(rows, columns=["table", "experiment", "method", "sampling", "metric", "value"]).to_csv(folder / "t3.csv", index=False)
    pd.DataFrame({"points": [512], "method": ["ICP"], "ms_per_pair": [1]}).to_csv(folder / "speed.csv", index=False)
    return folder


def _frame(methods, experiments=("unseen_shapes",), samplings=("os", "ts"), scale=1.0, **extra) -> pd.DataFrame:
    rows = []
    for i, method in enumerate(methods):
        for experiment in experiments:
            for sampling in samplings:
                for k, metric in enumerate(METRICS):
                    rows.append(dict(method=method, experiment=experiment, sampling=sampling, partial="prnet",
                                     metric=metric, value=scale * (2.0 + k) * (1 + 0.1 * i), **extra))
    return pd.DataFrame(rows)


def test_paper_tables_load_and_normalise(paper_dir):
    paper = load_paper_tables(paper_dir)
    assert set(paper["file"]) == {"t1.csv", "t3.csv"}  # the speed table has other columns
    assert "unseen_shapes_noise" in set(paper["experiment"]) and "gaussian_noise" not in set(paper["experiment"])
    assert method_key("$\\lambda$=2.0") == method_key("lambda=2") == method_key("λ=2.0") == "lambda=2"
    assert method_key("Ours") == method_key("OMNet") and method_key("Top-k, k=100") == method_key("top-k k=100")
    if REAL_PAPER_DIR.is_dir():
        real = load_paper_tables(REAL_PAPER_DIR)
        assert {"OMNet", "B+M+ML+F+C"} <= set(real["method"]) and {"prnet", "rpmnet"} <= set(real["partial"])


def test_paper_values_only_for_the_papers_protocol(paper_dir):
    paper = load_paper_tables(paper_dir)
    ours = _frame(["OMNet"], experiments=("unseen_shapes_noise",), samplings=("ts",))
    ours["noise_sigma"], ours["num_iters"], ours["dataset"] = 0.01, 4, "modelnet40"
    merged = attach_paper(ours, paper)
    assert merged["paper_value"].notna().all() and (merged["ratio"] - merged["value"] / merged["paper_value"]).abs().max() == 0
    assert protocol_mismatch({"experiment": "unseen_shapes_noise", "noise_sigma": 0.02}).startswith("noise sigma 0.02")
    assert protocol_mismatch({"experiment": "unseen_shapes", "dataset": "synthetic"}).startswith("dataset synthetic")
    assert protocol_mismatch({"experiment": "unseen_shapes", "num_iters": 2}).startswith("N = 2")
    assert protocol_mismatch({"experiment": "unseen_shapes", "overlap_ratio": 0.5}).startswith("overlap-ratio")
    assert protocol_mismatch({"experiment": "unseen_shapes", "dataset": "synthetic"}, any_dataset=True) is None
    synthetic = attach_paper(ours.assign(dataset="synthetic"), paper)
    assert synthetic["paper_value"].isna().all() and synthetic["paper_note"].str.startswith("dataset").all()
    real = ours.assign(dataset="modelnet40_resampled", experiment="real_airplane_noisy")
    assert attach_paper(real, paper)["paper_value"].isna().all()  # other data: no paper value unless asked
    beside = attach_paper(real, paper, any_dataset=True)  # asked: the counterpart's (Table 1(c)'s) values
    assert beside["paper_value"].tolist() == merged["paper_value"].tolist()
    assert protocol_mismatch({"experiment": "real_airplane_noisy", "noise_sigma": 0.0}, any_dataset=True).startswith("noise sigma 0")


def test_table1_layout_ranks_and_paper_rows(paper_dir):
    frame = _frame(["OMNet", "ICP", "DCP"], experiments=("unseen_shapes", "gaussian_noise"))
    table = build_table(frame, "table1", paper=load_paper_tables(paper_dir))
    assert [b.label for b in table.blocks] == ["(a) Unseen shapes", "(c) Gaussian noise (unseen shapes)"]  # the paper's
    labels = [r.label for r in table.blocks[0].rows]
    assert labels == ["ICP", "paper", "ours/paper", "DCP", "OMNet", "paper", "ours/paper"]  # paper order, OMNet last
    omnet, icp = table.blocks[0].rows[4], table.blocks[0].rows[0]
    assert omnet.ranks == [1] * 12 and icp.ranks == [2] * 12  # OMNet smallest (scale 1.0), ICP second
    ratio = table.blocks[0].rows[6]
    assert ratio.kind == "ratio" and all(v == pytest.approx(1.0) for v in ratio.values)
    tex = to_latex(table)
    assert check_latex(tex) == []
    (spec, body), = tabulars(tex)
    assert count_columns(spec) == 13
    row = next(r for r in tabular_rows(body) if r[0] == "DCP")
    assert row[1] == "2.400" and row[3] == "3.600"  # RMSE(R) OS, MAE(R) OS with 3 decimals
    assert next(r for r in tabular_rows(body) if r[0] == "OMNet")[1] == "\\textbf{2.000}"
    assert "\\quad\\textit{paper} & \\textit{2.000}" in tex and "1.00$\\times$" in tex
    _, markdown = markdown_table(to_markdown(table))
    rows, metrics = table.blocks[0].rows, [metric for metric, _ in table.columns]
    body = markdown.values.tolist()[1:1 + len(rows)]  # under the block's label row
    assert markdown.iloc[0, 0] == "***(a) Unseen shapes***"
    assert [row[0] for row in body] == ["ICP", "↳ *paper*", "↳ *ours/paper*", "DCP", "OMNet", "↳ *paper*", "↳ *ours/paper*"]
    assert body[4][1:] == [f"**{fmt(v, m)}**" for v, m in zip(omnet.values, metrics)]  # rank 1: bold
    assert body[0][1:] == [f"<u>{fmt(v, m)}</u>" for v, m in zip(icp.values, metrics)]  # rank 2: underlined
    assert body[5][1:] == [f"*{fmt(v, m)}*" for v, m in zip(rows[5].values, metrics)]  # the paper's: italic
    assert (body[4][1], body[5][1], body[0][1]) == ("**2.000**", "*2.000*", "<u>2.200</u>")


def test_table2_and_table3_layouts(paper_dir):
    frame = _frame(["RPMNet", "OMNet"], experiments=("unseen_categories_noise",))
    table = build_table(frame, "table2")
    assert table.samplings == ["TS"] and len(table.columns) == 6 and table.blocks[0].label is None
    assert any("sampling ['OS']" in note for note in table.notes)
    assert check_latex(to_latex(table)) == []
    names = ["lambda=0.1", "Top-k, k=100", "B+M+ML+F+C", "B", "lambda=2.0", "Top-k, k=500", "B+M"]
    frame = _frame(names, experiments=("unseen_shapes_noise",), samplings=("ts",), noise_sigma=0.01)
    table = build_table(frame, "table3", paper=load_paper_tables(paper_dir))
    ours = [r.label for r in table.blocks[0].rows if r.kind == "ours"]
    assert ours == ["B", "B+M", "B+M+ML+F+C", "Top-k, k=500", "Top-k, k=100", "lambda=2.0", "lambda=0.1"]
    tex = to_latex(table)
    assert check_latex(tex) == [] and "$\\lambda$=2.0" in tex and tex.count("\\midrule") == 3  # header + 2 group rules
    paper_rows = [r for r in table.blocks[0].rows if r.kind == "paper"]
    assert len(paper_rows) == 3  # B, B+M+ML+F+C, Top-k k=100 (λ=0.5 is not ours)


def test_tables_cli_writes_latex_and_markdown(paper_dir, tmp_path, capsys):
    frame = _frame(["OMNet", "ICP"])
    frame.to_csv(tmp_path / "ours.csv", index=False)
    code = tables_main([str(tmp_path / "ours.csv"), "--layout", "table1", "--out", str(tmp_path / "t"), "--paper",
                        "--paper-dir", str(paper_dir), "--standalone"])
    assert code == 0
    assert (tmp_path / "t" / "table1.tex").is_file() and (tmp_path / "t" / "table1.md").is_file()
    assert "\\documentclass" in (tmp_path / "t" / "table1_standalone.tex").read_text()
    (_, printed), = markdown_tables(capsys.readouterr().out)
    _, written = markdown_table((tmp_path / "t" / "table1.md").read_text())
    assert printed.equals(written) and {"OMNet", "ICP"} <= set(written["Method"])
    assert tables_main([str(tmp_path / "ours.csv"), "--layout", "table2", "--metrics", "bogus", "--out", str(tmp_path / "t")]) == 2


def test_latex_checker_finds_broken_tables():
    good = "\\begin{tabular}{l*{2}{c}}\\toprule a & b & c \\\\ \\multicolumn{3}{l}{x} \\\\ \\bottomrule\\end{tabular}"
    assert check_latex(good) == []
    assert any("cells" in p for p in check_latex(good.replace("a & b & c", "a & b")))
    assert any("unclosed" in p for p in check_latex(good.replace("{x}", "{x")))
    assert any("closes" in p for p in check_latex("\\begin{table}\\begin{tabular}{l}a\\end{table}\\end{tabular}"))
    assert check_latex("\\begin{tabular}{lc} a \\& b & c \\\\ \\end{tabular}") == []


def _noise_frame(dataset: str) -> pd.DataFrame:
    rows = []
    for sigma in (0.0, 0.005, 0.01, 0.02, 0.04):
        for metric in ("Error(R)", "Error(t)"):
            rows.append(dict(sweep="s1", method="OMNet", experiment="unseen_shapes_noise" if sigma else "unseen_shapes",
                             dataset=dataset, sampling="ts", partial="prnet", noise_sigma=sigma, overlap_ratio=None,
                             num_iters=4, metric=metric, value=1.0 + sigma))
    for n in range(1, 4):  # an iterations sweep in the same frame (σ = 0.01 throughout)
        for metric in METRICS:
            rows.append(dict(sweep="s2", method="OMNet", experiment="unseen_shapes_noise", dataset=dataset, sampling="ts",
                             partial="prnet", noise_sigma=0.01, overlap_ratio=None, num_iters=n, metric=metric, value=1.0 / n))
    return pd.DataFrame(rows)


def test_plots_mark_paper_values_only_where_the_paper_has_them(paper_dir, tmp_path):
    paper = load_paper_tables(paper_dir)
    written, notes = make_figures(_noise_frame("modelnet40"), tmp_path / "f", paper=paper)
    names = sorted(p.name for p in written)
    assert names == ["error_vs_iterations.pdf", "error_vs_iterations.png", "error_vs_noise.pdf", "error_vs_noise.png"]
    assert "noise: paper table values marked at 4 points" in notes  # σ = 0 and 0.01, two metrics
    assert any(n.startswith("overlap: skipped") for n in notes)
    assert f"iterations: {NO_PAPER_NUMBERS}" in notes  # N = 1..3: none is the paper's N = 4
    stats = figure_data(_noise_frame("synthetic"), FIGURES["noise"], paper)
    assert len(stats) == 10 and stats["paper_value"].isna().all()  # synthetic data: never the paper's numbers


def test_collect_reads_jobs_without_hydra_files(tmp_path):
    """A single run dir (config_resolved.yaml + metrics.json) and a job killed mid-way."""
    ok, killed = tmp_path / "sweep" / "0", tmp_path / "sweep" / "1"
    for job in (ok, killed):
        job.mkdir(parents=True)
        (job / "config_resolved.yaml").write_text(
            "task_name: t\nsampling: ts\npartial: prnet\nvariant: null\nseed: 1\n"
            "data: {dataset: synthetic, splits: {train: {split: train, categories: half1}, test: {split: test, categories: half2}},"
            " pair: {noise_sigma: 0.01, overlap_ratio: null}}\n"
            "model: {network: {_target_: src.models.omnet.OMNet, num_iters: 4, trans_loss_weight: 4.0}}\n")
    (ok / "metrics.json").write_text(json.dumps({"task": "t", "metrics": {"Error(R)": 1.5, "Error(t)": 0.1}}))
    result = collect(tmp_path / "sweep")
    assert result.jobs.set_index("job")["status"].to_dict() == {"0": "ok", "1": "missing"}
    row = result.tidy.iloc[0]
    assert (row["method"], row["experiment"], row["dataset"], row["num_iters"]) == ("OMNet", "unseen_categories_noise", "synthetic", 4)
    assert result.tidy.shape[0] == 2 and result.expected is None


def test_iteration_plot_points(paper_dir, tmp_path):
    """(companion of the plot test) N = 4 is the paper's setting: with it in the frame it is marked."""
    frame = _noise_frame("modelnet40")
    extra = frame[frame["sweep"] == "s2"].copy()
    extra = extra[extra["num_iters"] == 3].assign(num_iters=4, value=0.2)
    stats = figure_data(pd.concat([frame, extra]), FIGURES["iterations"], load_paper_tables(paper_dir))
    assert sorted(stats.loc[stats["paper_value"].notna(), "num_iters"].unique()) == [4]
    assert stats["paper_value"].notna().sum() == 6


def test_scan_pairs_table_and_plot_bin_a_grid_by_overlap(tmp_path, capsys):
    """+benchmark=scan_pairs on a tiny generated scan set: overlaps 2/3, 2/3, 1/6, 1/6 (benchmarks.plots scan-pairs)."""
    data = [f"data.source={write_scan_set(tmp_path / 'scans')}", "data.pair.num_points=64",
            "data.pair.min_overlap=0.1", "data.pair.overlap_spacing=0.5"]
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("benchmark_grid", overrides=[
            "+benchmark=scan_pairs", "benchmark.methods=[identity,icp]",
            "benchmark.overrides=[" + ",".join(f'"{o}"' for o in data) + "]",
            "workers=0", "progress=false", "paper=false", f"output_dir={tmp_path / 'grid'}"])
    pairs = run_grid(cfg).pairs
    assert plots_main(["scan-pairs", str(tmp_path / "grid"), *data, "--out", str(tmp_path / "out")]) == 0
    table = capsys.readouterr().out
    report = (tmp_path / "out" / "scan_pairs_by_overlap.md").read_text()
    for metric, digits in (("Error(R)", 2), ("Error(t)", 3)):
        _, by_overlap = markdown_table(report, f"{metric}, mean")
        assert by_overlap.columns.tolist() == ["Method", "pairs", "< 50 %", "50-70 %", "> 70 %", "all"]
        assert by_overlap["Method"].tolist() == ["Identity (no registration)", "ICP"]
        for label, method in (("Identity (no registration)", "identity"), ("ICP", "icp")):
            errors = pairs[pairs["method"] == method][metric].to_numpy()  # pairs (a,b), (b,a), (b,c), (c,b)
            row = by_overlap[by_overlap["Method"] == label].iloc[0].tolist()
            assert row[1:] == ["2 / 2 / 0", f"{errors[2:].mean():.{digits}f}", f"{errors[:2].mean():.{digits}f}", "--",
                               f"{errors.mean():.{digits}f}"]
    assert (tmp_path / "out" / "scan_pairs_error_vs_overlap.png").stat().st_size > 10_000
    assert report in table  # printed as written
    other = [*data[:2], "data.pair.min_overlap=0.5", data[3]]
    assert plots_main(["scan-pairs", str(tmp_path / "grid"), *other]) == 2
    assert "ran on other pairs than scan_pairs/ts/prnet" in capsys.readouterr().err


def test_the_categories_plot_gives_each_methods_error_per_shape_category(tmp_path, capsys):
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("benchmark_grid", overrides=[
            "benchmark.methods=[identity,icp]", "benchmark.experiments=[unseen_categories]", "benchmark.samplings=[ts]",
            "benchmark.partials=[prnet]", "benchmark.max_pairs=12", "workers=0", "progress=false", "paper=false",
            "benchmark.by_category=[unseen_categories]", f"output_dir={tmp_path / 'grid'}"])
    result = run_grid(cfg)
    pairs = result.pairs
    report(result, cfg)  # the grid draws it itself for benchmark.by_category
    by_grid = (tmp_path / "grid" / "unseen_categories_ts_prnet_by_category.md").read_text()
    capsys.readouterr()
    assert plots_main(["categories", str(tmp_path / "grid"), "--sampling", "ts", "--out", str(tmp_path / "out")]) == 0
    _, table = markdown_table(capsys.readouterr().out, "Error(R), mean (degrees), per category")
    assert table.columns.tolist() == ["Category", "pairs", "Identity (no registration)", "ICP"]
    from src.pair_sets import build_test_set

    test_set = build_test_set("unseen_categories", "ts", "prnet", "synthetic", [])
    labels = test_set.dataset.labels[test_set.dataset.shape_indices[:12]]
    icp = pairs[pairs["method"] == "icp"].sort_values("pair")["Error(R)"].to_numpy()
    for category, row in table.set_index("Category").drop("all").iterrows():
        own = [test_set.categories[label] == category for label in labels]
        assert int(row["pairs"]) == sum(own) and float(row["ICP"]) == pytest.approx(icp[own].mean(), abs=0.006)
    assert int(table.set_index("Category").loc["all", "pairs"]) == 12
    assert (tmp_path / "out" / "unseen_categories_ts_prnet_by_category.png").stat().st_size > 10_000
    assert (tmp_path / "out" / "unseen_categories_ts_prnet_by_category.md").read_text() == by_grid
    assert (tmp_path / "grid" / "unseen_categories_ts_prnet_by_category.png").is_file()


def test_sub_tables_keep_the_papers_letters_unless_they_are_not_the_papers_experiments(paper_dir):
    alone = build_table(_frame(["ICP"], experiments=("unseen_categories",)), "table1", paper=load_paper_tables(paper_dir))
    assert [b.label for b in alone.blocks] == ["(b) Unseen categories"]  # Table 1(b) alone is still (b)
    other = build_table(_frame(["ICP"], experiments=("unseen_shapes", "axisymmetric_z_rotation")), "table1")
    assert [b.label for b in other.blocks] == ["(a) Unseen shapes", "(b) Axisymmetric categories, z rotations"]


def test_data_of_one_sampling_gets_its_columns_only(tmp_path):
    table = build_table(_frame(["ICP"], experiments=("unseen_categories",), samplings=("os",)), "table1", caption="Real shapes, one sampling a shape")
    assert table.samplings == ["OS"] and len(table.columns) == 6
    assert table.caption.startswith("Real shapes, one sampling a shape. Registration errors, OS columns per metric "
                                    "(layout of the paper's Table 1, OS data only)")
    assert count_columns(tabulars(to_latex(table))[0][0]) == 7


def test_real_data_table_in_the_papers_order_with_its_caption(paper_dir):
    frame = _frame(["OMNet"], experiments=("real_unseen_category", "real_airplane_noisy", "real_airplane"),
                   dataset="modelnet40_resampled", noise_sigma=0.0)
    frame.loc[frame["experiment"] == "real_airplane_noisy", "noise_sigma"] = 0.01
    table = build_table(frame, "table1", paper=load_paper_tables(paper_dir), any_dataset=True,
                        caption="Real airplanes, 1 CPU hour each.")
    assert [b.label for b in table.blocks] == ["(a) Real airplanes (the paper: unseen shapes)",
                                               "(b) Real airplanes to real bathtubs (the paper: unseen categories)",
                                               "(c) Real airplanes with Gaussian noise (the paper: Gaussian noise)"]
    paper_rows = [r for b in table.blocks for r in b.rows if r.label == "paper"]
    assert len(paper_rows) == 2  # the fixture's paper tables hold unseen shapes and its noisy counterpart only
    assert table.caption.startswith("Real airplanes, 1 CPU hour each. Registration errors")
