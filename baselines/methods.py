"""Every registration method of the comparison, one record each; everything else is derived.

A :class:`Method` holds a method's facts: its key (``get_registrator(key)``, ``conf/model/<key>.yaml``
for a learned one), display name, kind, what registers (a classical method's lazy ``"module:Class"``,
a learned method's network ``_target_``), its place in the paper's tables, its citation and aliases.
Derived from :data:`METHODS`: the registry of :mod:`baselines.registry`, the learned adapters of
:mod:`baselines.learned.adapter`, the display names and the row order of :mod:`benchmarks.tables`,
the matching with the paper's tables (:func:`benchmarks.paper.method_key`), the grid's default
method list and ``method_options`` (:mod:`benchmarks.grid_plan`), and the speed tables' default methods
and column order (:mod:`benchmarks.speed`). Published weights name their
method (``Published.method`` in :mod:`baselines.learned.published`).

Adding a method means adding its record here (and its code); ``tests/test_methods.py`` checks that
every record composes, registers a pair and appears in the tables.

    python -m baselines                  # the registry as a Markdown table: key, name, kind, paper, code

Light on purpose: importing it imports no Open3D, torch or Hydra.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Literal, get_args

from src.errors import ConfigError

Kind = Literal["classical", "learned"]
KINDS: tuple[str, ...] = get_args(Kind)
#: The module whose generated classes wrap learned methods (one class per learned record).
ADAPTER_MODULE = "baselines.learned.adapter"
#: The paper's orders of methods: ``table1`` (rows of Tables 1 and 2) and ``speed`` (columns of the
#: supplementary speed table); see :func:`paper_rank`.
PAPER_TABLES = ("table1", "speed")


@dataclass(frozen=True)
class Method:
    """One registration method.

    Attributes:
        key: registry name (``get_registrator(key)``, ``benchmark.methods``, ``method_options.<key>``);
            a learned method's model config is ``conf/model/<key>.yaml``.
        display: its name in tables, plots and labels.
        kind: ``classical`` (registers as it is) or ``learned`` (needs weights).
        paper: the citation of its paper (``""`` for the identity).
        code: the authors' code; for ICP, whose paper has none, the implementation that runs here.
        target: classical only: the Registrator class, ``"module:Class"`` (imported on first use).
        network: learned only: the ``_target_`` of its network (``model.network`` of its model config).
        aliases: other names it answers to (besides spellings of ``key`` and ``display`` with other
            case, spaces, hyphens or underscores).
        table1: position of its row in the paper's Tables 1 and 2 (None: not in them).
        speed: position of its column in the speed tables: the paper's supplementary speed table, with
            Go-ICP and Symmetric ICP (not in it) after FGR as in Table 1 (None: not in them).
        ours: the paper's own method: last in every table, after methods the paper does not have.
        default_grid: part of the grid's default method list (``benchmark.methods``).
        slow: seconds a pair or more (a global search, a dense probabilistic fit): left out of the speed
            tables' default methods unless named (the paper's speed table has no Go-ICP).
    """

    key: str
    display: str
    kind: Kind
    paper: str = ""
    code: str = ""
    target: str = ""
    network: str = ""
    aliases: tuple[str, ...] = ()
    table1: int | None = None
    speed: int | None = None
    ours: bool = False
    default_grid: bool = False
    slow: bool = False

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"method {self.key}: kind must be one of {KINDS}, got {self.kind!r}")
        if (self.kind == "classical") != (":" in self.target) or (self.kind == "learned") != bool(self.network):
            raise ValueError(f"method {self.key}: a classical method names its target, a learned one its network")

    @property
    def registrator(self) -> str:
        """The Registrator class as a lazy ``"module:Class"``: a classical method's own; for a learned
        one the adapter class named after its network's class (``src.models.omnet.OMNet`` → ``OMNetRegistrator``)."""
        if self.kind == "classical":
            return self.target
        return f"{ADAPTER_MODULE}:{self.network.rpartition('.')[2]}Registrator"

    @property
    def grid_options(self) -> dict[str, Any]:
        """The grid's default ``method_options.<key>``: a learned method's ``checkpoint`` and ``weights``
        slots (so that ``method_options.<key>.checkpoint=PATH`` is a plain override), nothing for a
        classical one."""
        return {"checkpoint": None, "weights": None} if self.kind == "learned" else {}


