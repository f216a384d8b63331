"""No machine's own paths in the repository: source, configs, docs and tests name paths relative to
the repository (``src.utils.paths``), through ``$OMNET_CACHE_DIR`` / ``$OMNET_SHARED_DIR``, or under ``/tmp``."""

from __future__ import annotations

import re
import shutil
import tempfile

import pytest

from tests.helpers.paths import ROOT
from tests.helpers.tracked import tracked_texts

#: Top folders of machines (written without their slashes, so that this file names no such path itself).
MACHINE_ROOTS = tuple(f"/{name}/" for name in
                      ("work", "root", "home", "Users", "mnt", "scratch", "data", "opt", "media", "nfs"))
WORK, ROOT_HOME, HOME = MACHINE_ROOTS[:3]
# an absolute path: a machine root not continuing a word, a relative path or a URL (``../shared/data/`` passes)
MACHINE_PATH = re.compile(r"(?<![\w.~/-])(?:" + "|".join(map(re.escape, MACHINE_ROOTS)) + ")")


def machine_paths(text: str) -> list[tuple[int, str]]:
    """(line number, line) of each line of ``text`` that names an absolute path on a machine root."""
    return [(i, line.strip()) for i, line in enumerate(text.splitlines(), 1) if MACHINE_PATH.search(line)]


def test_the_pattern_finds_machine_paths_only():
    found = machine_paths(f"cache: {HOME}me/.cache\nsee `{WORK}.mirror/x`\nrun dir={ROOT_HOME}run\n"
                          f"../shared/data/x.zip\n{tempfile.gettempdir()}/x\nhttps://example.org{HOME}x\n~/.cache/omnet\n")
    assert [i for i, _ in found] == [1, 2, 3]


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="needs a git checkout")
def test_no_tracked_file_names_a_machine_path():
    offending = [f"{name}:{i}: {line[:120]}" for name, text in tracked_texts() for i, line in machine_paths(text)]
    assert not offending, "absolute machine paths (use paths relative to the repository, an env var or /tmp):\n" + \
        "\n".join(offending)
