"""benchmarks.studies.gpu_study.device_data: a prepared cache packed for the GPU machine and unpacked there is the same cache, file
for file (the cache's own sha256 check), negative zeros included; a cache it cannot pack losslessly is refused."""

from __future__ import annotations

import json

import pytest

from benchmarks.studies.gpu_study.device_data import pack, unpack
from src.data.cache import open_cache
from src.data.prepare import prepare
from src.utils.errors import DatasetError
from tests.helpers.modelnet import write_category


def _cache(tmp_path, first_line: str):
    folder = write_category(tmp_path / "src", "airplane", 3)
    shape = folder / "airplane" / "airplane_0001.txt"
    shape.write_text(first_line + "\n" + shape.read_text().split("\n", 1)[1])
    prepare("modelnet40_resampled", source=[folder], cache_root=tmp_path / "cache")
    return tmp_path / "cache" / "modelnet40_resampled"


def test_unpack_rebuilds_the_same_points_file_byte_for_byte(tmp_path):
    cache = _cache(tmp_path, "-0.000000,0.000000,-0.250000,0.1,0.2,0.3")
    packed = pack(cache, tmp_path / "packed")
    assert sorted(p.name for p in packed.iterdir()) == ["manifest.json", "train_labels.npy", "train_points.xz"]
    rebuilt = unpack(packed, tmp_path / "there")
    points = json.loads((cache / "manifest.json").read_text())["splits"]["train"]["files"]["points"]["name"]
    assert (rebuilt / points).read_bytes() == (cache / points).read_bytes()  # -0.0 kept: the bytes, not just ==
    assert open_cache(rebuilt).split("train").normals is None  # points only: the manifest lists no normals
    assert open_cache(rebuilt).split("train").shape_names == open_cache(cache).split("train").shape_names


def test_points_that_are_not_micro_units_are_refused(tmp_path):
    cache = _cache(tmp_path, "0.1234567,0.000000,-0.250000,0.1,0.2,0.3")
    with pytest.raises(DatasetError, match="cannot be packed losslessly"):
        pack(cache, tmp_path / "packed")
