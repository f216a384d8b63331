"""benchmarks.speed.gpu_trial: the time-boxed GPU trial runs end to end on the CPU in --dry-run mode; weight
shards under the size limit rebuild a checkpoint that loads."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from benchmarks.speed import gpu_trial
from src.utils.errors import CheckpointError
from src.models.module import RegistrationModule


def test_dry_run_times_the_step_measures_the_loader_trains_and_exports_shards(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("OMNET_CACHE_DIR", str(tmp_path / "cache"))
    out, run = tmp_path / "out", tmp_path / "run"
    assert gpu_trial.main(["--out", str(out), "--dry-run", "--minutes", "6", "--run-dir", str(run), "--shard-mb", "1"]) == 0
    report = (out / "gpu_trial.md").read_text()
    assert "DRY RUN" in report and "training pairs/s" in report and "src.train exit 0" in report
    assert "no batch-64 step was timed" in report  # the dry run times batch 2 only
    shards = sorted((out / "weights_best").glob("weights-*.pt"))
    assert shards and all(p.stat().st_size < 2**20 + 2**16 for p in shards)  # 1 MB of tensors + the pickle's framing
    joined = gpu_trial.join_weights(out / "weights_best", tmp_path / "joined.ckpt")
    module = RegistrationModule.load_from_checkpoint(joined, map_location="cpu")
    original = torch.load(gpu_trial.selected_checkpoint(run), map_location="cpu", weights_only=False)["state_dict"]
    assert all(torch.equal(module.state_dict()[k], v) for k, v in original.items())


def test_shards_split_at_the_size_limit_and_refuse_an_oversized_tensor(tmp_path: Path):
    module = RegistrationModule({"_target_": "src.models.omnet.OMNet", "width": 0.0625})
    ckpt = tmp_path / "m.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams), "global_step": 3}, ckpt)
    sizes = sorted(t.numel() * t.element_size() for t in module.state_dict().values())
    limit = sizes[-1]
    shards = gpu_trial.split_weights(ckpt, tmp_path / "shards", shard_bytes=limit)
    assert len(shards) > 1
    for shard in shards:
        state = torch.load(shard, weights_only=False)["state_dict"]
        assert sum(t.numel() * t.element_size() for t in state.values()) <= limit
    joined = torch.load(gpu_trial.join_weights(tmp_path / "shards", tmp_path / "j.ckpt"), weights_only=False)
    assert joined["global_step"] == 3 and joined["state_dict"].keys() == module.state_dict().keys()
    with pytest.raises(CheckpointError, match="exceeds"):
        gpu_trial.split_weights(ckpt, tmp_path / "small", shard_bytes=limit - 1)


def test_projection_from_the_batch_64_step():
    steps = gpu_trial.pd.DataFrame([{"batch": 64, "precision": "bf16", "compile": "none", "ms_per_step": 100.0, "note": ""}])
    assert "260,000 steps ≈ 7.2 h" in gpu_trial.projection(steps)


def test_bad_arguments_are_one_line(tmp_path: Path, capsys):
    assert gpu_trial.main(["--dry-run"]) == 2
    assert "--out is required" in capsys.readouterr().err
    assert gpu_trial.main(["join", str(tmp_path), str(tmp_path / "x.ckpt")]) == 2
    assert "no weights-*.pt shards" in capsys.readouterr().err
    assert gpu_trial.main(["--out", str(tmp_path), "--dry-run", "--shard-mb", "0"]) == 2
    assert "--shard-mb must be a positive number" in capsys.readouterr().err
