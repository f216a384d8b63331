"""Sweeps through the real Hydra entry points on tiny synthetic data: a 2x2 grid with one failing
job, collected into one frame (the failure reported, the other jobs' results kept), DDP evaluation
on 2 CPU processes equal to a single process, a LaTeX table of the collected numbers, and the
sweep/launcher configs.

The two subprocess runs start together in one module fixture (they share a prebuilt cache); the
file needs ~25 s of CPU (60-70 s wall on 2 cores shared with other jobs).
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from benchmarks.collect import collect, main as collect_main
from benchmarks.tables.latex_check import check_latex, compile_latex, tabular_rows, tabulars
from benchmarks.tables.render import build_table, fmt, to_latex, to_markdown
from src.config import register_resolvers
from src.eval import evaluate
from src.run.reporting import read_csv_logs
from src.train import train
from tests.helpers.markdown import markdown_table
from tests.helpers.registration_helpers import TINY
from tests.helpers.paths import ROOT

CONF = str(ROOT / "conf")
STEP = ["trainer.max_steps=1", "trainer.limit_train_batches=1", "trainer.limit_val_batches=1"]
register_resolvers()


def _compose(*overrides: str, hydra_cfg: bool = False):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=hydra_cfg)


def _popen(args: list[str], log: Path) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    handle = log.open("w")
    return subprocess.Popen([sys.executable, *args], cwd=ROOT, env=env, stdout=handle, stderr=subprocess.STDOUT, text=True)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Builds the cache and a checkpoint in-process, then runs together: a 2x2 grid multirun
    (partial {prnet, rpmnet} x data.pair.noise_sigma {0.0, -0.5}; a negative noise is refused, so the two
    jobs with it fail; a key that one partial manner does not read would be refused in its jobs, see
    tests/integration/test_bad_input.py) and a 2-process DDP evaluation of the checkpoint;
    meanwhile the same checkpoint is evaluated in this process (eval batches of 3 over 7 pairs:
    2 batches on rank 0, 1 on rank 1)."""
    tmp = tmp_path_factory.mktemp("sweeps")
    cache = f"data.cache_root={tmp / 'cache'}"
    train(_compose(*TINY, cache, *STEP, f"output_dir={tmp / 'ckpt_run'}"))
    ckpt = tmp / "ckpt_run" / "checkpoints" / "last.ckpt"
    eval_args = [*TINY, cache, f"ckpt_path={ckpt}", "data.eval_batch_size=3"]
    procs = {
        "grid": _popen(["-m", "src.train", "-m", *TINY, cache, *STEP, "trainer.limit_test_batches=1",
                        f"hydra.sweep.dir={tmp / 'grid'}", "partial=prnet,rpmnet", "data.pair.noise_sigma=0.0,-0.5"],
                       tmp / "grid.log"),
        "ddp": _popen(["-m", "src.eval", *eval_args, "trainer=ddp", "trainer.devices=2",
                       f"hydra.run.dir={tmp / 'ddp'}"], tmp / "ddp.log"),
    }
    single = evaluate(_compose(*eval_args, f"output_dir={tmp / 'single'}"))
    overlap = evaluate(_compose(*eval_args, "data.pair.overlap_ratio=0.5", f"output_dir={tmp / 'overlap'}"))
    codes = {name: proc.wait(timeout=600) for name, proc in procs.items()}
    logs = {name: (tmp / f"{name}.log").read_text() for name in procs}
    return {"tmp": tmp, "codes": codes, "logs": logs, "single": single, "overlap": overlap, "ckpt": ckpt}


# --- the grid and its frame ----------------------------------------------------------------------


