"""Several real categories in one cache (``prepare --source A --source B``) and the experiments that
use them (``+exp=real_unseen_category``, ``+exp=real_airplane real_train_categories=[...]``), on tiny
generated archives shaped like the shared ones: one zip per category, test files withheld."""

import logging
from pathlib import Path

import hydra
import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from src.config import register_resolvers
from src.data.cache import file_sha256
from src.data.prepare import main, prepare
from src.data.readers import MergedReader, open_reader
from src.utils.errors import ConfigError, DatasetError
from tests.helpers.modelnet import TRAIN
from tests.helpers.paths import CONF

register_resolvers()
@pytest.fixture
def info_logs(caplog):
    caplog.set_level(logging.INFO, logger="src.data.prepare")
    return caplog


def _names(cache, split="train") -> list[str]:
    return list(cache.split(split).shape_names)


def test_merged_cache_holds_both_categories(zips, tmp_path, info_logs):
    cache = prepare("modelnet40_resampled", source=[zips["bathtub"], zips["airplane"]], cache_root=tmp_path / "c")
    assert cache.categories == ["airplane", "bathtub"] and cache.halves == {"1": ["airplane", "bathtub"], "2": []}
    assert _names(cache) == [f"airplane_{i:04d}" for i in range(1, 7)] + [f"bathtub_{i:04d}" for i in range(1, 5)]
    assert cache.split("train").labels.tolist() == [0] * 6 + [1] * 4
    alone = {c: prepare("modelnet40_resampled", source=z, cache_root=tmp_path / c) for c, z in zips.items()}
    merged = np.asarray(cache.split("train").points)
    assert np.array_equal(merged, np.concatenate([np.asarray(alone[c].split("train").points) for c in TRAIN]))
    assert np.array_equal(cache.split("train").normals[6:], alone["bathtub"].split("train").normals)
    source = cache.manifest["source"]
    assert sorted(source["paths"]) == sorted(str(z.resolve()) for z in zips.values())
    assert sorted(f["sha256"] for f in source["fingerprints"]) == sorted(file_sha256(z) for z in zips.values())
    missing = cache.manifest["missing_splits"]["test"]
    assert missing["by_category"] == {
        "airplane": {"missing": 2, "listed": 2, "examples": ["airplane_0007", "airplane_0008"]},
        "bathtub": {"missing": 2, "listed": 2, "examples": ["bathtub_0005", "bathtub_0006"]},
    }
    assert missing["message"].startswith("split 'test' is not built: 4 of 4 shapes listed in its split list are")
    assert missing["message"].endswith(
        "(airplane: 2 of 2, first: airplane_0007, airplane_0008; bathtub: 2 of 2, first: bathtub_0005, bathtub_0006)"
    )
    assert missing["message"] in info_logs.messages and all(str(z) in missing["message"] for z in zips.values())
    with pytest.raises(DatasetError, match="split 'test' is not built: 4 of 4"):
        cache.split("test")


def test_rerun_in_any_order_is_a_noop_and_other_sources_rebuild(zips, tmp_path, info_logs):
    both = {"source": [zips["airplane"], zips["bathtub"]], "cache_root": tmp_path}
    prepare("modelnet40_resampled", **both)
    stamp = (tmp_path / "modelnet40_resampled" / "train_points.npy").stat().st_mtime_ns
    info_logs.clear()
    prepare("modelnet40_resampled", **{**both, "source": both["source"][::-1]})
    assert "up to date" in info_logs.text
    assert (tmp_path / "modelnet40_resampled" / "train_points.npy").stat().st_mtime_ns == stamp
    cache = prepare("modelnet40_resampled", source=zips["airplane"], cache_root=tmp_path)
    assert "was built with different source" in info_logs.text and cache.categories == ["airplane"]


def test_command_line_merges_repeated_sources_with_a_limit_per_category(zips, tmp_path):
    argv = ["modelnet40_resampled", "--source", str(zips["airplane"]), "--source", str(zips["bathtub"])]
    assert main([*argv, "--limit", "2", "--workers", "1", "--cache-root", str(tmp_path)]) == 0
    cache = prepare("modelnet40_resampled", source=list(zips.values()), cache_root=tmp_path, limit=2)
    assert _names(cache) == ["airplane_0001", "airplane_0002", "bathtub_0001", "bathtub_0002"]


