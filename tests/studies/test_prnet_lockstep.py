"""benchmarks.studies.lockstep.harness's PRNet adapter, offline and without the authors' code; the float64 start check against
WangYueFt/prnet runs only where PRNET_AUTHORS_DIR names a checkout of it."""

import argparse
import json
import os
from pathlib import Path

import pytest
import torch

from baselines.learned.prnet import PRNet
from benchmarks.studies.lockstep import harness as lockstep
from benchmarks.studies.lockstep import prnet as prnet_lockstep
from src.compose import compose_conf
from src.utils.errors import ConfigError
from tests.helpers.registration_helpers import turned_batch


def test_every_weight_of_ours_has_a_counterpart_in_theirs():
    ours = PRNet(width=1.0)
    names = prnet_lockstep.layer_names(1) + prnet_lockstep.layer_norm_names(1)
    mapped = [name for name, _ in names]
    owners = {key.rsplit(".", 1)[0] for key in ours.state_dict()}
    assert owners == set(mapped) and len(mapped) == len(set(mapped))
    theirs = {name for _, name in names}
    assert {"acpnet.emb_nn.conv5", "acpnet.temp_net.nn.9", "acpnet.attention.model.decoder.layers.0.src_attn.linears.3",
            "acpnet.attention.model.encoder.layers.0.sublayer.1.norm"} <= theirs


def test_their_args_carry_our_settings_under_their_flags():
    network = {ours: f"value of {ours}" for ours in prnet_lockstep.AUTHORS_ARGS}
    args = prnet_lockstep.authors_args(network)
    assert (args.n_emb_dims, args.n_keypoints, args.cat_sampler) == ("value of emb_dims", "value of num_keypoints",
                                                                     "value of sampler")
    assert (args.emb_nn, args.attention, args.head, args.model_path) == ("dgcnn", "transformer", "svd", "")


def test_our_config_is_the_authors_main_py_defaults():
    network = compose_conf([*prnet_lockstep.PROTOCOL, "model_scale=1.0"]).model.network
    wanted = {**{k: v for k, (_, v) in prnet_lockstep.AUTHORS_ARGS.items()}, **prnet_lockstep.FIXED}
    assert {k: network[k] for k in wanted} == wanted


def test_their_torch_runs_cuda_code_on_the_cpu_in_the_default_dtype():
    view = prnet_lockstep.cpu_torch()
    assert view.device("cuda") == torch.device("cpu") and view.matmul is torch.matmul
    assert view.eye(3, dtype=torch.float32).dtype == torch.get_default_dtype()
    with lockstep.float64_mode():
        assert view.zeros(3, dtype=torch.float32).dtype == torch.float64
        assert view.from_numpy(torch.ones(2, dtype=torch.float32).numpy()).dtype == torch.float64
        assert view.eye(2, dtype=torch.int64).dtype == torch.int64


def test_the_caught_backward_keeps_the_loss_for_the_harness():
    weight = torch.ones(2, requires_grad=True)
    with prnet_lockstep._caught_backward() as caught:
        (weight * 3).sum().backward()
    assert weight.grad is None and len(caught) == 1
    caught[0].backward()
    assert torch.equal(weight.grad, torch.full((2,), 3.0))


def test_authors_without_model_py_other_widths_and_settings_are_config_errors(tmp_path, capsys):
    with pytest.raises(ConfigError, match="no model.py"):
        prnet_lockstep.load_authors(tmp_path)
    other = tmp_path / "other"
    other.mkdir()
    for name in ("model.py", "util.py"):
        (other / name).write_text("x = 1\n")
    with pytest.raises(ConfigError, match="not PRNet's"):
        prnet_lockstep.load_authors(other)
    common = ["--authors", str(tmp_path), "--out", str(tmp_path / "run"), "--steps", "0"]
    assert lockstep.main(["--method", "prnet", *common]) == 2
    assert "no model.py/util.py" in capsys.readouterr().err
    assert lockstep.main(["--method", "prnet", "--width", "0.5", *common]) == 2
    assert "width 1.0 only" in capsys.readouterr().err
    cfg = compose_conf([*prnet_lockstep.PROTOCOL, "model_scale=1.0", "model.network.num_keypoints=256"])
    with pytest.raises(ConfigError, match="num_keypoints"):
        prnet_lockstep.build(argparse.Namespace(authors=tmp_path, width=1.0), cfg)


def test_the_defaults_are_the_authors_recipe_and_the_budget_run():
    args = lockstep.parser_for(prnet_lockstep, "x", with_method=True).parse_args(
        ["--method", "prnet", "--authors", "a", "--out", "o"])
    assert (args.steps, args.val_every, args.batch, args.width) == (142, 14, 36, 1.0)
    assert (args.lr, args.weight_decay, args.milestones, args.val_pairs) == (1e-3, 1e-4, [0.29, 0.59, 0.79], None)


@pytest.mark.skipif(not os.environ.get("PRNET_AUTHORS_DIR"),
                    reason="PRNET_AUTHORS_DIR (a checkout of WangYueFt/prnet) not set: their side is not checked")
def test_same_start_against_the_authors_code(tmp_path):
    network = {k: v for k, (_, v) in prnet_lockstep.AUTHORS_ARGS.items()}
    network.update(prnet_lockstep.FIXED, num_keypoints=24)  # of 40 points: seconds, not minutes
    torch.manual_seed(0)
    pair = prnet_lockstep.make_pair(prnet_lockstep.load_authors(Path(os.environ["PRNET_AUTHORS_DIR"])), network)
    batch = turned_batch(3, 40)
    prnet_lockstep.check_same_start(pair, batch, tmp_path)  # raises ConfigError where the mapping is wrong
    result = json.loads((tmp_path / "start_check.json").read_text())
    assert result["eval"]["transform"] < 1e-10 and result["train"]["gradient_rel"] < 1e-10
    assert result["train_our_svd_weights"]["loss_rel"] > 1e-12  # the deviation the check removes is real
    loss, transform = pair.outputs("authors", batch)  # their float32 training step: a loss the harness backpropagates
    loss.backward()
    assert transform.shape == (3, 4, 4) and pair.nets["authors"].acpnet.emb_nn.conv1.weight.grad is not None
