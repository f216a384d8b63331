"""baselines.classical.sweep: it tunes on the real airplanes' training shapes; its test-set mode draws the grid's pairs."""

import hydra
import numpy as np
import pytest

from baselines.classical import sweep
from src.data.prepare import prepare
from src.utils.paths import shared_path
from tests.helpers.registration_helpers import compose_config

ZIP = shared_path("data", "modelnet40_normal_resampled_airplane.zip")
pytestmark = pytest.mark.shared_data("data/modelnet40_normal_resampled_airplane.zip")


@pytest.fixture(scope="module")
def overrides(tmp_path_factory) -> list[str]:
    root = tmp_path_factory.mktemp("cache")
    prepare("modelnet40_resampled", source=[ZIP], cache_root=root, limit=6, workers=1)
    return [f"data.cache_root={root}", "test_size=3", "val_size=1"]  # 6 airplanes: 2 train, 1 val, 3 test


def _datamodule(overrides: list[str], stage: str):
    cfg = compose_config("+exp=real_airplane", "sampling=os", "partial=rpmnet", "data.pair.noise_sigma=0.01",
                         *overrides)
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup(stage)
    return datamodule


def _assert_same_pairs(pairs, dataset) -> None:
    for (src, ref, gt), item in zip(pairs, dataset):
        for array, name in ((src, "points_src"), (ref, "points_ref"), (gt, "transform_gt")):
            np.testing.assert_array_equal(array, item[name].numpy())


def test_the_sweep_tunes_on_training_shapes_by_default(overrides, capsys):
    key, pairs = sweep.sweep_pairs(2, "os", "rpmnet", ["data.pair.noise_sigma=0.01", *overrides])
    fit, test = _datamodule(overrides, "fit"), _datamodule(overrides, "test")
    assert key == "real_airplane/os/rpmnet (train)" and len(pairs) == 2
    _assert_same_pairs(pairs, fit.datasets["train"])
    held_out = {*fit.datasets["val"].shape_indices, *test.datasets["test"].shape_indices}
    assert not held_out & set(fit.datasets["train"].shape_indices[:2])
    assert sweep.main(["icp", "--pairs", "2", "--os", "--workers", "0", "--override", *overrides]) == 0
    out = capsys.readouterr().out
    assert "2 pairs of real_airplane/os/rpmnet (train) (noise 0.01), 717 points" in out and "never tune" not in out
    assert sweep.main(["icp", "--pairs", "3", "--workers", "0", "--override", *overrides]) == 2
    assert capsys.readouterr().err == "error: --pairs 3: real_airplane/ts/rpmnet (train) has 2 pairs\n"


def test_the_test_split_is_the_grids_and_says_it_is_not_for_tuning(overrides, capsys):
    key, pairs = sweep.sweep_pairs(3, "os", "rpmnet", ["data.pair.noise_sigma=0.01", *overrides], split="test")
    assert key == "real_airplane/os/rpmnet (test)" and len(pairs) == 3
    _assert_same_pairs(pairs, _datamodule(overrides, "test").datasets["test"])
    assert sweep.main(["icp", "--split", "test", "--pairs", "2", "--workers", "0", "--override", *overrides]) == 0
    assert "for reporting only, never tune on them" in capsys.readouterr().out
    assert sweep.main(["icp", "--split", "test", "--pairs", "4", "--workers", "0", "--override", *overrides]) == 2
    assert capsys.readouterr().err == ("error: --pairs 4: real_airplane/ts/rpmnet (test) has 3 pairs "
                                       "(--override test_size=N carves out more shapes)\n")
