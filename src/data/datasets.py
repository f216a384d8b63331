"""Every dataset the cache holds, one record each; everything else is derived.

A :class:`Dataset` holds a dataset's facts: its name (the cache folder ``<cache_root>/<name>/``,
``data.dataset``, ``python -m src.data.prepare <name>``, ``conf/data/<name>.yaml``), the archive
layouts it is prepared from (:class:`Source`: the manifest's ``source_layout``, the reader of
:mod:`src.data.readers`, what such an archive holds, its official download), the sampling defaults
of ``prepare``, where its categories come from and whether axisymmetric categories are dropped.
Derived from :data:`DATASETS`: the cache's dataset and layout lists and its prepare hint
(:mod:`src.data.cache`), ``prepare``'s choices, layouts, URLs and defaults (:mod:`src.data.prepare`),
the readers' table and layout detection (:mod:`src.data.readers`); ``tests/unit/src/test_datasets.py`` checks
that each record has its ``conf/data/<name>.yaml`` and that they agree.

Adding a dataset means adding its record here, its reader (a new layout) and its config.

Light on purpose: importing it imports nothing but :mod:`src.utils.errors`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from src.utils.errors import ConfigError


@dataclass(frozen=True)
class Source:
    """One archive layout a dataset is prepared from.

    Attributes:
        layout: the manifest's ``source_layout``.
        reader: the :class:`~src.data.readers.Reader` subclass of :mod:`src.data.readers` that reads it
            (``""``: generated, nothing to read). Layouts are detected in registry order: a catch-all
            layout (any mesh file) comes last.
        archive: what such an archive holds, for messages.
        url: its official archive, fetched by ``prepare --download`` (the dataset's first source with one).
        as_provided: ``""`` for meshes sampled here (``num_samplings`` x ``num_points``); else the points
            are stored as provided, one sampling per shape, and this is the cache's ``pair_sampling``.
        one_process: its shapes are rows of large files: read in one process (each file read once).
    """

    layout: str
    reader: str
    archive: str
    url: str = ""
    as_provided: str = ""
    one_process: bool = False

    @property
    def meshes(self) -> bool:
        """Meshes, sampled by ``prepare`` (else points stored as provided)."""
        return not self.as_provided


@dataclass(frozen=True)
class Dataset:
    """One dataset of the cache.

    Attributes:
        name: the cache folder, ``data.dataset``, ``prepare``'s argument, ``conf/data/<name>.yaml``.
        description: one line, for ``prepare --help``.
        sources: the layouts it is prepared from (several: any one of them, detected).
        num_samplings: ``prepare``'s default mesh samplings per shape (None: no meshes).
        num_points: ``prepare``'s default points per mesh sampling (None: no meshes).
        categories: where its categories (label = index) and halves come from.
        remove_axisymmetric: ``data.remove_axisymmetric`` of its config (the paper drops ModelNet40's
            axisymmetric categories; scans have none).
        generated: built by ``prepare`` (and on first use) from code, not from an archive.
        build: further defaults of a generated dataset's build (``data.build.*``).
    """

    name: str
    description: str
    sources: tuple[Source, ...]
    num_samplings: int | None = None
    num_points: int | None = None
    categories: str = ""
    remove_axisymmetric: bool = True
    generated: bool = False
    build: Mapping[str, int] = field(default_factory=dict)

    @property
    def layouts(self) -> tuple[str, ...]:
        return tuple(s.layout for s in self.sources)

    @property
    def url(self) -> str:
        """The official archive ``prepare --download`` fetches (``""``: none)."""
        return next((s.url for s in self.sources if s.url), "")

    @property
    def build_defaults(self) -> dict[str, int]:
        """A generated dataset's build defaults (``data.build`` of its config), the samplings included."""
        return {**self.build, "num_samplings": self.num_samplings, "num_points": self.num_points}


MODELNET40_CATEGORIES = "src.data.categories: the 40 categories of shape_names.txt, the official halves"

DATASETS: tuple[Dataset, ...] = (
    Dataset(
        "modelnet40", "ModelNet40: the Princeton meshes or PointNet's h5 points", num_samplings=40, num_points=2048,
        categories=MODELNET40_CATEGORIES,
        sources=(
            Source("princeton_off", "PrincetonOffReader", "Princeton meshes (ModelNet40/<category>/{train,test}/*.off)",
                   url="http://modelnet.cs.princeton.edu/ModelNet40.zip"),
            Source("pointnet_h5", "PointNetH5Reader",
                   "PointNet h5 (modelnet40_ply_hdf5_2048: ply_data_*.h5 + shape_names.txt)",
                   url="https://shapenet.cs.stanford.edu/media/modelnet40_ply_hdf5_2048.zip",
                   as_provided="single_sampling", one_process=True),
        ),
    ),
    Dataset(
        "modelnet40_resampled", "ModelNet40 in PointNet++'s modelnet40_normal_resampled (points + normals)",
        categories=MODELNET40_CATEGORIES,
        sources=(
            Source("pointnet2_resampled", "ResampledReader",
                   "PointNet++ resampled (modelnet40_normal_resampled: modelnet40_shape_names.txt, "
                   "modelnet40_{train,test}.txt, <category>/<id>.txt)",
                   url="https://shapenet.cs.stanford.edu/media/modelnet40_normal_resampled.zip",
                   as_provided="disjoint_subsets"),
        ),
    ),
    Dataset(
        "stanford", "real scans: a folder of .off/.ply meshes (e.g. the Stanford Bunny)", num_samplings=40,
        num_points=2048, categories="one per scan file (its name); no halves", remove_axisymmetric=False,
        sources=(Source("scan_meshes", "ScanMeshReader", "a folder of .off/.ply scans"),),
    ),
    Dataset(
        "synthetic", "the embedded procedural default (synthetic CAD-like solids)", num_samplings=10, num_points=2048,
        categories="src.data.synthetic: SYNTHETIC_CATEGORIES, SYNTHETIC_HALVES", generated=True,
        build={"num_train_per_category": 24, "num_test_per_category": 8},
        sources=(Source("procedural", "", "src.data.synthetic's generator"),),
    ),
)

DATASET_NAMES: tuple[str, ...] = tuple(d.name for d in DATASETS)
#: Every ``source_layout`` a manifest may record.
SOURCE_LAYOUTS: tuple[str, ...] = tuple(s.layout for d in DATASETS for s in d.sources)
_BY_NAME = {d.name: d for d in DATASETS}


def get_dataset(name: str) -> Dataset:
    """The record of dataset ``name`` (ConfigError naming the known ones otherwise)."""
    if name not in _BY_NAME:
        raise ConfigError(f"unknown dataset {name!r}; expected one of {', '.join(DATASET_NAMES)}")
    return _BY_NAME[name]


def read_sources() -> tuple[Source, ...]:
    """The layouts read from archives, in detection order."""
    return tuple(s for d in DATASETS for s in d.sources if s.reader)


def source_of(layout: str) -> tuple[Dataset, Source]:
    """The dataset a layout is prepared as, and the layout's record."""
    return next((d, s) for d in DATASETS for s in d.sources if s.layout == layout)
