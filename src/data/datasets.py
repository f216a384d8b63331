"""Every dataset the cache holds, one record each; everything else is derived.

A :class:`Dataset` holds a dataset's facts: its name (the cache folder ``<cache_root>/<name>/``,
``data.dataset``, ``python -m src.data.prepare <name>``, ``conf/data/<name>.yaml``), the archive
layouts it is prepared from (:class:`Source`: the manifest's ``source_layout``, the reader of
:mod:`src.data.readers`, what such an archive holds, the hosts it is downloaded from, in order, each a
:class:`Mirror` with what is published about its file and where that is published), the sampling defaults
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
class Mirror:
    """One host of an archive, and what is published about the file it serves.

    Attributes:
        url: the archive's address (fetched by :mod:`src.data.download`; a HuggingFace address from the
            endpoint that ``HF_ENDPOINT`` names).
        sha256, md5: its published checksum, verified after every download (``""``: none published;
            then its size, when published, and its structure are what is verified).
        size: its published size in bytes (None: none published).
        evidence: where the address, checksum and size come from (repository, file, line), and what
            is known of the host's state.
    """

    url: str
    sha256: str = ""
    md5: str = ""
    size: int | None = None
    evidence: str = ""

    @property
    def known_hash(self) -> str | None:
        """The checksum in ``pooch``'s ``"alg:hex"`` form (None: none published)."""
        if self.sha256:
            return f"sha256:{self.sha256}"
        return f"md5:{self.md5}" if self.md5 else None

    @property
    def file_name(self) -> str:
        """The archive's file name (the last part of its address)."""
        return self.url.split("?")[0].rstrip("/").rsplit("/", 1)[-1]


@dataclass(frozen=True)
class Source:
    """One archive layout a dataset is prepared from.

    Attributes:
        layout: the manifest's ``source_layout``.
        reader: the :class:`~src.data.readers.Reader` subclass of :mod:`src.data.readers` that reads it
            (``""``: generated, nothing to read). Layouts are detected in registry order: a catch-all
            layout (any mesh file) comes last.
        archive: what such an archive holds, for messages.
        mirrors: the hosts ``prepare --download`` tries, in order (live mirrors first, the original
            host last); empty: nothing to download.
        as_provided: ``""`` for meshes sampled here (``num_samplings`` x ``num_points``); else the points
            are stored as provided, one sampling per shape, and this is the cache's ``pair_sampling``.
        one_process: its shapes are rows of large files: read in one process (each file read once).
        axes: its axis convention, as measured (``""``: not measured); ``prepare --swap-yz`` maps the
            y-up convention of the PointNet++ resampled archive and the meshes' z-up one into each other.
    """

    layout: str
    reader: str
    archive: str
    mirrors: tuple[Mirror, ...] = ()
    as_provided: str = ""
    one_process: bool = False
    axes: str = ""

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
    def downloads(self) -> tuple[Source, ...]:
        """Its layouts that ``prepare --download`` can fetch; the first is fetched by default."""
        return tuple(s for s in self.sources if s.mirrors)

    @property
    def build_defaults(self) -> dict[str, int]:
        """A generated dataset's build defaults (``data.build`` of its config), the samplings included."""
        return {**self.build, "num_samplings": self.num_samplings, "num_points": self.num_points}


MODELNET40_CATEGORIES = "src.data.categories: the 40 categories of shape_names.txt, the official halves"

