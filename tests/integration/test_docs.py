"""The README is the front door: its relative links and those of docs/ and benchmarks/ resolve, and every page
of docs/ is reachable from it."""

from __future__ import annotations

import re
from pathlib import Path

from tests.helpers.paths import ROOT

LINK = re.compile(r"\]\(([^)\s]+)\)")


def relative_links(page: Path) -> list[tuple[str, Path]]:
    links = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue  # a URL or an anchor of the same page
        links.append((target, (page.parent / target.split("#")[0]).resolve()))
    return links


def pages() -> list[Path]:
    """The README, docs/, and the result and study pages under benchmarks/."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "benchmarks").rglob("*.md"))]


def test_every_relative_link_resolves():
    broken = [f"{page.relative_to(ROOT)}: {target}" for page in pages() for target, path in relative_links(page)
              if not path.exists()]
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_every_docs_page_is_reachable_from_the_readme():
    seen, todo = set(), [(ROOT / "README.md").resolve()]
    while todo:
        page = todo.pop()
        if page in seen or page.suffix != ".md" or not page.is_file():
            continue
        seen.add(page)
        todo += [path / "README.md" if path.is_dir() else path for _, path in relative_links(page)]
    unreachable = [str(p.relative_to(ROOT)) for p in pages() if p.resolve() not in seen]
    assert not unreachable, f"pages no link from the README leads to: {unreachable}"


def test_the_readme_links_every_result_file():
    """Each file of benchmarks/results/ is linked from the README's Results, or is part of one that is (a summary
    table the linked report names)."""
    readme = (ROOT / "README.md").read_text()
    results = {p.name: p.read_text() for p in (ROOT / "benchmarks" / "results").glob("*.md")}
    linked = {name for name in results if f"(benchmarks/results/{name})" in readme}
    missing = sorted(name for name in set(results) - linked if not any(name in results[r] for r in linked))
    assert linked and not missing, f"result files the README's Results do not reach: {missing}"