def test_grid_multirun_is_collected_into_one_frame(runs, capsys):
    grid = runs["tmp"] / "grid"
    assert runs["codes"]["grid"] == 3, runs["logs"]["grid"][-3000:]  # FailureSummary: the sweep finished, a job failed
    assert "2 of 4 jobs failed" in runs["logs"]["grid"]
    result = collect(grid)
    metrics = sorted(json.loads((grid / "0" / "metrics.json").read_text())["metrics"])
    assert result.expected == 4 and len(result.jobs) == 4
    assert sorted(result.swept) == ["data.pair.noise_sigma", "partial"]
    status = result.jobs.set_index(["partial", "data.pair.noise_sigma"])["status"].to_dict()
    assert status == {("prnet", 0.0): "ok", ("prnet", -0.5): "failed", ("rpmnet", 0.0): "ok", ("rpmnet", -0.5): "failed"}
    assert result.tidy.shape[0] == 2 * len(metrics)
    assert {"method", "experiment", "sampling", "partial", "metric", "value", "data.pair.noise_sigma"} <= set(result.tidy.columns)
    assert set(result.tidy["method"]) == {"OMNet"} and set(result.tidy["experiment"]) == {"unseen_shapes"}
    counts = result.tidy.groupby(["partial", "data.pair.noise_sigma"]).size().to_dict()
    assert counts == {("prnet", 0.0): len(metrics), ("rpmnet", 0.0): len(metrics)}
    assert result.wide.shape[0] == 2 and set(metrics) <= set(result.wide.columns)
    one = result.wide.set_index(["partial", "data.pair.noise_sigma"]).loc[("rpmnet", 0.0)]
    assert one["Error(R)"] == json.loads((Path(one["run_dir"]) / "metrics.json").read_text())["metrics"]["Error(R)"]
    # the CLI writes parquet + CSV that read back to the same frame
    out = runs["tmp"] / "collected_grid"
    assert collect_main([str(grid), "--out", str(out)]) == 0
    assert "4 jobs" in capsys.readouterr().out
    back = pd.read_parquet(out / "results.parquet")
    pd.testing.assert_frame_equal(back, result.tidy, check_dtype=False)
    assert pd.read_csv(out / "results.csv").shape == result.tidy.shape
    assert pd.read_csv(out / "jobs.csv").shape[0] == 4


def test_failing_job_is_recorded_and_the_others_survive(runs, capsys):
    grid = runs["tmp"] / "grid"
    failed = collect(grid).failures
    assert len(failed) == 2
    job = Path(failed.iloc[0]["run_dir"])
    record = json.loads((job / "failure.json").read_text())
    assert "noise_sigma" in record["reason"]
    assert record["user_error"] and "data.pair.noise_sigma=-0.5" in record["overrides"] and "Traceback" in record["traceback"]
    assert not (job / "metrics.json").exists()
    assert sum((d / "metrics.json").is_file() for d in grid.iterdir() if d.is_dir()) == 2
    assert collect_main([str(grid), "--out", str(runs["tmp"] / "c_fail"), "--strict"]) == 1
    out = capsys.readouterr().out
    assert "2 failed" in out and "noise_sigma" in out
    # a job killed without a trace (no metrics, no failure.json) is reported as missing
    ok = Path(collect(grid).wide.iloc[0]["run_dir"])
    (ok / "metrics.json").rename(ok / "metrics.json.bak")
    try:
        jobs = collect(grid).jobs
        assert jobs.set_index("run_dir")["status"][str(ok)] == "missing"
    finally:
        (ok / "metrics.json.bak").rename(ok / "metrics.json")


def test_latex_table_compiles_and_holds_the_collected_numbers(runs, tmp_path):
    frame = collect(runs["tmp"] / "grid").tidy
    frame["method"] = "OMNet noise=" + frame["data.pair.noise_sigma"].astype(str)
    table = build_table(frame, "table2")
    tex = to_latex(table)
    assert check_latex(tex) == []
    (spec, body), = tabulars(tex)
    rows = tabular_rows(body)
    degrees = {m: " ($^\\circ$)" if m.endswith("(R)") else "" for m in table.metrics}  # units and direction
    assert rows[0] == ["Method", *[f"{m[:-3]}($\\mathbf{{{m[-2]}}}$){degrees[m]} $\\downarrow$" for m in table.metrics]]
    blocks = [r[0] for r in rows if r[0].startswith("\\multicolumn")]
    assert len(blocks) == 2 and "Unseen shapes" in blocks[0] and "RPMNet manner" in blocks[1]
    seen = 0
    for partial, label_rows in (("prnet", rows[2:3]), ("rpmnet", rows[4:5])):
        for row in label_rows:
            cells = [re.sub(r"\\(textbf|underline)\{(.*)\}", r"\2", c) for c in row[1:]]
            for metric, cell in zip(table.metrics, cells):
                value = frame[(frame["method"] == row[0]) & (frame["partial"] == partial) & (frame["metric"] == metric)]["value"]
                assert cell == fmt(float(value.iloc[0]), metric)
                seen += 1
    assert seen == 2 * len(table.metrics)
    assert "synthetic data, not ModelNet40" in tex
    _, markdown = markdown_table(to_markdown(table))
    md_rows = [[re.sub(r"^\*\*(.*)\*\*$|^<u>(.*)</u>$", r"\1\2", c) for c in cells]
               for cells in markdown.values.tolist() if not cells[0].startswith("***")]  # block labels aside
    tex_rows = [[re.sub(r"\\(textbf|underline)\{(.*)\}", r"\2", c) for c in row]
                for row in rows[1:] if not row[0].startswith("\\multicolumn")]
    assert md_rows == tex_rows  # the same rows and numbers as the LaTeX table, checked against the frame above
    assert "OMNet noise=0.0" in markdown["Method"].tolist()
    ok, log = compile_latex(to_latex(table, standalone=True), tmp_path / "table.pdf")
    if ok is None:
        pytest.skip(f"structure checked; not compiled: {log}")
    assert ok, log


