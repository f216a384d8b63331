"""Markdown reports read back as data: each pipe table a frame of its cells, so that tests check the
cells a report holds (against the numbers it was made from), not substrings of its text."""

from __future__ import annotations

import re

import pandas as pd

_RULE = re.compile(r"^\|(\s*:?-+:?\s*\|)+$")


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip()[1:-1].split("|")]


def markdown_tables(text: str) -> list[tuple[str, pd.DataFrame]]:
    """Every pipe table of ``text``, in order: (its title: the nearest non-empty line above it without
    ``**``, "" if none; a frame of its cells as strings, columns = the header row)."""
    lines, tables, i = text.splitlines(), [], 0
    while i < len(lines) - 1:
        if lines[i].lstrip().startswith("|") and _RULE.match(lines[i + 1].strip()):
            header, j = _cells(lines[i]), i + 2
            rows = []
            while j < len(lines) and lines[j].lstrip().startswith("|"):
                rows.append(_cells(lines[j]))
                j += 1
            assert all(len(row) == len(header) for row in rows), f"ragged table under {lines[i]!r}"
            title = next((line.strip().strip("*") for line in reversed(lines[:i]) if line.strip()), "")
            tables.append((title, pd.DataFrame(rows, columns=header)))
            i = j
        else:
            i += 1
    return tables


def markdown_table(text: str, title: str = "") -> tuple[str, pd.DataFrame]:
    """The one table of ``text`` whose title starts with ``title``: (full title, frame)."""
    found = [(t, frame) for t, frame in markdown_tables(text) if t.startswith(title)]
    assert len(found) == 1, f"{len(found)} tables titled {title!r}...: {[t for t, _ in markdown_tables(text)]}"
    return found[0]
