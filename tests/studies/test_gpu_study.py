"""benchmarks.studies.gpu_study.study: the study runs end to end on the CPU (--dry-run): phases stopped by SIGTERM at their
deadlines, the second started from the first's last weights at its own learning rate, the best validated
checkpoint selected over both, exported in float16, and everything but the training checkpoints returned as
a tar in parts that ``collect`` joins."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import torch

from benchmarks.studies.gpu_study import study as gpu_study
from src.models.module import RegistrationModule


def test_dry_run_trains_in_phases_selects_exports_and_collects(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("OMNET_CACHE_DIR", str(tmp_path / "cache"))
    out, root, rates = tmp_path / "out", tmp_path / "runs", tmp_path / "rates.json"
    assert gpu_study.main(["run", "--out", str(out), "--seconds", "50", "--dry-run", "--root", str(root),
                           "--runs", "omnet_w025_b16", "--rates-file", str(rates)]) == 0
    back = tmp_path / "back"
    gpu_study.collect(out, back)
    record = json.loads((back / "runs" / "study.json").read_text())["runs"]["omnet_w025_b16"]
    first = record["phases"][0]
    assert first["stopped_at_deadline"] and first["exit"] == 143 and first["steps"] > 0 and first["lr"] == 3e-3
    assert len(record["phases"]) == 2 and record["phases"][1]["lr"] == 3e-4  # from the first phase's last.ckpt
    overrides = (root / "omnet_w025_b16" / "phase1" / ".hydra" / "overrides.yaml").read_text()
    assert f"init_weights={root / 'omnet_w025_b16' / 'phase0' / 'checkpoints' / 'last.ckpt'}" in overrides
    selected = record["selected"]
    assert selected["monitor"] == "val/score" and selected["checkpoint"].startswith(f"phase{selected['phase']}/checkpoints/best-")
    assert not list(back.rglob("*/checkpoints/*"))  # training checkpoints stay on the machine
    model = back / "runs" / "omnet_w025_b16" / "model.ckpt"
    assert all(t.dtype == torch.float16 for t in torch.load(model, weights_only=False)["state_dict"].values()
               if t.is_floating_point())
    assert RegistrationModule.load_from_checkpoint(model, map_location="cpu").network.__class__.__name__ == "OMNet"
    assert json.loads(rates.read_text())["omnet_w025_b16"] == first["steps_per_s"] > 0
    curves, summary, figure = gpu_study.report(back / "runs", tmp_path / "report", {"omnet_w025_b16": 7.2}, {}, None)
    curve = pd.read_csv(curves)
    assert not curve.empty and (curve["cpu_hours"] == curve["step"] * 7.2 / 3600).all()
    assert (curve["pairs"] == curve["step"] * 4).all() and curve["step"].is_monotonic_increasing  # phases in turn
    steps = sum(p.get("steps", 0) for p in record["phases"])
    assert f"| omnet_w025_b16 |" in summary.read_text() and f"{steps * 7.2 / 3600:.1f}" in summary.read_text()
    assert figure.stat().st_size > 0


def test_validation_interval_from_the_rate_the_table_or_the_command_line():
    run = gpu_study.RUNS[0]
    assert gpu_study.val_interval(run, 500, {}, None) == run.val_every
    assert gpu_study.val_interval(run, 500, {run.name: 4.0}, None) == 100  # 20 validations over 2,000 steps
    assert gpu_study.val_interval(run, 500, {run.name: 4.0}, 7) == 7


def test_a_process_past_its_deadline_is_terminated_then_killed():
    ignoring = subprocess.Popen([sys.executable, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                                 "print(flush=True); time.sleep(60)"], stdout=subprocess.PIPE, start_new_session=True)
    ignoring.stdout.readline()  # its handler is set
    start = time.perf_counter()
    status, stopped = gpu_study.stop_at(ignoring, time.perf_counter() + 0.2, grace=0.5)
    assert stopped and status == -9 and time.perf_counter() - start < 10
    quick = subprocess.Popen([sys.executable, "-c", "pass"], start_new_session=True)
    assert gpu_study.stop_at(quick, time.perf_counter() + 30) == (0, False)


def test_unknown_runs_and_missing_parts_are_one_line_errors(tmp_path, capsys):
    assert gpu_study.main(["run", "--out", str(tmp_path), "--seconds", "5", "--dry-run", "--runs", "omnet,idam"]) == 2
    assert "--runs: unknown ['omnet']; choose from omnet_w05_b64" in capsys.readouterr().err
    assert gpu_study.main(["collect", str(tmp_path), "--into", str(tmp_path / "x")]) == 2
    assert "no study.tar.part* files in" in capsys.readouterr().err
    assert gpu_study.main(["report", str(tmp_path), "--cpu-step", "omnet_w05_b64"]) == 2
    assert "--cpu-step takes RUN=VALUE items" in capsys.readouterr().err


@pytest.mark.parametrize("size", [0, 5, 100])
def test_parts_join_back_to_the_tar(tmp_path, size):
    root = tmp_path / "runs"
    (root / "a" / "checkpoints").mkdir(parents=True)
    (root / "a" / "log.csv").write_bytes(bytes(range(256)) * size)
    (root / "a" / "checkpoints" / "last.ckpt").write_bytes(b"x" * 1000)
    parts = gpu_study.pack_parts(root, tmp_path / "out", part_bytes=4096)
    assert all(p.stat().st_size <= 4096 for p in parts)
    back = gpu_study.collect(tmp_path / "out", tmp_path / "back")
    assert (back / "runs" / "a" / "log.csv").read_bytes() == bytes(range(256)) * size
    assert not (back / "runs" / "a" / "checkpoints").exists()