# Where each download comes from. A checksum is recorded (and verified) only where a loader that
# checks it after every download publishes it; no host publishes a size, so the structure of what
# arrives (a readable archive in the expected layout) is verified instead.
_PRINCETON_MD5 = "79bcee68fdf02f581938ba15f4cdca51"  # see the evidence of the first mirror below
_PRINCETON = (
    Mirror("https://modelnet.cs.princeton.edu/ModelNet40.zip", md5=_PRINCETON_MD5,
           evidence="original host; url: arthurdjn/pytorch-pointcloud torch_pointcloud/datasets/modelnet.py, "
                    "class ModelNet40 (data_url + resource); md5: the same class (its download checks it after each "
                    "transfer)"),
    Mirror("http://modelnet.cs.princeton.edu/ModelNet40.zip", md5=_PRINCETON_MD5,
           evidence="original host over http; url: pyg-team/pytorch_geometric torch_geometric/datasets/modelnet.py:83 "
                    "(kept when ModelNet10's url was changed, e574f59, 2025-09-01); md5: as above"),
)
_H5_ZIP = "modelnet40_ply_hdf5_2048.zip"
_POINTNET_H5 = (
    Mirror(f"https://huggingface.co/datasets/Msun/modelnet40/resolve/main/{_H5_ZIP}",
           evidence="mirror; ma-xu/pointMLP-pytorch classification_ModelNet40/data.py:16 names it as the source of "
                    "its release asset (f74ae62, 2024-11-25, 'Update modenet40 dataset link'); no checksum published"),
    Mirror(f"https://github.com/ma-xu/pointMLP-pytorch/releases/download/Modenet40_dataset/{_H5_ZIP}",
           evidence="mirror; ma-xu/pointMLP-pytorch classification_ModelNet40/data.py:17, the url its loader "
                    "downloads since f74ae62 (the Stanford url commented out on line 14); no checksum published"),
    Mirror(f"https://shapenet.cs.stanford.edu/media/{_H5_ZIP}",
           evidence="original host (charlesq34/pointnet provider.py:13, '416MB' in README.md:40; "
                    "yewzijian/RPMNet src/data_loader/datasets.py:227), replaced by the mirrors above in "
                    "pointMLP's loader; guochengqian/openpoints dataset/modelnet/modelnet40_ply_2048_loader.py:70 "
                    "declares md5 c9ab8e6dfb16f67afdab25e155c79e59 for it but its load_data never checks it: "
                    "not enforced here"),
)
_POINTNET2_RESAMPLED = (
    Mirror("https://huggingface.co/datasets/Pointcept/modelnet40_normal_resampled-compressed/resolve/main/"
           "modelnet40_normal_resampled.tar.gz", md5="46ed374f8ef5f7504ec4870298772ac2",
           evidence="mirror; Pointcept/Pointcept README.md:519 (added 06b802a, 2025-03-27); file name and md5: "
                    "arthurdjn/pytorch-pointcloud torch_pointcloud/datasets/modelnet.py, class "
                    "ModelNetNormalResampled (checked after each download by its download)"),
    Mirror("https://shapenet.cs.stanford.edu/media/modelnet40_normal_resampled.zip",
           evidence="original host (charlesq34/pointnet2 README.md:61, '1.6GB'; Pointcept "
                    "pointcept/datasets/modelnet.py:5); no checksum published"),
)

_NPY_COMMIT = "76fa94eff342546c58ba5c294ae22c4ef889f9c4"
_PER_SHAPE_NPY = (
    Mirror(f"https://github.com/prasadsawant5/PointNet/archive/{_NPY_COMMIT}.zip",
           evidence="original host: GitHub's archive of prasadsawant5/PointNet at 76fa94e, whose ModelNet40/"
                    "<category>/{train,test}/*.npy hold the official splits, 1,024 points a shape; GitHub publishes no "
                    "checksum of its generated archives"),
)
#: The axis conventions measured on the real archives (a median 0.011 apart after (x, y, z) -> (x, z, y)).
Z_UP = "z up: the ModelNet40 meshes' own axes"
Y_UP = "y up: the meshes' y and z swapped"

DATASETS: tuple[Dataset, ...] = (
    Dataset(
        "modelnet40", "ModelNet40: the Princeton meshes or PointNet's h5 points", num_samplings=40, num_points=2048,
        categories=MODELNET40_CATEGORIES,
        sources=(
            Source("princeton_off", "PrincetonOffReader", "Princeton meshes (ModelNet40/<category>/{train,test}/*.off)",
                   mirrors=_PRINCETON, axes=Z_UP),
            Source("pointnet_h5", "PointNetH5Reader",
                   "PointNet h5 (modelnet40_ply_hdf5_2048: ply_data_*.h5 + shape_names.txt)",
                   mirrors=_POINTNET_H5,
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
                   mirrors=_POINTNET2_RESAMPLED,
                   as_provided="disjoint_subsets", axes=Y_UP),
        ),
    ),
    Dataset(
        "modelnet40_npy", "ModelNet40 as one NumPy file a shape (e.g. 1,024 points, z up)",
        categories=MODELNET40_CATEGORIES,
        sources=(
            Source("per_shape_npy", "NumpyShapeReader",
                   "one .npy a shape (<category>/{train,test}/<category>_NNNN.npy: (N, 3) points or (N, 6) with "
                   "normals; withheld_test_ids.txt names test files left out)",
                   mirrors=_PER_SHAPE_NPY, as_provided="single_sampling", axes=Z_UP),
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
