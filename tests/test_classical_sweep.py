"""baselines.classical.sweep: its pairs are the benchmark's (the real-airplane test set of the grid and src.eval)."""

from pathlib import Path

import hydra
import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from baselines.classical import sweep
from src.config import register_resolvers
from src.data.prepare import prepare
from src.paths import REPO_ROOT, shared_path

ZIP = shared_path("data", "modelnet40_normal_resampled_airplane.zip")
pytestmark = pytest.mark.skipif(not ZIP.is_file(), reason=f"{ZIP} not available")
register_resolvers()


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cache")
    prepare("modelnet40_resampled", source=[ZIP], cache_root=root, limit=6, workers=1)
    return root


def test_the_sweep_registers_the_pairs_src_eval_tests_on(cache_root, capsys):
    overrides = [f"data.cache_root={cache_root}", "test_size=3", "val_size=1"]
    key, pairs = sweep.benchmark_pairs(3, "os", "rpmnet", ["data.pair.noise_sigma=0.01", *overrides])
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=real_airplane", "sampling=os", "partial=rpmnet",
                                           "data.pair.noise_sigma=0.01", *overrides])
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("test")
    assert key == "real_airplane/os/rpmnet" and len(pairs) == 3
    for (src, ref, gt), item in zip(pairs, datamodule.datasets["test"]):
        for array, name in ((src, "points_src"), (ref, "points_ref"), (gt, "transform_gt")):
            np.testing.assert_array_equal(array, item[name].numpy())
    assert sweep.main(["icp", "--pairs", "2", "--os", "--workers", "0", "--override", *overrides]) == 0
    assert "2 pairs of real_airplane/os/rpmnet (noise 0.01), 717 points" in capsys.readouterr().out
    assert sweep.main(["icp", "--pairs", "4", "--workers", "0", "--override", *overrides]) == 2
    assert capsys.readouterr().err == ("error: --pairs 4: the real_airplane/ts/rpmnet test set has 3 pairs "
                                       "(--override test_size=N carves out more shapes)\n")
