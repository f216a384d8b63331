"""benchmarks.studies.lockstep.harness (the shared loop) and its IDAM adapter, offline and without the authors' code; the float64
start check against jiahaowork/idam runs only where IDAM_AUTHORS_DIR names a checkout of it."""

import argparse
import csv
import json
import os
from pathlib import Path

import pytest
import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset

from baselines.learned.idam import IDAM
from benchmarks.studies.lockstep import idam as idam_lockstep
from benchmarks.studies.lockstep import harness as lockstep
from src.data.dataset import EpochSampler
from src.utils.errors import ConfigError
from src.geometry import se3_from_rt
from tests.helpers.registration_helpers import turned_batch


def test_every_weight_of_ours_has_a_counterpart_in_theirs():
    ours = IDAM()
    mapped = [name for name, _ in idam_lockstep.layer_names(ours.num_iters)]
    owners = {key.rsplit(".", 1)[0] for key in ours.state_dict()}
    assert owners == set(mapped) and len(mapped) == len(set(mapped))
    theirs = [name for _, name in idam_lockstep.layer_names(3)]
    assert "emb_nn.propogate1.conv2d.conv.0.conv" in theirs and "significance_fc.conv.2" in theirs
    assert "sim_mat_conv1.2.conv.1" in theirs and "weight_fc.0.conv.0.bn" in theirs


def test_copy_mapped_reshapes_linear_to_conv_and_refuses_a_bias_only_ours_has():
    ours = nn.Sequential(nn.Linear(4, 3, bias=False), nn.BatchNorm1d(3), nn.Linear(3, 2))
    theirs = nn.Sequential(nn.Conv2d(4, 3, 1, bias=False), nn.BatchNorm2d(3), nn.Conv1d(3, 2, 1))
    ours[1].running_mean.fill_(0.5)
    lockstep.copy_mapped(ours, theirs, [("0", "0"), ("1", "1"), ("2", "2")], zero_missing_bias=False)
    assert torch.equal(theirs[0].weight[:, :, 0, 0], ours[0].weight) and torch.equal(theirs[2].bias, ours[2].bias)
    assert torch.equal(theirs[1].running_mean, ours[1].running_mean)
    biased = nn.Sequential(nn.Linear(4, 3))  # a bias where theirs (bias=False) has none
    with pytest.raises(ConfigError, match="where 0 has none"):
        lockstep.copy_mapped(biased, theirs, [("0", "0")], zero_missing_bias=False)


class _Pairs(Dataset):
    def __len__(self):
        return 12

    def __getitem__(self, i):
        points = torch.full((5, 3), float(i)) / 12 + torch.arange(5.0).unsqueeze(1) / 10
        return {"points_src": points, "points_ref": points, "transform_gt": torch.eye(4)}


class _DataModule:
    batch_size = 3

    def __init__(self):
        self._train_sampler = EpochSampler(12, seed=7)

    def train_dataloader(self):
        return DataLoader(_Pairs(), batch_size=3, sampler=self._train_sampler, drop_last=True)

    def val_dataloader(self):
        return DataLoader(_Pairs(), batch_size=5)


class _ToyPair(lockstep.Pair):
    def outputs(self, name, batch):
        moved = self.nets[name](batch["points_src"])
        loss = ((moved - batch["points_ref"] - 0.1) ** 2).mean()
        return loss, se3_from_rt(torch.eye(3).expand(len(moved), 3, 3), moved.mean(dim=1) - batch["points_ref"].mean(dim=1))


def _toy_run(out: Path, steps: int) -> tuple[list, dict]:
    torch.manual_seed(0)
    pair = _ToyPair(nn.Linear(3, 3), nn.Linear(3, 3))
    args = argparse.Namespace(out=out, steps=steps, schedule_steps=6, milestones=[0.5], lr=0.01, weight_decay=1e-3,
                              val_every=2, val_pairs=7, progress_every=3)
    lockstep.train(pair, _DataModule(), args, lambda pair, batch, out: None)
    rows = [(r["step"], r["net"], r["train_loss"], r["val_rot_deg"], r["val_trans"]) for r in csv.DictReader((out / "curves.csv").open())]
    return rows, {n: {k: v.clone() for k, v in m.state_dict().items()} for n, m in pair.nets.items()}


def test_the_shared_loop_resumes_where_it_left_off(tmp_path):
    straight, nets = _toy_run(tmp_path / "straight", 6)  # 6 steps of 4 batches an epoch: across an epoch
    _toy_run(tmp_path / "resumed", 4)
    resumed, nets_resumed = _toy_run(tmp_path / "resumed", 6)
    assert resumed == straight and [r[0] for r in straight] == ["2", "2", "4", "4", "6", "6"]
    for n in nets:
        assert all(torch.equal(nets[n][k], nets_resumed[n][k]) for k in nets[n])


def test_the_loop_prints_both_losses_between_validations(tmp_path, capsys):
    _toy_run(tmp_path, 6)
    progress = [line for line in capsys.readouterr().out.splitlines() if "train loss" in line]
    assert [line.split(":")[0] for line in progress] == ["step 3/6", "step 6/6"]
    assert all("ours " in line and "authors " in line and "CPU-s" in line for line in progress)


def test_authors_without_model_py_and_other_widths_are_config_errors(tmp_path, capsys):
    with pytest.raises(ConfigError, match="no model.py"):
        idam_lockstep.load_authors(tmp_path)
    common = ["--authors", str(tmp_path), "--out", str(tmp_path / "run"), "--steps", "0"]
    assert lockstep.main(["--method", "idam", *common]) == 2
    assert "no model.py/util.py" in capsys.readouterr().err
    assert lockstep.main(["--method", "idam", "--width", "0.5", *common]) == 2
    assert "width 1.0 only" in capsys.readouterr().err


def test_the_defaults_are_the_authors_recipe_and_the_budget_run():
    args = lockstep.parser_for(idam_lockstep, "x", with_method=True).parse_args(
        ["--method", "idam", "--authors", "a", "--out", "o"])
    assert (args.steps, args.val_every, args.batch, args.width) == (1410, 141, 16, 1.0)
    assert (args.lr, args.weight_decay, args.milestones, args.val_pairs) == (1e-4, 1e-3, [0.75], None)
    assert not args.shared_selection  # each its own random point selection unless asked


@pytest.mark.skipif(not os.environ.get("IDAM_AUTHORS_DIR"),
                    reason="IDAM_AUTHORS_DIR (a checkout of jiahaowork/idam) not set: the authors' side is not checked")
def test_same_start_against_the_authors_code(tmp_path):
    from src.compose import compose_conf

    cfg = compose_conf([*idam_lockstep.PROTOCOL, *lockstep.DATA, "model_scale=1.0"])
    args = argparse.Namespace(authors=Path(os.environ["IDAM_AUTHORS_DIR"]), width=1.0)
    torch.manual_seed(0)
    pair = idam_lockstep.build(args, cfg)
    batch = turned_batch(4, 60)
    idam_lockstep.check_same_start(pair, batch, tmp_path)  # raises ConfigError where the mapping is wrong
    result = json.loads((tmp_path / "start_check.json").read_text())
    assert result["eval"]["embedding"] < 1e-10 and result["train_iteration1_only"]["gradient_rel"] < 1e-6
