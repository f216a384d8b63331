"""Every pointer of the code to the documentation resolves: ``README.md`` or ``docs/<page>.md``, with or without a
section (``(docs/results.md: Shipped checkpoints)``), names a file that exists and a heading it has. Pointers to a
section of the README that moved to docs/ (``README: Shipped checkpoints``) are found too and fail."""

from __future__ import annotations

import re
from pathlib import Path

from tests.helpers.paths import ROOT

FOLDERS = ("src", "baselines", "benchmarks", "conf")
SUFFIXES = (".py", ".yaml", ".sh")
#: ``README``, ``README.md`` or ``docs/<page>.md``, then optionally ``: Heading`` or ``, "Heading"``: the heading
#: runs to a bracket, a quote, a comma, a semicolon, a full stop or `` (``. The authors' READMEs are spoken of
#: as "the README's ..." or "official README", never with a capitalised section after a colon.
POINTER = re.compile(r'(?<![\w/.])(README(?:\.md)?|docs/[\w/-]+\.md)(?::|,)? ?"?([A-Z][^"(),;\n.]*?)?(?=["),;\n.]| \(|$)')
HEADING = re.compile(r"^#+\s+(.*?)\s*$", re.M)


def code_files() -> list[Path]:
    return [p for folder in FOLDERS for p in sorted((ROOT / folder).rglob("*"))
            if p.suffix in SUFFIXES and p.is_file() and "results" not in p.relative_to(ROOT).parts]


def pointers(text: str) -> list[tuple[str, str | None]]:
    """(file, heading or None) of every pointer in ``text``."""
    return [(target, (heading or "").strip() or None) for target, heading in POINTER.findall(text)]


def resolves(target: str, heading: str | None) -> bool:
    page = ROOT / (target if target.endswith(".md") else f"{target}.md")
    if not page.is_file():
        return False
    headings = HEADING.findall(re.sub(r"```.*?```", "", page.read_text(), flags=re.S))  # not a code block's comments
    return heading is None or any(h == heading or h.startswith(f"{heading} (") for h in headings)


def test_the_pattern_reads_the_pointers_of_the_code():
    assert pointers("see (docs/results.md: Shipped checkpoints) and docs/recipes.md.") == [
        ("docs/results.md", "Shipped checkpoints"), ("docs/recipes.md", None)]
    assert pointers('first (README, "Real ModelNet40 shapes"); then README: Benchmarks, sweeps') == [
        ("README", "Real ModelNet40 shapes"), ("README", "Benchmarks")]
    assert pointers("(README.md: Set-up, command 1)") == [("README.md", "Set-up")]
    assert resolves("README.md", "Set-up") and resolves("docs/results.md", "Expected runtimes")
    assert not resolves("README", "Shipped checkpoints") and not resolves("docs/nowhere.md", None)


def test_every_pointer_of_the_code_resolves():
    found = {(str(path.relative_to(ROOT)), target, heading) for path in code_files()
             for target, heading in pointers(path.read_text())}
    assert len(found) > 10  # the code does point to its documentation
    broken = sorted(f"{path}: {target}" + (f": {heading}" if heading else "") for path, target, heading in found
                    if not resolves(target, heading))
    assert not broken, "pointers to no file or heading:\n" + "\n".join(broken)
