"""exp=real_airplane and exp=real_unseen_category on the first shapes of the shared real ModelNet40
airplane and bathtub zips, prepared into one cache."""

from pathlib import Path

import hydra
import pytest
import torch
from hydra import compose, initialize_config_dir
from torch.utils.data import DataLoader

from src.config import register_resolvers
from src.data.prepare import prepare
from src.utils.errors import DatasetError
from src.utils.paths import REPO_ROOT, shared_path

ZIP = shared_path("data", "modelnet40_normal_resampled_airplane.zip")
BATHTUB_ZIP = shared_path("data", "modelnet40_normal_resampled_bathtub.zip")
CONF = str(REPO_ROOT / "conf")
ZIPS = pytest.mark.shared_data("data/modelnet40_normal_resampled_airplane.zip", "data/modelnet40_normal_resampled_bathtub.zip")  # the cache_root tests
register_resolvers()


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory) -> Path:
    """Both categories, the first 12 train shapes of each."""
    root = tmp_path_factory.mktemp("cache")
    prepare("modelnet40_resampled", source=[ZIP, BATHTUB_ZIP], cache_root=root, limit=12, workers=1)
    return root


def _datamodule(cache_root: Path, *overrides: str, exp: str = "real_airplane"):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("config", overrides=[f"+exp={exp}", *(("test_size=4", "val_size=2") if exp == "real_airplane" else ("val_size=4",)), f"data.cache_root={cache_root}",
                                           "data.num_workers=0", f"output_dir={cache_root / 'unused'}", *overrides])
    return hydra.utils.instantiate(cfg.data)


def _stage_names(datamodule) -> dict[str, list[str]]:
    names = datamodule.cache.split("train").shape_names
    return {stage: [names[i] for i in data.shape_indices] for stage, data in datamodule.datasets.items()}


def _ids(category: str, first: int, last: int) -> list[str]:
    return [f"{category}_{i:04d}" for i in range(first, last + 1)]


@ZIPS
def test_validation_carveout_is_the_last_train_ids(cache_root):
    dm = _datamodule(cache_root)
    dm.setup("fit")
    dm.setup("test")
    names = dm.cache.split("train").shape_names
    stages = {stage: [names[i] for i in data.shape_indices] for stage, data in dm.datasets.items()}
    assert stages["test"] == ["airplane_0009", "airplane_0010", "airplane_0011", "airplane_0012"]
    assert stages["val"] == ["airplane_0007", "airplane_0008"] * 4  # the ids before the test carve-out, 4 pairs each
    assert stages["train"] == [f"airplane_{i:04d}" for i in range(1, 7)]
    assert len({tuple(dm.datasets["val"][i]["points_src"][:3].flatten().tolist()) for i in range(8)}) == 8


@ZIPS
@pytest.mark.parametrize("partial", ["prnet", "rpmnet"])
def test_real_pairs_are_fixed_across_worker_counts(cache_root, partial):
    dm = _datamodule(cache_root, f"partial={partial}", "data.pair.noise_sigma=0.01")
    dm.setup("validate")
    dataset = dm.datasets["val"]
    one = [b["points_src"] for b in DataLoader(dataset, batch_size=2, num_workers=0)]
    two = [b["points_src"] for b in DataLoader(dataset, batch_size=2, num_workers=2)]
    torch.testing.assert_close(torch.cat(one), torch.cat(two))
    assert one[0].shape[1] == (768 if partial == "prnet" else 717)


@ZIPS
def test_asking_for_the_withheld_test_split_stops_with_the_prepare_message(cache_root):
    dm = _datamodule(cache_root, "data.splits.test.split=test")
    with pytest.raises(DatasetError, match=(
        r"150 of 150 shapes .* missing .*\(airplane: 100 of 100, first: airplane_0627, .*; "
        r"bathtub: 50 of 50, first: bathtub_0107, bathtub_0108, bathtub_0109, bathtub_0110, bathtub_0111, \.\.\.\)$"
    )):
        dm.setup("test")


@ZIPS
def test_training_on_both_categories_keeps_the_airplane_carveout(cache_root):
    dm = _datamodule(cache_root, "real_train_categories=[airplane,bathtub]")
    dm.setup()
    assert _stage_names(dm) == {"train": _ids("airplane", 1, 6) + _ids("bathtub", 1, 12),
                                "val": _ids("airplane", 7, 8) * 4, "test": _ids("airplane", 9, 12)}
    assert dm.datasets["train"][17]["points_src"].shape == (768, 3)  # a bathtub pair


@ZIPS
@pytest.mark.parametrize(("train", "test"), [("airplane", "bathtub"), ("bathtub", "airplane")])
def test_real_unseen_category_in_both_directions(cache_root, train, test):
    dm = _datamodule(cache_root, f"train_category={train}", f"test_category={test}", exp="real_unseen_category")
    dm.setup()
    assert _stage_names(dm) == {"train": _ids(train, 1, 8), "val": _ids(train, 9, 12), "test": _ids(test, 1, 12)}
    assert dm.datasets["test"][0]["points_src"].shape == (768, 3)


@pytest.mark.shared_data("data/stanford/bunny_npm_decimated.off")
def test_stanford_bunny_gives_repeated_fixed_pairs(tmp_path):
    bunny = ZIP.parent / "stanford" / "bunny_npm_decimated.off"
    prepare("stanford", source=bunny, cache_root=tmp_path, num_samplings=4, workers=1)
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("config", overrides=["+exp=stanford", "pairs_per_scan=3", f"data.cache_root={tmp_path}",
                                           "data.num_workers=0", f"output_dir={tmp_path / 'unused'}"])
    dm = hydra.utils.instantiate(cfg.data)
    dm.setup("test")
    pairs = [dm.datasets["test"][i] for i in range(3)]
    assert len(dm.datasets["test"]) == 3 and dm.cache.categories == ["bunny_npm_decimated"]
    assert not torch.equal(pairs[0]["transform_gt"], pairs[1]["transform_gt"])
    assert pairs[0]["points_src"].shape == (768, 3)
    torch.testing.assert_close(dm.datasets["test"][2]["points_ref"], pairs[2]["points_ref"])
