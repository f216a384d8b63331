"""The per-shape NumPy layout (``modelnet40_npy``): its reader, ``prepare``, the withheld test split and the
paper's experiments on it (their ``instead`` stages and carve-outs), the ``halves`` sampling and ``--swap-yz``."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import numpy as np
import pytest

from src.data.cache import open_cache
from src.data.datamodule import select_shapes
from src.data.prepare import main, prepare
from src.data.readers import NumpyShapeReader, PointShape, detect_layout, open_reader
from src.data.transforms import PickPair
from src.utils.errors import ConfigError, DatasetError
from tests.helpers.registration_helpers import compose_config

#: Categories of both halves and one axisymmetric one (bottle: removed by the paper's experiments).
TRAIN = {"airplane": 20, "bathtub": 20, "bottle": 3, "laptop": 4, "sofa": 5}
POINTS = 1024  # the data config's


def _cloud(seed: int, columns: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, size=(POINTS, columns)).astype(np.float32)


def write_npy_archive(root: Path, test: bool = False, columns: int = 3) -> Path:
    """``root/ModelNet40/<category>/train/<category>_NNNN.npy`` for :data:`TRAIN`; 2 test ids a category, written
    (``test``) or listed in ``withheld_test_ids.txt``."""
    base = root / "ModelNet40"
    withheld = []
    for c, (category, count) in enumerate(TRAIN.items()):
        for i in range(1, count + 3):
            split = "train" if i <= count else "test"
            name = f"{category}_{i:04d}"
            if split == "test" and not test:
                withheld.append(name)
                continue
            (base / category / split).mkdir(parents=True, exist_ok=True)
            np.save(base / category / split / f"{name}.npy", _cloud(100 * c + i, columns))
    if withheld:
        (base / "withheld_test_ids.txt").write_text("\n".join(withheld) + "\n")
    return base


@pytest.fixture
def npy_dir(tmp_path) -> Path:
    return write_npy_archive(tmp_path / "src")


@pytest.mark.parametrize("zipped", [False, True])
@pytest.mark.parametrize("columns", [3, 6])
def test_the_reader_reads_points_and_optional_normals_from_a_folder_or_a_zip(tmp_path, make_zip, zipped, columns):
    folder = write_npy_archive(tmp_path / "src", test=True, columns=columns)
    source = make_zip(folder) if zipped else folder
    assert detect_layout(source) == "per_shape_npy"
    reader = open_reader(source)
    assert isinstance(reader, NumpyShapeReader) and list(reader.categories) == list(TRAIN)
    assert [e.name for e in reader.entries["train"][:2]] == ["airplane_0001", "airplane_0002"]
    assert len(reader.entries["test"]) == 2 * len(TRAIN) and not reader.missing
    shape = reader.load(reader.entries["train"][1])
    expected = _cloud(2, columns)
    assert isinstance(shape, PointShape) and shape.points.dtype == np.float32
    np.testing.assert_array_equal(shape.points, expected[:, :3])
    assert (shape.normals is None) == (columns == 3)
    if columns == 6:
        np.testing.assert_array_equal(shape.normals, expected[:, 3:])


def test_a_withheld_test_split_is_reported_with_its_count_and_ids(npy_dir):
    reader = open_reader(npy_dir)
    assert "test" not in reader.entries and len(reader.entries["train"]) == sum(TRAIN.values())
    missing = reader.missing["test"]
    assert missing.count == 2 * len(TRAIN) and missing.by_category["laptop"]["examples"] == ["laptop_0005", "laptop_0006"]
    assert f"{2 * len(TRAIN)} of {2 * len(TRAIN)} shapes" in missing.message


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (None, r"airplane_0002.npy: not a readable \.npy array"),
        (np.zeros((POINTS, 4), np.float32), r"airplane_0002.npy: holds an array of shape \(1024, 4\), expected \(N, 3\)"),
        (np.zeros((2, POINTS, 3), np.float32), r"airplane_0002.npy: holds an array of shape \(2, 1024, 3\)"),
        (np.array(["a", "b", "c"])[None].repeat(POINTS, 0), r"airplane_0002.npy: holds <U1 values, expected numbers"),
        (np.where(np.arange(POINTS)[:, None] == 7, np.nan, _cloud(0)), r"airplane_0002.npy: 1 rows hold non-finite "
                                                                        r"values \(first: row 7"),
    ],
    ids=["corrupt", "four_columns", "three_dimensions", "strings", "nan"],
)
def test_a_bad_shape_file_is_one_line_naming_it(npy_dir, tmp_path, array, message):
    target = npy_dir / "airplane" / "train" / "airplane_0002.npy"
    if array is None:
        target.write_bytes(b"\x93NUMPY garbage")
    else:
        np.save(target, array)
    with pytest.raises(DatasetError, match=message):
        prepare("modelnet40_npy", source=npy_dir, cache_root=tmp_path / "cache")


def test_prepare_builds_the_cache_and_reports_the_withheld_split(npy_dir, tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        assert main(["modelnet40_npy", "--source", str(npy_dir), "--cache-root", str(tmp_path / "cache"), "--workers", "1"]) == 0
    assert f"split 'test' is not built: {2 * len(TRAIN)} of {2 * len(TRAIN)} shapes" in caplog.text
    cache = open_cache(tmp_path / "cache" / "modelnet40_npy")
    assert cache.pair_sampling == "single_sampling" and cache.available_splits == ["train"]
    assert cache.manifest["missing_splits"]["test"]["count"] == 2 * len(TRAIN)
    train = cache.split("train")
    assert train.points.shape == (sum(TRAIN.values()), 1, POINTS, 3)
    np.testing.assert_array_equal(train.points[1, 0], _cloud(2))
    with pytest.raises(DatasetError, match="split 'test' is not built"):
        cache.split("test")


def test_swap_yz_stores_the_other_axis_convention(npy_dir, tmp_path):
    plain = prepare("modelnet40_npy", source=npy_dir, cache_root=tmp_path / "a").split("train").points
    swapped = prepare("modelnet40_npy", source=npy_dir, cache_root=tmp_path / "b", swap_yz=True)
    assert swapped.manifest["sampling"]["swap_yz"] is True
    np.testing.assert_array_equal(swapped.split("train").points, plain[..., [0, 2, 1]])


def _datamodule(cache_root: Path, *overrides: str):
    cfg = compose_config(*overrides, f"data.cache_root={cache_root}", "data.num_workers=0")
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup()
    return datamodule


def _names(datamodule) -> dict[str, set[str]]:
    names = {}
    for stage, data in datamodule.datasets.items():
        split = datamodule.splits[stage]["split"]
        names[stage] = {datamodule.cache.split(split).shape_names[i] for i in data.shape_indices}
    return names


def _categories(names: set[str]) -> set[str]:
    return {n.rsplit("_", 1)[0] for n in names}


@pytest.mark.parametrize("experiment", ["unseen_shapes", "unseen_categories", "gaussian_noise"])
def test_the_papers_experiments_run_on_a_withheld_test_split_with_one_override(npy_dir, tmp_path, caplog, experiment):
    prepare("modelnet40_npy", source=npy_dir, cache_root=tmp_path / "cache")
    with caplog.at_level(logging.WARNING):
        datamodule = _datamodule(tmp_path / "cache", f"+exp={experiment}", "data=modelnet40_npy")
    names = _names(datamodule)
    first_half = {"airplane", "bathtub"}  # bottle: axisymmetric, removed
    assert _categories(names["train"]) == _categories(names["val"]) == first_half
    assert not names["train"] & names["val"] and not names["train"] & names["test"]
    assert _categories(names["test"]) == ({"laptop", "sofa"} if experiment == "unseen_categories" else first_half)
    assert "data.splits.val: the modelnet40_npy cache has no test split (10 shapes withheld)" in caplog.text
    assert datamodule.pair["sampling"] == "os" and datamodule.pair["num_points"] == 1024  # the data config's


def test_unseen_shapes_and_unseen_categories_train_on_the_same_shapes(npy_dir, tmp_path):
    prepare("modelnet40_npy", source=npy_dir, cache_root=tmp_path / "cache")
    shapes = _names(_datamodule(tmp_path / "cache", "+exp=unseen_shapes", "data=modelnet40_npy"))
    categories = _names(_datamodule(tmp_path / "cache", "+exp=unseen_categories", "data=modelnet40_npy"))
    assert shapes["train"] == categories["train"] and shapes["val"] == categories["val"]
    assert len(shapes["train"]) + len(shapes["val"]) + len(shapes["test"]) == TRAIN["airplane"] + TRAIN["bathtub"]


def test_with_the_test_split_present_the_papers_own_split_is_used(tmp_path, caplog):
    folder = write_npy_archive(tmp_path / "src", test=True)
    prepare("modelnet40_npy", source=folder, cache_root=tmp_path / "cache")
    with caplog.at_level(logging.WARNING):
        names = _names(_datamodule(tmp_path / "cache", "+exp=unseen_categories", "data=modelnet40_npy"))
    assert "stated alternative" not in caplog.text
    assert len(names["train"]) == TRAIN["airplane"] + TRAIN["bathtub"]  # the whole first-half train split
    assert names["val"] == {f"{c}_{i:04d}" for c in ("airplane", "bathtub") for i in (TRAIN[c] + 1, TRAIN[c] + 2)}
    assert _categories(names["test"]) == {"laptop", "sofa"} and len(names["test"]) == 4


def test_carve_outs_of_one_seed_tile_each_category(npy_dir, tmp_path):
    cache = prepare("modelnet40_npy", source=npy_dir, cache_root=tmp_path / "cache")
    parts = [select_shapes(cache, {"split": "train", "categories": "all", "carve": [3, a, b]}, False)[1]
             for a, b in ((0.0, 0.2), (0.2, 0.5), (0.5, 1.0))]
    joined = np.sort(np.concatenate(parts))
    np.testing.assert_array_equal(joined, np.arange(sum(TRAIN.values())))
    other_seed = select_shapes(cache, {"split": "train", "categories": "all", "carve": [4, 0.0, 0.2]}, False)[1]
    assert set(other_seed) != set(parts[0])  # the seed decides which shapes
    for carve in ([0, 0.5, 0.2], [0, 0.0], "all", [0, -0.1, 0.5]):
        with pytest.raises(ConfigError, match="data.splits carve=.* is invalid: give \\[seed, start, stop\\]"):
            select_shapes(cache, {"split": "train", "carve": carve}, False)


def test_as_many_as_draws_each_category_as_the_withheld_split_holds(npy_dir, tmp_path):
    cache = prepare("modelnet40_npy", source=npy_dir, cache_root=tmp_path / "cache")
    split, drawn = select_shapes(cache, {"split": "train", "categories": ["laptop", "sofa"], "as_many_as": [5, "test"]}, True)
    names = np.asarray(cache.split(split).shape_names)[drawn]
    assert sorted(n.rsplit("_", 1)[0] for n in names) == ["laptop", "laptop", "sofa", "sofa"]  # 2 withheld of each
    carved = select_shapes(cache, {"split": "train", "categories": ["laptop", "sofa"], "carve": [5, 0.0, 0.5]}, True)[1]
    assert set(drawn) <= set(carved)  # the front of the same seeded permutation
    built = prepare("modelnet40_npy", source=write_npy_archive(tmp_path / "full", test=True), cache_root=tmp_path / "c2")
    assert len(select_shapes(built, {"split": "train", "categories": ["sofa"], "as_many_as": [5, "test"]}, True)[1]) == 2
    assert len(select_shapes(built, {"split": "test", "categories": ["sofa"], "as_many_as": [5, "train"]}, True)[1]) == 2
    for value in ([5], [5, "validation"], "test", ["x", "test"]):
        with pytest.raises(ConfigError, match="data.splits as_many_as=.* is invalid: give \\[seed, split\\]"):
            select_shapes(cache, {"split": "train", "as_many_as": value}, False)


def test_excluding_a_stage_of_another_split_excludes_no_shape(tmp_path):
    cache = prepare("modelnet40_npy", source=write_npy_archive(tmp_path / "src", test=True), cache_root=tmp_path / "c")
    stages = {"val": {"split": "test", "categories": ["airplane"]}}
    spec = {"split": "train", "categories": ["airplane"], "exclude": ["val"]}
    assert len(select_shapes(cache, spec, True, stages)[1]) == TRAIN["airplane"]


def test_twice_sampled_pairs_from_one_sampling_are_refused_and_halves_offered():
    with pytest.raises(DatasetError, match="TS\\) pairs are impossible: use sampling=os, or sampling=halves"):
        PickPair("ts", "single_sampling")
    shape = np.arange(3 * POINTS, dtype=np.float32).reshape(1, POINTS, 3)
    sample = PickPair("halves", "single_sampling", POINTS)({"shape_points": shape}, np.random.default_rng(0))
    src, ref = sample["points_src"], sample["points_ref"]
    assert len(src) == len(ref) == POINTS // 2
    assert not {tuple(p) for p in src} & {tuple(p) for p in ref}  # disjoint halves of the one sampling
    assert {tuple(p) for p in src} | {tuple(p) for p in ref} == {tuple(p) for p in shape[0]}
