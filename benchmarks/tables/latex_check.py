"""A small structural checker for generated LaTeX tables (no TeX engine needed).

:func:`check_latex` reports unbalanced braces, mismatched ``\\begin``/``\\end`` environments and
tabular rows whose cell count (``&`` separators, ``\\multicolumn`` spans) differs from the column
specification. :func:`tabular_rows` splits a tabular into rows of cell strings, e.g. to read the
numbers back. :func:`compile_latex` runs ``pdflatex`` when one is installed, keeps the PDF, and names a missing
package in one line (:func:`latex_failure`).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from pathlib import Path

_RULES = re.compile(r"\\(?:toprule|midrule|bottomrule|hline|addlinespace)(?:\[[^\]]*\])?|\\cmidrule(?:\([^)]*\))?\{[^}]*\}")


def strip_comments(text: str) -> str:
    return "\n".join(re.sub(r"(?<!\\)%.*$", "", line) for line in text.splitlines())


def _balanced_groups(text: str) -> list[str]:
    problems, depth = [], 0
    for i, ch in enumerate(text):
        if ch in "{}" and i > 0 and text[i - 1] == "\\" and (i < 2 or text[i - 2] != "\\"):
            continue  # \{ or \}
        if ch == "{":
            depth += 1
        elif ch == "}":
            depth -= 1
            if depth < 0:
                problems.append(f"unmatched '}}' at offset {i}")
                depth = 0
    if depth:
        problems.append(f"{depth} unclosed '{{'")
    return problems


def _read_group(text: str, start: int) -> tuple[str, int]:
    """The content of the brace group opening at ``text[start] == '{'`` and the index after it."""
    assert text[start] == "{"
    depth = 0
    for i in range(start, len(text)):
        if text[i] == "{" and text[i - 1] != "\\":
            depth += 1
        elif text[i] == "}" and text[i - 1] != "\\":
            depth -= 1
            if depth == 0:
                return text[start + 1 : i], i + 1
    raise ValueError("unclosed brace group")


def count_columns(spec: str) -> int:
    """Columns of a tabular spec: ``l*{12}{c}`` -> 13; ``|``, ``@{..}``, ``!{..}``, ``>{..}``, ``<{..}`` add none."""
    n, i = 0, 0
    while i < len(spec):
        ch = spec[i]
        if ch == "*":
            count, i = _read_group(spec, i + 1)
            inner, i = _read_group(spec, i)
            n += int(count) * count_columns(inner)
            continue
        if ch in "@!><":
            _, i = _read_group(spec, i + 1)
            continue
        if ch in "pmbwWX" and i + 1 < len(spec) and spec[i + 1] == "{":
            _, i = _read_group(spec, i + 1)
            n += 1
            continue
        if ch.isalpha():
            n += 1
        i += 1
    return n


def _split_top(text: str, sep: str) -> list[str]:
    """Split on ``sep`` outside brace groups (``\\\\`` or ``&``; escaped ``\\&`` is kept)."""
    parts, depth, start, i = [], 0, 0, 0
    while i < len(text):
        ch = text[i]
        if ch == "\\" and text.startswith(sep, i) and sep == "\\\\" and depth == 0:
            parts.append(text[start:i])
            i += 2
            start = i
            continue
        if ch == "\\":
            i += 2  # skip escaped characters and the first letter of commands
            continue
        if ch == "{":
            depth += 1
        elif ch == "}":
            depth -= 1
        elif ch == sep and depth == 0:
            parts.append(text[start:i])
            start = i + 1
        i += 1
    parts.append(text[start:])
    return parts


def tabulars(text: str) -> list[tuple[str, str]]:
    """(column spec, body) of every ``tabular``/``tabular*`` in ``text``."""
    text = strip_comments(text)
    found = []
    for match in re.finditer(r"\\begin\{tabular\*?\}", text):
        i = match.end()
        if match.group(0).endswith("*}"):
            _, i = _read_group(text, i)  # width
        while text[i].isspace():
            i += 1
        if text[i] == "[":
            i = text.index("]", i) + 1
        spec, i = _read_group(text, i)
        end = text.index("\\end{tabular", i)
        found.append((spec, text[i:end]))
    return found


def tabular_rows(body: str) -> list[list[str]]:
    """Rows (lists of stripped cell strings) of a tabular body, rule-only lines dropped."""
    rows = []
    for raw in _split_top(body, "\\\\"):
        line = _RULES.sub("", raw).strip()
        if not line:
            continue
        rows.append([cell.strip() for cell in _split_top(line, "&")])
    return rows


def _span(cell: str) -> int:
    match = re.match(r"\\multicolumn\{(\d+)\}", cell.strip())
    return int(match.group(1)) if match else 1


def check_latex(text: str) -> list[str]:
    """Problems found in ``text`` (empty list: structurally fine)."""
    clean = strip_comments(text)
    problems = _balanced_groups(clean)
    stack: list[str] = []
    for match in re.finditer(r"\\(begin|end)\{([^}]*)\}", clean):
        kind, name = match.groups()
        if kind == "begin":
            stack.append(name)
        elif not stack:
            problems.append(f"\\end{{{name}}} without \\begin")
        elif stack[-1] != name:
            problems.append(f"\\end{{{name}}} closes \\begin{{{stack[-1]}}}")
            stack.pop()
        else:
            stack.pop()
    problems += [f"\\begin{{{name}}} never closed" for name in stack]
    if problems:
        return problems
    for t, (spec, body) in enumerate(tabulars(text)):
        ncols = count_columns(spec)
        for r, row in enumerate(tabular_rows(body)):
            width = sum(_span(cell) for cell in row)
            if width != ncols:
                problems.append(f"tabular {t}, row {r}: {width} cells, the spec {spec!r} has {ncols}: {' & '.join(row)[:80]}")
    return problems


_MISSING_FILE = re.compile(r"! LaTeX Error: File `([^']+)' not found")


def latex_failure(log: str) -> str:
    """One line for a failed compilation: the missing package (``booktabs.sty`` not found) and how to get
    it, else the log's first error line."""
    missing = _MISSING_FILE.search(log)
    if missing:
        name = missing.group(1)
        package = name.removesuffix(".sty")
        return (f"the LaTeX package {package} is not installed ({name} not found): install it (TeX Live: `tlmgr install "
                f"{package}`; Debian: apt-get install texlive-latex-recommended) or compile the .tex elsewhere")
    errors = [line for line in log.splitlines() if line.startswith("!")]
    return errors[0] if errors else "pdflatex failed (no error line in its log)"


def compile_latex(text: str, pdf: Path, engine: str = "pdflatex", timeout: float = 60) -> tuple[bool | None, str]:
    """Compile a standalone document into ``pdf``: (True, ""), (False, :func:`latex_failure`'s line), or
    (None, reason) when no engine is installed."""
    exe = shutil.which(engine)
    if exe is None:
        return None, f"{engine} not installed"
    with tempfile.TemporaryDirectory() as tmp:
        source = Path(tmp) / "table.tex"
        source.write_text(text)
        result = subprocess.run(
            [exe, "-interaction=nonstopmode", "-halt-on-error", source.name], cwd=tmp, capture_output=True,
            text=True, timeout=timeout,
        )
        built = Path(tmp) / "table.pdf"
        if result.returncode != 0 or not built.is_file():
            return False, latex_failure(result.stdout)
        shutil.copyfile(built, pdf)
        return True, ""
