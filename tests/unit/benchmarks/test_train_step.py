"""benchmarks.speed.train_step: the training-step timing table (a tiny OMNet on the CPU)."""

import pandas as pd

from benchmarks.speed.inference import format_rate
from benchmarks.speed.train_step import main, pair_batch
from tests.helpers.markdown import markdown_table

COLUMNS = ["# points", "precision", "compile", "ms/step (median)", "pairs/s", "vs eager fp32", "GFLOP/s", "% of mm"]


def test_train_step_table(tmp_path, capsys):
    code = main(["--device", "cpu", "--batch", "2", "--points", "48,64", "--model-scale", "0.0625", "--steps", "2",
                 "--warmup", "1", "--compile", "none", "--out", str(tmp_path)])
    assert code == 0
    frame = pd.read_csv(tmp_path / "train_step.csv")
    assert list(zip(frame["points"], frame["precision"])) == [(48, "fp32"), (48, "bf16"), (64, "fp32"), (64, "bf16")]
    assert (frame["ms_per_step"] > 0).all() and (frame["steps"] == 2).all()
    assert (frame["gflop_per_step"] > 0).all() and (frame["pct_of_mm"] > 0).all()
    assert frame.loc[2, "gflop_per_step"] > frame.loc[0, "gflop_per_step"]  # 64 points: more products than 48
    title, table = markdown_table((tmp_path / "train_step.md").read_text(), "Training step of")
    assert "batch 2 — CPU:" in title and table.columns.tolist() == COLUMNS
    assert table[["# points", "precision", "compile"]].values.tolist() == [
        [str(p), precision, "none"] for p, precision in zip(frame["points"], frame["precision"])]
    assert table["ms/step (median)"].tolist() == [f"{ms:.1f}" for ms in frame["ms_per_step"]]  # the CSV's numbers
    assert table["pairs/s"].tolist() == [format_rate(rate) for rate in frame["pairs_per_s"]]
    assert table["% of mm"].tolist() == [f"{pct:.0f}" for pct in frame["pct_of_mm"]]
    assert table.loc[table["precision"] == "fp32", "vs eager fp32"].tolist() == ["1.00×", "1.00×"]
    assert main(["--device", "cpu", "--precisions", "fp16", "--out", str(tmp_path)]) == 2
    assert "unknown precision 'fp16'" in capsys.readouterr().err


def test_pair_batch_is_rigid_and_seeded():
    import torch

    first, again = pair_batch(3, 40, torch.device("cpu")), pair_batch(3, 40, torch.device("cpu"))
    assert first["points_src"].shape == (3, 40, 3) and first["transform_gt"].shape == (3, 4, 4)
    assert all(torch.equal(first[k], again[k]) for k in first)
    rotation = first["transform_gt"][:, :3, :3]
    assert torch.allclose(rotation @ rotation.transpose(1, 2), torch.eye(3).expand(3, 3, 3), atol=1e-5)


def test_a_failing_configuration_is_recorded_not_fatal(tmp_path, monkeypatch):
    import benchmarks.speed.train_step as train_step

    real = train_step.time_steps

    def flaky(network, batch, precision, *args):
        if precision == "bf16":
            raise FloatingPointError("non-finite loss (nan) or gradients (3 tensors) under bf16")
        return real(network, batch, precision, *args)

    monkeypatch.setattr(train_step, "time_steps", flaky)
    assert main(["--device", "cpu", "--batch", "2", "--points", "48", "--model-scale", "0.0625", "--steps", "1",
                 "--warmup", "0", "--compile", "none", "--out", str(tmp_path)]) == 0
    frame = pd.read_csv(tmp_path / "train_step.csv").set_index("precision")
    assert frame.loc["fp32", "ms_per_step"] > 0 and pd.isna(frame.loc["bf16", "ms_per_step"])
    _, table = markdown_table((tmp_path / "train_step.md").read_text(), "Training step of")
    failed = table.set_index("precision").loc["bf16"]
    assert failed["# points"] == "48" and failed["compile"] == "none"
    assert failed["ms/step (median)"].startswith("failed: FloatingPointError: non-finite loss")
    assert failed[COLUMNS[4:]].tolist() == ["-"] * 4


def test_profile_writes_the_operators_with_the_most_cpu_time(tmp_path):
    assert main(["--device", "cpu", "--batch", "2", "--points", "48", "--model-scale", "0.0625", "--steps", "1",
                 "--warmup", "0", "--precisions", "fp32", "--compile", "none", "--profile", "5", "--out", str(tmp_path)]) == 0
    table = (tmp_path / "profile_48_fp32_none.txt").read_text()
    assert "Self CPU" in table and "aten::" in table
