"""docs/training.md's expected output of set-up command 1 against a run: the numbers it shows (the rows that do not
depend on the run's training) match exactly; what it shows as ``…`` (times, the run's own row) is checked by its
structure. The run is command 1's (``+exp=unseen_shapes data=synthetic trainer=smoke``, so the same 32 test pairs)
with one training step of a narrower network, which changes only the run's own row."""

from __future__ import annotations

import contextlib
import io
import re

import pytest

from benchmarks.demo import main as demo_main
from src.train import train
from tests.helpers.markdown import markdown_table
from tests.helpers.paths import ROOT
from tests.helpers.registration_helpers import compose_config

VARIES = "…"
NUMBER = re.compile(r"^-?\d[\d,]*(\.\d+)?$")


def documented_output() -> str:
    """The text block under the heading "What set-up command 1 prints"."""
    page = (ROOT / "docs" / "training.md").read_text()
    section = page.split("## What set-up command 1 prints", 1)[1]
    return re.search(r"```text\n(.*?)```", section, re.S).group(1)


@pytest.fixture(scope="module")
def printed(tmp_path_factory) -> str:
    """What ``python -m benchmarks.demo`` prints after the run."""
    tmp = tmp_path_factory.mktemp("setup")
    train(compose_config("+exp=unseen_shapes", "data=synthetic", "trainer=smoke", f"data.cache_root={tmp / 'cache'}",
                         f"output_dir={tmp / 'run'}", "model_scale=0.0625", "trainer.max_steps=1",
                         "trainer.val_check_interval=1"))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert demo_main(["--run", str(tmp / "run")]) == 0
    return out.getvalue()


def _pattern(label: str) -> str:
    """A documented label as a pattern: exact, except that numbers and ``…`` stand for any number."""
    return r"[\d,.]+".join(re.escape(part) for part in re.split(r"…|\d+(?:[.,]\d+)*", label))


def test_the_documented_table_matches_a_run(printed):
    _, documented = markdown_table(documented_output())
    _, actual = markdown_table(printed)
    assert list(actual.columns) == list(documented.columns)
    assert len(actual) == len(documented)
    for (_, want), (_, got) in zip(documented.iterrows(), actual.iterrows()):
        if VARIES in want["Method"]:  # the run's own row: its steps and width are this run's
            assert re.fullmatch(_pattern(want["Method"]), got["Method"]), (want["Method"], got["Method"])
        else:
            assert got["Method"] == want["Method"]
        for column in documented.columns[1:]:
            if want[column] == VARIES:
                assert NUMBER.match(got[column]), (got["Method"], column, got[column])
            else:  # the same on every machine
                assert got[column] == want[column], (got["Method"], column, got[column], want[column])


def test_the_documented_notes_match_a_run_in_structure(printed):
    note = next(line for line in documented_output().splitlines() if line.startswith("- "))
    claim = note.split(") is ", 1)[1].split(":", 1)[0]  # "a pipeline check, not a result"
    assert any(line.startswith("- OMNet (this run: ") and f") is {claim}:" in line for line in printed.splitlines())
    assert re.search(r"^demo: \d+ s$", printed, re.M)
