"""The dataset records (src/data/datasets.py) and what derives from them: each record has its
conf/data/<name>.yaml and they agree; the cache, prepare and the readers take their lists from them."""

from __future__ import annotations

import inspect

import pytest
from omegaconf import OmegaConf

from src.data import prepare, readers
from src.data.datasets import DATASET_NAMES, DATASETS, SOURCE_LAYOUTS, get_dataset, read_sources, source_of
from src.utils.errors import ConfigError
from tests.helpers.registration_helpers import CONF, compose_config

CACHE_DATAMODULE = "src.data.datamodule.RegistrationDataModule"
#: conf/data/*.yaml composed as data=<name>: those of the cache's datamodule are the records' configs.
CONFIGS = {p.stem: compose_config(f"data={p.stem}").data for p in sorted((CONF / "data").glob("*.yaml")) if p.stem != "base"}


def test_every_record_has_its_config_and_every_cache_config_a_record():
    cache_configs = {name for name, data in CONFIGS.items() if data._target_ == CACHE_DATAMODULE}
    assert cache_configs == set(DATASET_NAMES)
    assert all(CONFIGS[name].dataset == name for name in cache_configs)


@pytest.mark.parametrize("dataset", DATASETS, ids=DATASET_NAMES)
def test_the_config_agrees_with_its_record(dataset):
    data = CONFIGS[dataset.name]
    assert data.remove_axisymmetric == dataset.remove_axisymmetric
    build = OmegaConf.to_container(data.build)
    if dataset.generated:  # data.build holds the record's build defaults
        assert {key: build.get(key) for key in dataset.build_defaults} == dataset.build_defaults
    else:  # a prepared cache is opened as built
        assert build == {}


def test_records_are_consistent():
    assert len(set(DATASET_NAMES)) == len(DATASETS) and len(set(SOURCE_LAYOUTS)) == len(SOURCE_LAYOUTS)
    for dataset in DATASETS:
        meshes = any(source.meshes for source in dataset.sources)
        assert (dataset.num_samplings is not None) == meshes == (dataset.num_points is not None), dataset.name
        assert dataset.generated == (not any(source.reader for source in dataset.sources)), dataset.name
        assert all(source_of(layout)[0] is dataset for layout in dataset.layouts)
    assert [s.layout for s in read_sources()][-1] == "scan_meshes"  # the catch-all layout is detected last


def test_unknown_dataset_is_one_line():
    with pytest.raises(ConfigError, match=r"^unknown dataset 'modelnet10'; expected one of modelnet40, [^\n]*$"):
        get_dataset("modelnet10")


def test_prepare_and_readers_derive_from_the_records():
    assert list(readers.READERS) == list(readers.LAYOUTS) == [s.layout for s in read_sources()]
    assert all(readers.READERS[s.layout].__name__ == s.reader and readers.READERS[s.layout].layout == s.layout
               for s in read_sources())
    choices = next(a for a in prepare._parser()._actions if a.dest == "dataset").choices
    assert tuple(choices) == DATASET_NAMES
    params = inspect.signature(prepare.build_synthetic_cache).parameters
    assert all(params[key].default == value for key, value in get_dataset("synthetic").build_defaults.items())