METHODS: tuple[Method, ...] = (
    Method("icp", "ICP", "classical", target="baselines.classical.icp:ICP", table1=0, speed=0, default_grid=True,
           paper="Besl & McKay, A Method for Registration of 3-D Shapes, TPAMI 1992",
           code="https://github.com/isl-org/Open3D"),
    Method("fgr", "FGR", "classical", target="baselines.classical.fgr:FGR", table1=3, speed=1, default_grid=True,
           paper="Zhou, Park & Koltun, Fast Global Registration, ECCV 2016",
           code="https://github.com/isl-org/FastGlobalRegistration"),
    Method("goicp", "Go-ICP", "classical", target="baselines.classical.goicp:GoICP", table1=1, speed=2,
           default_grid=True, slow=True,
           paper="Yang, Li, Campbell & Jia, Go-ICP: A Globally Optimal Solution to 3D ICP Point-Set Registration, "
                 "TPAMI 2016",
           code="https://github.com/yangjiaolong/Go-ICP"),
    Method("symmetric_icp", "Symmetric ICP", "classical", target="baselines.classical.symmetric_icp:SymmetricICP",
           aliases=("symicp",), table1=2, speed=3, default_grid=True,
           paper="Rusinkiewicz, A Symmetric Objective Function for ICP, ACM TOG (SIGGRAPH) 2019",
           code="https://gfx.cs.princeton.edu/proj/trimesh2/"),
    Method("ransac", "RANSAC (FPFH)", "classical", target="baselines.classical.ransac:RANSAC", default_grid=True,
           aliases=("ransac_fpfh",),
           paper="Fischler & Bolles, Random Sample Consensus, CACM 1981; features: Rusu, Blodow & Beetz, Fast Point "
                 "Feature Histograms (FPFH) for 3D Registration, ICRA 2009",
           code="https://github.com/isl-org/Open3D"),
    Method("ransac_icp", "RANSAC (FPFH) + ICP", "classical", target="baselines.classical.ransac:RANSACICP",
           default_grid=True,
           paper="Fischler & Bolles, Random Sample Consensus, CACM 1981; refined by ICP (Besl & McKay, TPAMI 1992)",
           code="https://github.com/isl-org/Open3D"),
    Method("point_to_plane_icp", "Point-to-plane ICP", "classical",
           target="baselines.classical.open3d_icp:PointToPlaneICP", aliases=("plane_icp",), default_grid=True,
           paper="Chen & Medioni, Object Modelling by Registration of Multiple Range Images, IVC 1992",
           code="https://github.com/isl-org/Open3D"),
    Method("gicp", "GICP", "classical", target="baselines.classical.open3d_icp:GeneralizedICP",
           aliases=("generalized_icp",), default_grid=True,
           paper="Segal, Haehnel & Thrun, Generalized-ICP, RSS 2009",
           code="https://github.com/isl-org/Open3D"),
    Method("small_gicp", "small_gicp", "classical", target="baselines.classical.smallgicp:SmallGICP",
           default_grid=True,
           paper="Koide, small_gicp: Efficient and parallel algorithms for point cloud registration, JOSS 2024",
           code="https://github.com/koide3/small_gicp"),
    # CPD (~7 s a pair of 768 points on 2 cores) and FilterReg (probreg: compiled from its sdist) are named, not default
    Method("cpd", "CPD", "classical", target="baselines.classical.cpd:CPD", aliases=("coherent_point_drift",), slow=True,
           paper="Myronenko & Song, Point Set Registration: Coherent Point Drift, TPAMI 2010",
           code="https://github.com/siavashk/pycpd"),
    Method("filterreg", "FilterReg", "classical", target="baselines.classical.filterreg:FilterReg",
           paper="Gao & Tedrake, FilterReg: Robust and Efficient Probabilistic Point-Set Registration using Gaussian "
                 "Filter and Twist Parameterization, CVPR 2019",
           code="https://github.com/neka-nat/probreg"),
    Method("identity", "Identity (no registration)", "classical", target="baselines.classical.identity:Identity"),
    Method("omnet", "OMNet", "learned", network="src.models.omnet.OMNet", aliases=("ours",), ours=True,
           paper="Xu, Liu, Ye, Zhang, Zeng & Liu, OMNet: Learning Overlapping Mask for Partial-to-Partial Point "
                 "Cloud Registration, ICCV 2021",
           code="https://github.com/megvii-research/OMNet"),
    Method("dcp", "DCP", "learned", network="baselines.learned.dcp.DCP", table1=5, speed=5,
           paper="Wang & Solomon, Deep Closest Point: Learning Representations for Point Cloud Registration, "
                 "ICCV 2019",
           code="https://github.com/WangYueFt/dcp"),
    Method("prnet", "PRNet", "learned", network="baselines.learned.prnet.PRNet", table1=7, speed=6,
           paper="Wang & Solomon, PRNet: Self-Supervised Learning for Partial-to-Partial Registration, NeurIPS 2019",
           code="https://github.com/WangYueFt/prnet"),
    Method("rpmnet", "RPMNet", "learned", network="baselines.learned.rpmnet.RPMNet", table1=6, speed=8,
           paper="Yew & Lee, RPM-Net: Robust Point Matching using Learned Features, CVPR 2020",
           code="https://github.com/yewzijian/RPMNet"),
    Method("idam", "IDAM", "learned", network="baselines.learned.idam.IDAM", table1=9, speed=9,
           paper="Li, Zhang, Zhu, Tang & Yin, Iterative Distance-Aware Similarity Matrix Convolution with "
                 "Mutual-Supervised Point Elimination for Efficient Point Cloud Registration, ECCV 2020",
           code="https://github.com/jiahaowork/idam"),
    Method("pointnetlk", "PointNetLK", "learned", network="baselines.learned.pointnetlk.PointNetLK", table1=4,
           speed=4,
           paper="Aoki, Goforth, Srivatsan & Lucey, PointNetLK: Robust & Efficient Point Cloud Registration using "
                 "PointNet, CVPR 2019",
           code="https://github.com/hmgoforth/PointNetLK"),
    Method("pointnetlk_revisited", "PointNetLK-Revisited", "learned",
           network="baselines.learned.pointnetlk_revisited.PointNetLKRevisited",
           paper="Li, Pontes & Lucey, PointNetLK Revisited, CVPR 2021",
           code="https://github.com/Lilac-Lee/PointNetLK_Revisited"),
    Method("fmr", "FMR", "learned", network="baselines.learned.fmr.FMR", table1=8, speed=7,
           paper="Huang, Mei & Zhang, Feature-Metric Registration: A Fast Semi-Supervised Approach for Robust Point "
                 "Cloud Registration without Correspondences, CVPR 2020",
           code="https://github.com/XiaoshuiHuang/fmr"),
    Method("deepgmr", "DeepGMR", "learned", network="baselines.learned.deepgmr.DeepGMR", table1=10, speed=10,
           paper="Yuan, Eckart, Kim, Jampani, Fox & Kautz, DeepGMR: Learning Latent Gaussian Mixture Models for "
                 "Registration, ECCV 2020",
           code="https://github.com/wentaoyuan/deepgmr"),
)


