"""RPM-Net's golden reference (benchmarks/studies/golden/authors_rpmnet.py): loading the authors' code from a
checkout, their arguments from our settings, and, where RPMNET_AUTHORS_DIR names a checkout of yewzijian/RPMNet,
the authors' network with our weights computing what ours computes (float64)."""

import os
import sys
import types
from pathlib import Path

import pytest
import torch

from baselines.learned.rpmnet import RPMNet
from benchmarks.studies.golden import authors_rpmnet
from src.utils.errors import ConfigError

SETTINGS = {"num_iters": 3, "num_sk_iter": 5, "slack": True, "features": ["ppf", "dxyz", "xyz"], "feat_dim": 96,
            "radius": 0.3, "num_neighbors": 16, "normals": "estimated", "normals_k": 10}


def test_a_folder_without_the_authors_model_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="no src/models/rpmnet.py"):
        authors_rpmnet.load_authors(tmp_path)


def test_the_authors_modules_import_apart_from_modules_of_the_same_name(tmp_path, monkeypatch):
    models = tmp_path / "src" / "models"
    models.mkdir(parents=True)
    (models / "rpmnet.py").write_text("from models.feature_nets import WHO\n")
    (models / "feature_nets.py").write_text("WHO = 'authors'\n")
    elsewhere = types.ModuleType("models")
    monkeypatch.setitem(sys.modules, "models", elsewhere)
    loaded = authors_rpmnet.load_authors(tmp_path)
    assert loaded.rpmnet.WHO == "authors"
    assert sys.modules["models"] is elsewhere and "models.feature_nets" not in sys.modules
    assert str(tmp_path / "src") not in sys.path


def test_the_authors_arguments_are_our_settings():
    args = authors_rpmnet.authors_args({**SETTINGS, "slack": False}, feat_dim=48)
    assert (args.radius, args.num_neighbors, args.feat_dim, args.num_sk_iter, args.num_reg_iter) == (0.3, 16, 48, 5, 3)
    assert args.no_slack and args.features == ["ppf", "dxyz", "xyz"]


@pytest.mark.skipif(not os.environ.get("RPMNET_AUTHORS_DIR"),
                    reason="RPMNET_AUTHORS_DIR (a checkout of yewzijian/RPMNet) not set: the authors' side is not checked")
@pytest.mark.parametrize("width", [1.0, 0.5])
def test_the_authors_network_with_our_weights_is_ours(width):
    torch.manual_seed(0)
    settings = {**SETTINGS, "width": width}
    ours = RPMNet(**settings).double().eval()
    theirs = authors_rpmnet.authors_network(Path(os.environ["RPMNET_AUTHORS_DIR"]), ours, settings)
    src, ref = torch.rand(2, 2, 96, 3, dtype=torch.float64) - 0.5
    with torch.no_grad():
        expected = ours(src, ref)["transforms"][-1]
        got = authors_rpmnet.authors_estimate(theirs, ours, src, ref, settings["num_iters"])
    assert (got - expected).abs().max() < 1e-10
