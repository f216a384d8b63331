"""The time-to-accuracy precision study: a tiny run writes a well-formed row of the verdict table, and the row's
numbers come from the runs as the table defines them."""

import pandas as pd
import pytest

from benchmarks.studies.precision.time_to_accuracy import COLUMNS, main, verdict_of
from src.run.precision import cpu_kind, load_verdicts, read_cpuinfo

OMNET = "src.models.omnet.OMNet"


def _tiny(tmp_path) -> list[str]:
    """3 seeds x 2 steps fitting 2 synthetic pairs of 128 points at width 1/16 (bf16 is emulated on a CPU without
    bf16 units: slower, and the study's speed numbers then say so, which is all a verdict row may claim here)."""
    return ["--method", "omnet", "--width", "0.0625", "--seeds", "0,1,2", "--target", "170", "--steps", "2",
            "--val-every", "1", "--pairs", "2", "--out", str(tmp_path / "out"),
            "+exp=unseen_shapes", "data=synthetic", "data.build.num_train_per_category=2",
            "data.build.num_test_per_category=1", "data.build.num_samplings=3", "data.build.num_points=128",
            "data.pair.num_points=128", "data.pair.prnet_num_keep=96", "data.num_workers=0", "data.pin_memory=false",
            f"data.cache_root={tmp_path / 'cache'}"]


def test_a_tiny_study_writes_a_row_that_the_verdict_table_reads(tmp_path, capsys):
    argv = _tiny(tmp_path)
    assert main(argv) == 0
    kind = cpu_kind(read_cpuinfo())
    (key, row), = load_verdicts.__wrapped__(tmp_path / "out" / "verdicts.yaml").items()
    assert key == (OMNET, kind) and row.seeds == (0, 1, 2) and row.target_deg == 170.0
    assert row.command == "python -m benchmarks.studies.precision.time_to_accuracy " + " ".join(argv)
    runs = pd.read_csv(tmp_path / "out" / "runs.csv")
    assert tuple(runs.columns) == COLUMNS and len(runs) == 6 and set(runs["precision"]) == {"fp32", "bf16"}
    assert all(len(curve.split()) == 2 for curve in runs["curve"])  # validated after steps 1 and 2
    fp32 = runs[runs["precision"] == "fp32"]["final_deg"]
    assert (row.fp32.final_deg.min, row.fp32.final_deg.max) == (round(fp32.min(), 3), round(fp32.max(), 3))
    assert f"omnet on {kind}: {row.verdict} (" in capsys.readouterr().out
    assert main(argv) == 0 and len(pd.read_csv(tmp_path / "out" / "runs.csv")) == 6  # finished runs are kept
    assert "step 1:" not in capsys.readouterr().out


def test_fewer_than_three_seeds_are_refused_in_one_line(tmp_path, capsys):
    argv = _tiny(tmp_path)
    argv[argv.index("0,1,2")] = "0,1"
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == "error: --seeds: a verdict needs at least 3 seeds, got '0,1'"


def _runs(bf16_cpu_s: list[float | None], bf16_final: list[float]) -> pd.DataFrame:
    """Three seeds: fp32 reaches the target after 100 CPU-s at 0.5 s/step, final 10-14 deg; bf16 as given at 0.25 s/step."""
    rows = []
    for seed in range(3):
        for precision, cpu_s, final, per_step in (("fp32", 100.0, 10.0 + 2 * seed, 0.5),
                                                  ("bf16", bf16_cpu_s[seed], bf16_final[seed], 0.25)):
            rows.append({"setup": "s", "method": "omnet", "seed": seed, "precision": precision, "steps": 400,
                         "cpu_s": 400 * per_step, "s_per_step": per_step,
                         "step_to_target": None if cpu_s is None else cpu_s / per_step, "cpu_s_to_target": cpu_s,
                         "final_deg": final, "curve": "", "cpu_kind": "intel-amx", "cpu": "Intel Xeon X"})
    return pd.DataFrame(rows, columns=COLUMNS)


@pytest.mark.parametrize("bf16_cpu_s, bf16_final, speedup, verdict", [
    ([50.0, 50.0, 50.0], [11.0, 12.0, 13.0], 2.0, "bf16"),     # twice as fast, final 12 within fp32's 10-14
    ([50.0, 50.0, 50.0], [20.0, 22.0, 24.0], 2.0, "fp32"),     # faster, but worse than every fp32 seed
    ([150.0, 150.0, 150.0], [11.0, 12.0, 13.0], 0.667, "fp32"),  # faster steps, slower to the target
    ([50.0, None, 50.0], [11.0, 12.0, 13.0], None, "fp32"),    # a bf16 seed never reached it
])
def test_a_row_is_the_runs_speed_ups_and_spreads(bf16_cpu_s, bf16_final, speedup, verdict):
    row = verdict_of(_runs(bf16_cpu_s, bf16_final), OMNET, 20.0, "s", "cmd")
    assert (row.step_speedup, row.time_to_target_speedup, row.verdict) == (2.0, speedup, verdict)
    assert (row.fp32.reached, row.fp32.cpu_s_to_target, row.fp32.final_deg.mean) == (3, 100.0, 12.0)
    assert row.bf16.reached == sum(c is not None for c in bf16_cpu_s) and row.cpu_kind == "intel-amx"