def spelling(name: Any) -> str:
    """A name without case, spaces, commas, hyphens and underscores (``Symmetric ICP`` = ``symmetric_icp``)."""
    return re.sub(r"[\s,_\-]+", "", str(name).strip().lower())


_BY_SPELLING: dict[str, Method] = {
    spelling(name): method for method in METHODS for name in (method.key, method.display, *method.aliases)
}


def find_method(name: Any) -> Method | None:
    """The method ``name`` (key, display name or alias, in any spelling) denotes, or None."""
    return _BY_SPELLING.get(spelling(name))


def get_method(name: Any) -> Method:
    """The method ``name`` denotes (ConfigError naming the known ones otherwise)."""
    method = find_method(name)
    if method is None:
        raise ConfigError(f"unknown method '{name}'; known: {', '.join(m.key for m in METHODS)}")
    return method


def learned_methods() -> list[Method]:
    """The learned methods, in registry order."""
    return [m for m in METHODS if m.kind == "learned"]


def method_of_network(target: str) -> Method | None:
    """The learned method whose network is ``target`` (a ``_target_``), or None."""
    return next((m for m in learned_methods() if m.network == target), None)


def display_name(name: str) -> str:
    """The display name of a method (key, alias or display name); other names unchanged."""
    method = find_method(name)
    return method.display if method else name


def paper_rank(name: str, table: str = "table1") -> tuple[int, int]:
    """Sort key of a method in the paper's order for ``table`` (:data:`PAPER_TABLES`): the paper's
    baselines in its order ``(0, position)``, then methods it does not have ``(1, 0)``, then its own
    method ``(2, 0)``."""
    if table not in PAPER_TABLES:
        raise ValueError(f"table must be one of {PAPER_TABLES}, got {table!r}")
    method = find_method(name)
    if method is not None and method.ours:
        return (2, 0)
    position = None if method is None else getattr(method, table)
    return (1, 0) if position is None else (0, position)


def default_grid_methods() -> list[str]:
    """The grid's default ``benchmark.methods``."""
    return [m.key for m in METHODS if m.default_grid]


def default_speed_methods() -> list[str]:
    """The speed tables' default methods: the grid's default classical ones but the slow ones, then every
    learned network, in registry order."""
    return [m.key for m in METHODS if m.default_grid and not m.slow] + [m.key for m in learned_methods()]


def markdown_table() -> str:
    """The registry as a Markdown table: key, name, kind, paper, code."""
    lines = ["| key | method | kind | paper | code |", "| --- | --- | --- | --- | --- |"]
    lines += [f"| `{m.key}` | {m.display} | {m.kind} | {m.paper or '-'} | {m.code or '-'} |" for m in METHODS]
    return "\n".join(lines) + "\n"
