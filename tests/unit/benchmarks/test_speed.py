"""benchmarks.speed: the paper-shaped speed table for a toy method (and an untrained tiny network)."""

import pandas as pd

import benchmarks.speed.inference as speed
from src.utils.machine_speed import MatmulReference
from baselines import register_registrator
from baselines.testing import ToyRegistrator
from tests.helpers.markdown import markdown_table, markdown_tables

register_registrator("toy", ToyRegistrator)


def test_speed_table_for_a_toy_method_at_two_sizes(tmp_path, capsys):
    code = speed.main(["--methods", "toy", "--sizes", "32,64", "--repeats", "3", "--warmup", "1", "--devices", "cpu",
                       "--out", str(tmp_path), "--no-progress", "--no-paper"])
    assert code == 0
    frame = pd.read_csv(tmp_path / "speed.csv")
    assert list(frame["points"]) == [32, 64] and set(frame["method"]) == {"toy"} and set(frame["device"]) == {"cpu"}
    assert (frame["runs"] == 3).all() and (frame["ms_per_pair"] > 0).all() and (frame["weights"] == "none").all()
    markdown = (tmp_path / "speed.md").read_text()
    title, table = markdown_table(markdown, "Speed (ms per pair, median)")
    assert table.columns.tolist() == ["# points", "toy"] and table["# points"].tolist() == ["32", "64"]
    assert table["toy"].tolist() == [speed._fmt_ms(ms) for ms in frame["ms_per_pair"]]  # the CSV's numbers
    assert "CPU:" in title and "median over 3" in markdown  # the device; the notes under the table
    assert markdown_tables(capsys.readouterr().out)[0][1].equals(table)  # printed too


def test_untrained_network_is_labelled(tmp_path):
    code = speed.main(["--methods", "toy,omnet", "--sizes", "32", "--repeats", "1", "--warmup", "0", "--devices", "cpu",
                       "--model-scale", "0.0625", "--out", str(tmp_path), "--no-progress", "--no-paper"])
    assert code == 0
    frame = pd.read_csv(tmp_path / "speed.csv").set_index("method_id")
    assert frame.loc["omnet", "weights"] == "untrained" and frame.loc["omnet", "method"] == "OMNet (untrained)"
    markdown = (tmp_path / "speed.md").read_text()
    _, table = markdown_table(markdown, "Speed (ms per pair, median)")
    assert table.columns.tolist() == ["# points", "toy", "OMNet†"] and "† freshly initialised weights" in markdown
    assert table.loc[0, "OMNet†"] == speed._fmt_ms(frame.loc["omnet", "ms_per_pair"])


def test_speed_errors_are_one_line(tmp_path, capsys):
    assert speed.main(["--methods", "nosuch", "--out", str(tmp_path), "--no-progress"]) == 2
    assert capsys.readouterr().err.strip().startswith("error: unknown registration method 'nosuch'")
    assert speed.main(["--methods", "omnet", "--checkpoint", f"omnet={tmp_path}/none.ckpt", "--devices", "cpu",
                       "--out", str(tmp_path), "--no-progress"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_batched_throughput_table_for_a_network(tmp_path):
    code = speed.main(["--methods", "toy,omnet", "--sizes", "32,48", "--batch-sizes", "1,4", "--repeats", "2",
                       "--warmup", "1", "--devices", "cpu", "--precision", "bf16", "--model-scale", "0.0625",
                       "--out", str(tmp_path), "--no-progress", "--no-paper"])
    assert code == 0
    frame = pd.read_csv(tmp_path / "speed.csv")
    assert sorted(frame.loc[frame["method_id"] == "omnet", "batch"]) == [1, 1, 4, 4]
    assert (frame.loc[frame["method_id"] == "toy", "batch"] == 1).all()  # classical methods: one pair per call
    assert ((frame["pairs_per_s"] - 1000.0 / frame["ms_per_pair"]).abs() < 1e-6 * frame["pairs_per_s"]).all()
    markdown = (tmp_path / "speed.md").read_text()
    _, table = markdown_table(markdown, "Speed (ms per pair, median)")
    assert table.columns.tolist() == ["# points", "toy", "OMNet [bf16]†"] and table["# points"].tolist() == ["32", "48"]
    _, throughput = markdown_table(markdown, "Throughput (pairs per second)")
    omnet = frame[frame["method_id"] == "omnet"]
    label = omnet["method"].iloc[0]
    assert label == "OMNet (untrained) [bf16]"
    assert throughput.columns.tolist() == ["# points", f"{label} B=1", f"{label} B=4"]
    for batch in (1, 4):
        rates = omnet[omnet["batch"] == batch].sort_values("points")["pairs_per_s"]
        assert throughput[f"{label} B={batch}"].tolist() == [speed.format_rate(r) for r in rates]
    network = frame[frame["method_id"] == "omnet"]
    assert (network["gflop_per_call"] > 0).all() and (network["pct_of_mm"] > 0).all() and (network["mm_gflop_per_s"] > 0).all()
    assert frame.loc[frame["method_id"] == "toy", "gflop_per_s"].isna().all()  # no network: no FLOPs counted
    _, limit = markdown_table(markdown, "Distance to the limit")
    assert limit.columns.tolist() == ["# points", f"{label} B=1", f"{label} B=4"]
    for batch in (1, 4):
        cells = omnet[omnet["batch"] == batch].sort_values("points")
        assert limit[f"{label} B={batch}"].tolist() == [
            f"{rate:.1f} ({pct:.0f} %)" for rate, pct in zip(cells["gflop_per_s"], cells["pct_of_mm"])]


def test_flops_are_the_matrix_products_of_a_call():
    import torch

    x, w = torch.randn(5, 7), torch.randn(3, 7)
    assert speed.count_flops(lambda: torch.nn.functional.linear(x, w)) == 2 * 5 * 7 * 3
    assert speed.count_flops(lambda: x.relu()) == 0
    assert MatmulReference("cpu", clock="cpu").rate() > 0


def test_batch_flops_scale_with_the_batch(tmp_path):
    code = speed.main(["--methods", "omnet", "--sizes", "32", "--batch-sizes", "1,3", "--repeats", "1", "--warmup", "0",
                       "--devices", "cpu", "--model-scale", "0.0625", "--clock", "cpu", "--out", str(tmp_path),
                       "--no-progress", "--no-paper"])
    assert code == 0
    flops = pd.read_csv(tmp_path / "speed.csv").set_index("batch")["gflop_per_call"]
    assert abs(flops[3] - 3 * flops[1]) < 0.05 * flops[3]  # untrained: every point kept (masks all ones)
    assert "process's CPU time" in (tmp_path / "speed.md").read_text()


def test_default_methods_and_columns_come_from_the_registry():
    from baselines.methods import METHODS, get_method

    defaults = speed.default_methods()
    assert defaults == [m.key for m in METHODS if (m.default_grid or m.kind == "learned") and not m.slow]
    assert "goicp" not in defaults and "goicp" in [m.key for m in METHODS if m.default_grid]  # the paper times no Go-ICP
    columns = [get_method(m) for m in sorted(reversed(defaults), key=speed._column_order)]
    positions = [m.speed for m in columns if m.speed is not None]
    assert positions == sorted(positions) and columns[-1].ours  # the registry's speed order, OMNet last
