"""The repository speaks of the framework and its users only: no tracked text names how it was built (the
work's issue numbers, its work sessions, a machine lent or borrowed for it and that machine's transfer limits).
The words are spelled out below in pieces, so that this file is the one exception."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from tests.helpers.paths import ROOT
from tests.helpers.tracked import tracked_texts

#: Phrases of the work rather than of the product, each a regular expression (case-insensitive).
PATTERNS = (
    "is" + r"sue ?#?\d+",                  # the tracker's numbers
    r"(?<!new_)\bses" + r"sions?\b",        # work sessions (not `start_new_session`)
    r"\bl" + r"ent\b", r"\bbor" + r"rowed\b", r"\bl" + r"ease\b",   # a machine someone else owns
    r"dev" + r"ice tool", r"per returned file",                      # the tool that carried files to it
)
WORDS = re.compile("|".join(PATTERNS), re.IGNORECASE)


def offending_lines(text: str) -> list[tuple[int, str]]:
    return [(i, line.strip()) for i, line in enumerate(text.splitlines(), 1) if WORDS.search(line)]


def test_the_patterns_find_the_words_of_the_work_only():
    text = ("fixed in is" + "sue 21\nthe first ses" + "sion's curve\na GPU l" + "ent for 15 minutes\n"
            "resumed from last.ckpt\nclient, talent, silent, released\nthe paper, §4.2\n")
    assert [i for i, _ in offending_lines(text)] == [1, 2, 3]


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="needs a git checkout")
def test_no_tracked_text_names_how_the_framework_was_made():
    this_file = Path(__file__).resolve().relative_to(ROOT).as_posix()
    offending = [f"{name}:{i}: {line[:140]}" for name, text in tracked_texts() if name != this_file
                 for i, line in offending_lines(text)]
    assert not offending, "words of how the framework was made (say what the product does, for its users):\n" + \
        "\n".join(offending)