def test_merging_refuses_a_shape_twice_and_mixed_layouts(zips, princeton_dir, tmp_path, capsys):
    folder = tmp_path / "src" / "airplane"
    with pytest.raises(DatasetError, match=r"^shape airplane_0001 \(train\) is in two sources: ") as error:
        prepare("modelnet40_resampled", source=[zips["airplane"], folder], cache_root=tmp_path)
    assert str(zips["airplane"]) in str(error.value) and f"{folder} and " in str(error.value)
    argv = ["modelnet40_resampled", "--source", str(zips["airplane"]), "--source", str(princeton_dir)]
    assert main([*argv, "--cache-root", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: sources to merge must share one layout: ") and error.count("\n") == 1
    assert f"{princeton_dir} is princeton_off" in error and f"{zips['airplane']} is pointnet2_resampled" in error


def test_merged_reader_loads_each_shape_from_its_archive(zips):
    reader = MergedReader([open_reader(zips["bathtub"]), open_reader(zips["airplane"])])
    assert reader.categories == ["airplane", "bathtub"] and list(reader.entries) == ["train"]
    entries = reader.entries["train"]
    assert [e.source for e in entries] == [1] * 6 + [0] * 4
    shape = reader.load(entries[-1])
    assert (shape.name, shape.category) == ("bathtub_0004", "bathtub") and shape.points.shape == (16, 3)


# --- experiments ---------------------------------------------------------------------------


def _datamodule(cache_root: Path, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=[f"data.cache_root={cache_root}", "data.num_workers=0",
                                           f"output_dir={cache_root / 'unused'}", *overrides])
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup()
    return datamodule


def _stage_names(datamodule) -> dict[str, list[str]]:
    names = datamodule.cache.split("train").shape_names
    return {stage: [names[i] for i in data.shape_indices] for stage, data in datamodule.datasets.items()}


def _ids(category: str, first: int, last: int) -> list[str]:
    return [f"{category}_{i:04d}" for i in range(first, last + 1)]


@pytest.mark.parametrize(
    ("overrides", "train", "val", "test"),
    [
        ([], _ids("airplane", 1, 4), _ids("airplane", 5, 6), _ids("bathtub", 1, 4)),
        (["train_category=bathtub", "test_category=airplane"], _ids("bathtub", 1, 2), _ids("bathtub", 3, 4),
         _ids("airplane", 1, 6)),
    ],
)
def test_real_unseen_category_tests_on_the_other_category(merged_root, overrides, train, val, test):
    datamodule = _datamodule(merged_root, "+exp=real_unseen_category", "val_size=2", *overrides)
    assert _stage_names(datamodule) == {"train": train, "val": val, "test": test}


@pytest.mark.parametrize(
    ("overrides", "train"),
    [([], _ids("airplane", 1, 4)),
     (["real_train_categories=[airplane,bathtub]"], _ids("airplane", 1, 4) + _ids("bathtub", 1, 4))],
)
def test_real_airplane_trains_on_one_or_both_categories_and_keeps_the_airplane_carveout(merged_root, overrides, train):
    datamodule = _datamodule(merged_root, "+exp=real_airplane", "test_size=1", "val_size=1", "val_repeat=2", *overrides)
    assert _stage_names(datamodule) == {"train": train, "val": _ids("airplane", 5, 5) * 2, "test": _ids("airplane", 6, 6)}


def test_one_category_on_both_sides_of_the_unseen_category_experiment_is_refused(merged_root):
    with pytest.raises(ConfigError, match="also training shapes .*first: airplane_0001"):
        _datamodule(merged_root, "+exp=real_unseen_category", "val_size=2", "train_category=airplane", "test_category=airplane")


def test_exclude_must_name_a_stage_without_exclude(merged_root):
    with pytest.raises(ConfigError, match="exclude: 'test' must be a stage without exclude"):
        _datamodule(merged_root, "+exp=real_airplane", "test_size=1", "val_size=1", "+data.splits.test.exclude=[train]")