# --- DDP ------------------------------------------------------------------------------------------


def test_ddp_evaluation_on_two_cpu_processes_equals_one_process(runs):
    log = runs["logs"]["ddp"]
    assert runs["codes"]["ddp"] == 0, log[-3000:]
    assert "GLOBAL_RANK: 1, MEMBER: 2/2" in log
    ddp_dir = runs["tmp"] / "ddp"
    ddp = json.loads((ddp_dir / "metrics.json").read_text())["metrics"]
    single = runs["single"]
    assert set(ddp) == set(single)
    for name, value in single.items():  # sums in float64; only the order of the final sum differs
        assert ddp[name] == pytest.approx(value, rel=1e-12, abs=1e-12), name
    # the logged test loss (sum-reduced MeanMetric) matches too, despite 2 batches on rank 0 and 1 on rank 1
    loss = lambda d: read_csv_logs(d)["test/loss"].dropna().iloc[-1]  # noqa: E731
    assert loss(ddp_dir) == pytest.approx(loss(runs["tmp"] / "single"), rel=1e-6)
    assert not list(ddp_dir.glob("failure*.json"))


def test_eval_with_overlap_ratio_runs_and_changes_the_pairs(runs):
    overlap, single = runs["overlap"], runs["single"]
    assert set(overlap) == set(single) and overlap["chamfer"] != single["chamfer"]
    cfg = _compose("+sweep=overlap", "ckpt_path=x.ckpt")
    assert cfg.data.pair.overlap_ratio is None and cfg.task_name == "sweep_overlap"


# --- configs --------------------------------------------------------------------------------------

SWEEPS = {
    "noise": ("data.pair.noise_sigma", 5, "gaussian_noise"),
    "partial": ("partial", 2, "unseen_categories"),
    "sampling": ("sampling", 2, "unseen_shapes"),
    "table1": ("sampling", 2, "unseen_shapes"),
    "lambda": ("model.network.trans_loss_weight", 4, "gaussian_noise"),
    "ablation": ("+model/ablation", 8, "gaussian_noise"),
    "iterations": ("model.network.num_iters", 6, "gaussian_noise"),
    "overlap": ("data.pair.overlap_ratio", 10, "unseen_shapes"),
}


@pytest.mark.parametrize("name", sorted(SWEEPS))
def test_sweep_configs_compose(name):
    key, count, base = SWEEPS[name]
    cfg = _compose(f"+sweep={name}", "data=synthetic", hydra_cfg=True)
    params = cfg.hydra.sweeper.params
    assert len(str(params[key]).split(",")) == count
    assert cfg.task_name == f"sweep_{name}" and cfg.on_failure == "auto"
    assert cfg.data.splits.test.categories == ("half2" if base == "unseen_categories" else "half1")
    assert cfg.data.pair.noise_sigma == (0.01 if base == "gaussian_noise" or name == "partial" else 0.0)
    if name == "table1":
        assert len(params) == 3
    if name == "lambda":
        assert _compose("+sweep=lambda", "model.network.trans_loss_weight=0.5").variant == "lambda=0.5"


ABLATIONS = {
    "B": ("B", (False, False, False, False), "argmax"),
    "B_M": ("B+M", (True, False, False, False), "argmax"),
    "B_M_ML": ("B+M+ML", (True, True, False, False), "argmax"),
    "B_M_ML_F": ("B+M+ML+F", (True, True, True, False), "argmax"),
    "B_M_ML_F_C": ("B+M+ML+F+C", (True, True, True, True), "argmax"),
    "topk100": ("Top-k, k=100", (True, True, True, True), "topk"),
    "topk300": ("Top-k, k=300", (True, True, True, True), "topk"),
    "topk500": ("Top-k, k=500", (True, True, True, True), "topk"),
}


@pytest.mark.parametrize("name", sorted(ABLATIONS))
def test_ablation_variants_are_named_configs(name):
    label, flags, mode = ABLATIONS[name]
    cfg = _compose("+sweep=ablation", f"+model/ablation={name}")
    net = cfg.model.network
    assert cfg.variant == label and (net.mask_module, net.mask_loss, net.fusion, net.connection) == flags
    assert net.mask_mode == mode and (mode == "argmax" or net.topk == int(name[4:]))


