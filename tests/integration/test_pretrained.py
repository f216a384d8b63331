"""Shipped checkpoints: export of a run, lookup by experiment, and `src.eval` without ckpt_path."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from src.utils.errors import CheckpointError
from src.eval import evaluate
from src.models.module import RegistrationModule
from src.models.pretrained import SHIPPED_DIR, export, find_shipped, main
from src.train import train
from tests.helpers.registration_helpers import tiny_config

IDENTITY = {"task": "unseen_shapes", "dataset": "synthetic", "sampling": "ts", "partial": "prnet"}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pretrained")
    train(tiny_config(tmp, "+exp=unseen_shapes", "trainer.max_steps=2", "trainer.val_check_interval=1",
                      "trainer.check_val_every_n_epoch=null", "trainer.limit_val_batches=1", "trainer.limit_test_batches=1"))
    return tmp / "run"


def test_export_writes_weights_only_checkpoint_and_card(run_dir, tmp_path):
    target = export(run_dir, "tiny", tmp_path, note="test export")
    card = json.loads((tmp_path / "tiny.json").read_text())
    assert card["experiment"] | IDENTITY == card["experiment"] and card["note"] == "test export"
    assert card["training"]["steps_run"] == 2 and card["training"]["fit_seconds_last_process"] > 0
    assert [row["step"] for row in card["training"]["validation"]] == [0, 1]
    assert set(card["metrics"]["test"]) >= {"Error(R)", "Error(t)"}
    saved = torch.load(target, weights_only=False)
    assert set(saved) == {"state_dict", "hyper_parameters", "pytorch-lightning_version", "trained_on"}  # no optimiser state
    assert {k: saved["trained_on"][k] for k in IDENTITY} == {k: card["experiment"][k] for k in IDENTITY}
    best = torch.load(json.loads((run_dir / "metrics.json").read_text())["checkpoint"], weights_only=False)
    assert all(torch.equal(saved["state_dict"][k], v) for k, v in best["state_dict"].items())
    assert card["parameters"] == sum(p.numel() for p in RegistrationModule.load_from_checkpoint(target).parameters())


def test_half_export_stores_float16_and_registers_as_the_float32_weights(run_dir, tmp_path):
    full, half = export(run_dir, "full", tmp_path), export(run_dir, "half", tmp_path, half=True)
    card = json.loads((tmp_path / "half.json").read_text())
    assert card["weights_dtype"] == "float16" and json.loads((tmp_path / "full.json").read_text())["weights_dtype"] == "float32"
    stored = torch.load(half, weights_only=False)["state_dict"]
    assert {v.dtype for v in stored.values() if v.is_floating_point()} == {torch.float16}
    assert half.stat().st_size < 0.6 * full.stat().st_size
    nets = [RegistrationModule.load_from_checkpoint(p).eval() for p in (full, half)]
    assert all(p.dtype == torch.float32 for p in nets[1].parameters())  # loaded back as float32
    torch.manual_seed(0)
    src, ref = torch.rand(2, 64, 3) - 0.5, torch.rand(2, 64, 3) - 0.5
    with torch.no_grad():
        poses = [net.network(src, ref)["transforms"][-1] for net in nets]
    assert torch.allclose(poses[0], poses[1], atol=2e-2) and not torch.equal(poses[0], poses[1])


def test_the_card_names_no_path_of_this_machine(run_dir, tmp_path):
    copy = tmp_path / "resumed_run"
    shutil.copytree(run_dir, copy)
    results = json.loads((copy / "metrics.json").read_text())
    (copy / "metrics.json").write_text(json.dumps(results | {"resumed_from": str(copy / "checkpoints" / "last.ckpt")}))
    export(copy, "tiny", tmp_path / "out")
    text = (tmp_path / "out" / "tiny.json").read_text()
    assert str(tmp_path) not in text and json.loads(text)["training"]["resumed_from"] == "<run dir>/checkpoints/last.ckpt"
    sibling = str(tmp_path / "classifier" / "checkpoints" / "best-3.ckpt")  # an earlier stage's checkpoint
    (copy / "metrics.json").write_text(json.dumps(results | {"resumed_from": sibling}))
    export(copy, "tiny", tmp_path / "out")
    card = json.loads((tmp_path / "out" / "tiny.json").read_text())
    assert card["training"]["resumed_from"] == "<run dir>/../classifier/checkpoints/best-3.ckpt"


def test_find_shipped_matches_the_experiment(run_dir, tmp_path):
    (run_dir / ".hydra").mkdir(exist_ok=True)
    (run_dir / ".hydra" / "overrides.yaml").write_text("- +exp=unseen_shapes\n- model_scale=0.0625\n- task_name=a_label\n")
    main(["export", str(run_dir), "--name", "tiny", "--out-dir", str(tmp_path),
          "--evaluation", f"again={run_dir / 'metrics.json'}"])
    assert find_shipped(IDENTITY, tmp_path) == tmp_path / "tiny.ckpt"
    card = json.loads((tmp_path / "tiny.json").read_text())
    assert card["metrics"]["again"] == card["metrics"]["test"]
    assert card["training"]["command"] == "python -m src.train +exp=unseen_shapes model_scale=0.0625 task_name=a_label"
    assert card["experiment"]["task"] == "unseen_shapes"  # the +exp, not the task_name label
    with pytest.raises(CheckpointError, match="no shipped checkpoint for task=unseen_shapes dataset=modelnet40 .*"
                       "shipped: task=unseen_shapes dataset=synthetic sampling=ts partial=prnet.*ckpt_path"):
        find_shipped(IDENTITY | {"dataset": "modelnet40"}, tmp_path)
    target = card["network"]["_target_"]
    assert find_shipped(IDENTITY, tmp_path, network=target) == tmp_path / "tiny.ckpt"
    with pytest.raises(CheckpointError, match=r"network=baselines.learned.dcp.DCP \(shipped: .* network=" + target):
        find_shipped(IDENTITY, tmp_path, network="baselines.learned.dcp.DCP")  # the same experiment, another network


def test_eval_without_ckpt_path_uses_the_shipped_checkpoint(tmp_path):
    """What a fresh clone gets from `python -m src.eval +exp=unseen_categories` (on a tiny test set here)."""
    shipped = find_shipped({"task": "unseen_categories", "dataset": "synthetic", "sampling": "ts", "partial": "prnet"})
    card = json.loads(shipped.with_suffix(".json").read_text())
    assert shipped.parent == SHIPPED_DIR and shipped.stat().st_size < 60 * 2**20 and card["file"] == shipped.name
    metrics = evaluate(tiny_config(tmp_path, "+exp=unseen_categories"))
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["checkpoint"] == str(shipped) and saved["metrics"]["Error(R)"] == pytest.approx(metrics["Error(R)"])
    with pytest.raises(CheckpointError, match="no shipped checkpoint for task=gaussian_noise"):
        evaluate(tiny_config(tmp_path, "+exp=gaussian_noise"))


def test_shipped_resolver_names_a_checkpoint_wherever_the_command_runs(tmp_path, monkeypatch):
    from omegaconf import OmegaConf

    from src.config import register_resolvers

    register_resolvers()
    monkeypatch.chdir(tmp_path)
    assert OmegaConf.create({"c": "${shipped:dcp_real_airplane_ts_prnet}"}).c == str(SHIPPED_DIR / "dcp_real_airplane_ts_prnet.ckpt")


@pytest.mark.parametrize("shipped", sorted(SHIPPED_DIR.glob("*.ckpt")), ids=lambda p: p.stem)
def test_eval_finds_the_model_of_every_shipped_checkpoint(shipped):
    """`src.eval +exp=E ckpt_path=checkpoints/<method>_....ckpt` needs no model=: the checkpoint's network names it."""
    from omegaconf import OmegaConf

    from src.eval import model_of_checkpoint
    from src.utils.paths import CONF_DIR

    args = ["+exp=real_airplane", f"ckpt_path={shipped}"]
    added = model_of_checkpoint(args)
    assert added[:2] == args and len(added) == 3 and added[2].startswith("model=")
    model = OmegaConf.load(CONF_DIR / "model" / f"{added[2].removeprefix('model=')}.yaml")
    card = json.loads(shipped.with_suffix(".json").read_text())
    assert model.network._target_ == card["network"]["_target_"]
    assert model_of_checkpoint([*args, "model=omnet"]) == [*args, "model=omnet"]  # the user's choice stands
    missing = ["+exp=real_airplane", "ckpt_path=no/such.ckpt"]
    assert model_of_checkpoint(missing) == missing  # left to load_checkpoint's one-line error


def test_eval_of_a_network_that_samples_at_test_repeats(tmp_path):
    """PRNet draws its keypoints at test (Gumbel-softmax, as the official test loop): src.eval seeds them."""
    shipped = SHIPPED_DIR / "prnet_real_airplane_ts_prnet.ckpt"
    first, second = (evaluate(tiny_config(tmp_path / run, "+exp=unseen_shapes", "model=prnet", f"ckpt_path={shipped}"))
                     for run in ("first", "second"))
    assert first == second and first["Error(R)"] > 0


@pytest.mark.parametrize("path", sorted(SHIPPED_DIR.glob("*.*")), ids=lambda p: p.name)
def test_no_shipped_file_names_a_path_of_the_machine_it_was_made_on(path):
    """A card or checkpoint holds no absolute path above the repository (a training stage's checkpoint in the
    network's hyper-parameters, as PointNetLK's feature_init was, must be written relative to the run)."""
    assert (str(SHIPPED_DIR.resolve().parent.parent) + "/").encode() not in path.read_bytes()
