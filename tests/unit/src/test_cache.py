import json
import os

import numpy as np
import pytest

from src.data import cache as cache_module
from src.data.cache import (
    CacheSplit, CacheWriter, check_cache, default_cache_root, is_cache_valid, open_cache, write_cache,
)
from src.utils.errors import DatasetError

HINT = (
    "run `python -m src.data.prepare modelnet40 --source PATH` "
    "(or use data=synthetic for the embedded synthetic default)"
)
MISSING = {"count": 2, "examples": ["b_0003", "b_0004"], "message": "split 'test' is not built: 2 of 2 shapes ..."}


def fields(**overrides) -> dict:
    base = {
        "dataset": "modelnet40", "source_layout": "princeton_off", "pair_sampling": "independent_samplings",
        "categories": ["a", "b"], "halves": {"1": ["a"], "2": ["b"]}, "sampling": {"num_samplings": 2, "seed": 0},
        "source": {"paths": ["/x"], "fingerprints": [{"sha256": "0"}]}, "missing_splits": {"test": MISSING},
    }
    return base | overrides


@pytest.fixture
def split() -> CacheSplit:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(3, 2, 5, 3)).astype(np.float32)
    return CacheSplit("train", points, -points, np.array([0, 1, 1]), ["a_0001", "b_0001", "b_0002"])


@pytest.fixture
def cache_dir(tmp_path, split):
    write_cache(tmp_path / "modelnet40", fields(), {"train": split})
    return tmp_path / "modelnet40"


def test_round_trip_is_memory_mapped(cache_dir, split):
    cache = open_cache(cache_dir)
    assert (cache.dataset, cache.categories, cache.pair_sampling) == ("modelnet40", ["a", "b"], "independent_samplings")
    assert cache.halves == {"1": ["a"], "2": ["b"]} and cache.available_splits == ["train"]
    loaded = cache.split("train")
    assert isinstance(loaded.points, np.memmap) and loaded.points.dtype == np.float32
    assert np.array_equal(loaded.points, split.points) and np.array_equal(loaded.normals, split.normals)
    assert loaded.labels.dtype == np.int64 and loaded.labels.tolist() == [0, 1, 1]
    assert loaded.shape_names == split.shape_names


def test_manifest_contents(cache_dir):
    manifest = json.loads((cache_dir / "manifest.json").read_text())
    assert list(manifest)[0] == "format_version" and list(manifest)[-1] == "complete" and manifest["complete"] is True
    info = manifest["splits"]["train"]
    assert info["count"] == 3 and info["shape"] == [3, 2, 5, 3]
    assert set(info["files"]) == {"points", "normals", "labels"}
    assert info["files"]["points"]["bytes"] == (cache_dir / "train_points.npy").stat().st_size
    assert len(manifest["content_hash"]) == 64 and manifest["missing_splits"] == {"test": MISSING}
    assert not list(cache_dir.parent.glob(".modelnet40.*"))  # no temporary folders left


def test_unbuilt_and_unknown_splits(cache_dir):
    cache = open_cache(cache_dir)
    with pytest.raises(DatasetError, match="^split 'test' is not built: 2 of 2 shapes ...$"):
        cache.split("test")
    with pytest.raises(DatasetError, match=r"split 'val' is not in the cache .* \(available: train\)"):
        cache.split("val")


def _truncate(path):
    path.write_bytes(path.read_bytes()[:-4])


def _flip(path):
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))


def _incomplete(path):
    manifest = json.loads(path.read_text())
    del manifest["complete"]
    path.write_text(json.dumps(manifest))


@pytest.mark.parametrize(
    ("damage", "file", "cause"),
    [
        (lambda p: p.unlink(), "manifest.json", "has no manifest.json"),
        (_incomplete, "manifest.json", "is incomplete"),
        (lambda p: p.write_text("{"), "manifest.json", "is unreadable"),
        (_truncate, "train_points.npy", "has .* bytes, expected .* \\(truncated or corrupt\\)"),
        (lambda p: p.unlink(), "train_labels.npy", "train_labels.npy is missing"),
        (_flip, "train_normals.npy", "is corrupt \\(sha256 mismatch\\)"),
    ],
)
def test_damage_is_detected_with_a_one_line_fix(cache_dir, damage, file, cause):
    damage(cache_dir / file)
    with pytest.raises(DatasetError, match=cause) as error:
        open_cache(cache_dir)
    assert str(error.value).endswith(HINT) and "\n" not in str(error.value)
    assert not is_cache_valid(cache_dir, {})


