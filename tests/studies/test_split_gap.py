"""benchmarks.studies.diagnostics.split_gap: the validation and test pairs of an experiment, each method's mean and interval on both."""

import numpy as np
import pytest

from baselines.testing import rotation_error_deg, translation_error
from benchmarks.studies.diagnostics import split_gap
from src.data.prepare import prepare
from src.utils.paths import shared_path
from tests.helpers.registration_helpers import compose_config

ZIP = shared_path("data", "modelnet40_normal_resampled_airplane.zip")


def test_the_bootstrap_interval_holds_the_mean_and_is_a_point_for_a_constant():
    values = np.random.default_rng(1).exponential(size=100)
    low, high = split_gap.bootstrap_mean(values)
    assert low < values.mean() < high and high - low < 4 * values.std() / 10
    assert split_gap.bootstrap_mean(values) == (low, high)  # seeded
    assert split_gap.bootstrap_mean(np.full(50, 3.0)) == (3.0, 3.0)


@pytest.mark.shared_data("data/modelnet40_normal_resampled_airplane.zip")
def test_both_splits_are_the_datamodules_and_identity_scores_their_true_poses(tmp_path, capsys):
    import hydra

    prepare("modelnet40_resampled", source=[ZIP], cache_root=tmp_path, limit=6, workers=1)
    overrides = [f"data.cache_root={tmp_path}", "test_size=3", "val_size=1"]  # 2 train, 1 val (x val_repeat), 3 test
    pairs = split_gap.split_pairs("real_airplane", "ts", "prnet", overrides)
    cfg = compose_config("+exp=real_airplane", "sampling=ts", "partial=prnet", *overrides)
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("fit")
    datamodule.setup("test")
    for split in ("val", "test"):
        assert len(pairs[split]) == len(datamodule.datasets[split])
        for (src, ref, gt), item in zip(pairs[split], datamodule.datasets[split]):
            np.testing.assert_array_equal(src, item["points_src"].numpy())
            np.testing.assert_array_equal(gt, item["transform_gt"].numpy())
    rows = split_gap.gap_table(["identity"], pairs, "prnet", workers=0)
    assert [(r["split"], r["pairs"]) for r in rows] == [("val", len(pairs["val"])), ("test", 3)]
    for row in rows:
        truth = [(rotation_error_deg(np.eye(4), gt), translation_error(np.eye(4), gt)) for *_, gt in pairs[row["split"]]]
        assert row["Error(R)"] == pytest.approx(np.mean([r for r, _ in truth]), rel=1e-5)
        assert row["Error(t)"] == pytest.approx(np.mean([t for _, t in truth]), rel=1e-5)
    out = tmp_path / "gap.md"
    assert split_gap.main(["--methods", "identity", "--workers", "0", "--out", str(out),
                           *[f"--override={o}" for o in overrides]]) == 0
    assert "| identity | test    |       3 |" in out.read_text()
    assert out.read_text().startswith("`python -m benchmarks.studies.diagnostics.split_gap --methods identity --workers 0 --out ")
    assert split_gap.main(["--methods", "identity", "--checkpoint", "idam", *[f"--override={o}" for o in overrides]]) == 2
    assert capsys.readouterr().err.endswith("error: --checkpoint expects METHOD=PATH, got 'idam'\n")


@pytest.mark.shared_data("data/modelnet40_normal_resampled_airplane.zip")
def test_training_pairs_are_fixed_pairs_of_the_first_training_shapes(tmp_path, capsys):
    import hydra

    prepare("modelnet40_resampled", source=[ZIP], cache_root=tmp_path, limit=8, workers=1)
    overrides = [f"data.cache_root={tmp_path}", "test_size=3", "val_size=1"]  # 4 train, 1 val (x val_repeat), 3 test
    pairs = split_gap.split_pairs("real_airplane", "ts", "prnet", overrides, train_shapes=3)
    assert list(pairs) == ["train", "val", "test"] and len(pairs["train"]) == 3
    for without, with_train in zip(split_gap.split_pairs("real_airplane", "ts", "prnet", overrides)["test"], pairs["test"]):
        np.testing.assert_array_equal(without[0], with_train[0])  # the other splits are what they were
    cfg = compose_config("+exp=real_airplane", "sampling=ts", "partial=prnet", *overrides)
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("fit")
    train = datamodule.datasets["train"]
    fixed = split_gap.fixed_training_pairs(train, 3)
    assert list(fixed.shape_indices) == list(train.shape_indices[:3])
    assert not set(fixed.shape_indices) & set(datamodule.datasets["val"].shape_indices)
    for (src, _, gt), item in zip(pairs["train"], fixed):
        np.testing.assert_array_equal(src, item["points_src"].numpy())
        np.testing.assert_array_equal(gt, item["transform_gt"].numpy())
    epoch_draw = train[0]["transform_gt"].numpy()  # the training stream draws other poses of the same shape
    assert not np.array_equal(epoch_draw, pairs["train"][0][2])
    assert split_gap.main(["--methods", "identity", "--workers", "0", "--train-shapes", "9",
                           *[f"--override={o}" for o in overrides]]) == 2
    assert capsys.readouterr().err.endswith("error: --train-shapes must be between 1 and the 4 training shapes, got 9\n")