@pytest.mark.filterwarnings("ignore:(?s).*validated against ConfigStore schema")
def test_launcher_configs_compose_and_instantiate():
    import hydra

    base = _compose(hydra_cfg=True)
    assert base.hydra.launcher._target_.endswith("BasicLauncher")
    assert base.hydra.callbacks.failure_summary._target_ == "src.run.failures.FailureSummary"
    joblib = _compose("hydra/launcher=joblib", hydra_cfg=True).hydra.launcher
    assert joblib._target_.endswith("JoblibLauncher") and joblib.n_jobs == 2
    slurm = _compose("hydra/launcher=submitit_slurm", "trainer=ddp", "trainer.devices=4", "trainer.num_nodes=2",
                     hydra_cfg=True).hydra.launcher
    assert slurm._target_.endswith("SlurmLauncher")
    assert (slurm.tasks_per_node, slurm.gpus_per_node, slurm.nodes) == (4, 4, 2)
    assert _compose("hydra/launcher=submitit_slurm", hydra_cfg=True).hydra.launcher.nodes == 1
    for launcher, plugin in ((joblib, "hydra_plugins.hydra_joblib_launcher"), (slurm, "hydra_plugins.hydra_submitit_launcher")):
        pytest.importorskip(plugin)
        assert type(hydra.utils.instantiate(launcher)).__name__ == launcher._target_.rsplit(".", 1)[1]


def test_ddp_trainer_config():
    trainer = _compose("trainer=ddp").trainer
    assert trainer.strategy == "ddp" and trainer.use_distributed_sampler is False
    assert trainer.devices == "auto" and trainer.num_nodes == 1 and trainer.max_steps == 260000


def test_on_failure_record_and_raise_in_process(tmp_path, monkeypatch):
    from src.run.failures import record_failures, resolve_on_failure

    def boom(cfg):
        raise RuntimeError("kaput")

    cfg = _compose(f"output_dir={tmp_path / 'a'}", "on_failure=record")
    assert record_failures(boom)(cfg) is None
    assert json.loads((tmp_path / "a" / "failure.json").read_text())["reason"] == "RuntimeError: kaput"
    cfg = _compose(f"output_dir={tmp_path / 'b'}")  # auto outside a multirun: raise, but still recorded
    assert resolve_on_failure("auto") == "raise"
    with pytest.raises(RuntimeError, match="kaput"):
        record_failures(boom)(cfg)
    assert (tmp_path / "b" / "failure.json").is_file()
    assert record_failures(lambda c: 1)(cfg) == 1 and not (tmp_path / "b" / "failure.json").exists()


@pytest.mark.slow  # ~1 min on 2 cores: --run-slow
def test_joblib_launcher_multirun_with_a_failing_job(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    log = tmp_path / "joblib.log"
    proc = _popen(["-m", "src.train", "-m", *TINY, f"data.cache_root={tmp_path / 'cache'}", *STEP, "trainer.limit_test_batches=1",
                   f"hydra.sweep.dir={tmp_path / 'mr'}", "model.network.num_iters=0,1", "hydra/launcher=joblib"], log)
    assert proc.wait(timeout=600) == 3, log.read_text()[-3000:]
    status = collect(tmp_path / "mr").jobs.set_index("job")["status"].to_dict()
    assert status == {"0": "failed", "1": "ok"} and not math.isnan(collect(tmp_path / "mr").tidy["value"].sum())


def test_failed_jobs_keep_their_overrides(tmp_path):
    """A job that failed before writing config_resolved.yaml (e.g. an invalid value) is labelled by its
    overrides: .hydra/overrides.yaml, or failure.json's when Hydra wrote no .hydra folder."""
    def job(num: str, overrides: list[str], hydra_dir: bool, ok: bool) -> None:
        folder = tmp_path / num
        (folder / ".hydra").mkdir(parents=True)
        if hydra_dir:
            (folder / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
        if ok:
            (folder / "config_resolved.yaml").write_text("partial: prnet\nsampling: ts\ndata: {pair: {noise_sigma: 0.0}}\n")
            (folder / "metrics.json").write_text(json.dumps({"metrics": {"Error(R)": 1.0}}))
        else:
            (folder / "failure.json").write_text(json.dumps({"reason": "ConfigError: invalid", "overrides": overrides}))

    job("0", ["partial=prnet", "data.pair.noise_sigma=0.0"], hydra_dir=True, ok=True)
    job("1", ["partial=yy", "data.pair.noise_sigma=0.0"], hydra_dir=True, ok=False)
    job("2", ["partial=rpmnet", "data.pair.noise_sigma=0.02"], hydra_dir=False, ok=False)
    jobs = collect(tmp_path).jobs.set_index("job")
    assert jobs["status"].to_dict() == {"0": "ok", "1": "failed", "2": "failed"}
    assert jobs["partial"].to_dict() == {"0": "prnet", "1": "yy", "2": "rpmnet"}
    assert jobs["noise_sigma"].to_dict() == {"0": 0.0, "1": 0.0, "2": 0.02}