def test_same_size_damage_is_noticed_on_open(cache_dir):
    points = np.load(cache_dir / "train_points.npy", mmap_mode="r+")
    points[:2] = 0  # in place: same size, valid .npy
    points.flush()
    with pytest.raises(DatasetError, match="train_points.npy is corrupt \\(sha256 mismatch\\)"):
        open_cache(cache_dir)


def _paths(tree, path=()):
    """Key paths to every value of a manifest: each field, and each value nested in a field's dicts."""
    yield path
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from _paths(value, (*path, key))


def test_every_manifest_field_is_covered_by_the_content_hash(cache_dir):
    manifest = json.loads((cache_dir / "manifest.json").read_text())
    checked_apart = {"content_hash", "complete", "format_version"}
    paths = [p for p in _paths(manifest) if p and p[0] not in checked_apart]
    assert {p[0] for p in paths} == set(manifest) - checked_apart
    for path in paths:
        edited = json.loads(json.dumps(manifest))
        parent = edited
        for key in path[:-1]:
            parent = parent[key]
        parent[path[-1]] = ["edited", parent[path[-1]]]
        (cache_dir / "manifest.json").write_text(json.dumps(edited))
        with pytest.raises(DatasetError, match=r"manifest.json is corrupt \(its content_hash does not match"):
            open_cache(cache_dir)


def test_content_is_hashed_once_per_process_while_files_are_unchanged(cache_dir, monkeypatch):
    monkeypatch.setattr(cache_module, "_verified", set())
    real_sha256, hashed = cache_module.file_sha256, []
    monkeypatch.setattr(cache_module, "file_sha256", lambda path: hashed.append(path.name) or real_sha256(path))
    open_cache(cache_dir)
    open_cache(cache_dir)
    assert sorted(hashed) == ["train_labels.npy", "train_normals.npy", "train_points.npy"]
    _flip(cache_dir / "train_points.npy")
    stat = (cache_dir / "train_points.npy").stat()
    os.utime(cache_dir / "train_points.npy", ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    with pytest.raises(DatasetError, match="sha256 mismatch"):
        open_cache(cache_dir)


def test_missing_cache_names_the_fix(tmp_path):
    with pytest.raises(DatasetError, match="no dataset cache at .*; run `python -m src.data.prepare modelnet40_resampled"):
        open_cache(tmp_path / "modelnet40_resampled")
    with pytest.raises(DatasetError, match=r"no dataset cache at .*; run `python -m src.data.prepare synthetic`$"):
        open_cache(tmp_path / "synthetic")


def test_is_cache_valid_compares_expected_sub_dict(cache_dir):
    source = {"fingerprints": [{"sha256": "0"}]}
    assert is_cache_valid(cache_dir, {"sampling": {"num_samplings": 2, "seed": 0}, "source": source})
    assert not is_cache_valid(cache_dir, {"sampling": {"num_samplings": 40, "seed": 0}})
    assert check_cache(cache_dir, {"dataset": "synthetic"}).endswith("was built with different dataset")


def test_interrupted_build_leaves_nothing(tmp_path, split):
    with pytest.raises(RuntimeError), CacheWriter(tmp_path / "modelnet40", fields()) as writer:
        writer.add_split("train", split.points.shape, split.labels, split.shape_names, normals=False)
        raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


def test_rewrite_replaces_the_old_cache(cache_dir, split):
    write_cache(cache_dir, fields(missing_splits={}), {"test": split})
    assert open_cache(cache_dir).available_splits == ["test"]
    assert not (cache_dir / "train_points.npy").exists() and len(list(cache_dir.parent.iterdir())) == 1


def test_default_cache_root(monkeypatch, tmp_path):
    monkeypatch.setenv("OMNET_CACHE_DIR", str(tmp_path))
    assert default_cache_root() == tmp_path
    monkeypatch.delenv("OMNET_CACHE_DIR")
    assert default_cache_root().parts[-2:] == (".cache", "omnet-registration")
