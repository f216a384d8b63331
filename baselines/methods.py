"""Every registration method of the comparison, one record each (``methods.yaml``); everything else is derived.

A :class:`Method` holds a method's facts: its key (``get_registrator(key)``, ``conf/model/<key>.yaml``
for a learned one), display name, kind, what registers (a classical method's lazy ``"module:Class"``,
a learned method's network ``_target_``), its place in the paper's tables, its citation and aliases.
Derived from :data:`METHODS`: the registry of :mod:`baselines.registry`, the learned adapters of
:mod:`baselines.learned.adapter`, the display names and the row order of :mod:`benchmarks.tables`,
the matching with the paper's tables (:func:`benchmarks.tables.paper.method_key`), the grid's default
method list and ``method_options`` (:mod:`benchmarks.grid.plan`), and the speed tables' default methods
and column order (:mod:`benchmarks.speed`). Published weights name their
method (``Published.method`` in :mod:`baselines.learned.published`).

Adding a method means adding its record to ``baselines/methods.yaml`` (and its code);
``tests/unit/baselines/test_methods.py`` checks that every record composes, registers a pair and
appears in the tables.

    python -m baselines                  # the registry as a Markdown table: key, name, kind, paper, code

Light on purpose: importing it imports no Open3D, torch or Hydra.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

from src.utils.errors import ConfigError
from src.utils.records import load_records

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


#: The records of ``baselines/methods.yaml``, in its order.
METHODS: tuple[Method, ...] = load_records(Path(__file__).with_name("methods.yaml"), Method)


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
