"""The threads study's summary: pairs/s summed over a set-up's processes, the median over rounds."""

import pandas as pd
import pytest

from benchmarks.studies.threads.measure import main, summary
from tests.helpers.markdown import markdown_table


def test_the_summary_sums_the_processes_of_a_setup_and_takes_the_median_round():
    rows = [{"setup": "1 run x 2 threads", "round": k, "threads": 2, "ms_per_step": 1000.0, "pairs_per_s": p,
             "mm_gflop_per_s": 100.0, "pct_of_mm": 50.0} for k, p in enumerate((16.0, 18.0, 20.0))]
    rows += [{"setup": "2 runs x 1 thread", "round": k, "threads": 1, "ms_per_step": 1500.0, "pairs_per_s": p,
              "mm_gflop_per_s": 60.0, "pct_of_mm": 80.0} for k, p in enumerate((12.0, 13.0, 14.0)) for _ in range(2)]
    _, table = markdown_table(summary(pd.DataFrame(rows), "cmd"))
    table = table.set_index("setup")
    assert table.loc["1 run x 2 threads", "pairs/s (all processes)"] == "18.00"
    assert table.loc["2 runs x 1 thread", "pairs/s (all processes)"] == "26.00"
    assert table.loc["2 runs x 1 thread", "vs 1 run x 2 threads"] == "1.44x"


def test_rounds_must_be_positive(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--out", "unused", "--rounds", "0"])
    assert stop.value.code == 2
    assert "--rounds must be at least 1" in capsys.readouterr().err
