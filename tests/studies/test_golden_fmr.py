"""FMR's golden reference (benchmarks/studies/golden/authors_fmr.py): the refusals, the encoders' layer map, and,
where FMR_AUTHORS_DIR names a checkout of XiaoshuiHuang/fmr, the authors' network with our weights computing what
ours computes (float64) and giving its golden file."""

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from baselines.learned.fmr import FMR
from benchmarks.studies.golden import authors_fmr, golden_file
from src.utils.errors import ConfigError

NETWORK = {"dim_k": 64, "width": 1.0}
AUTHORS_DIR = os.environ.get("FMR_AUTHORS_DIR")
needs_authors = pytest.mark.skipif(not AUTHORS_DIR, reason="FMR_AUTHORS_DIR (a checkout of XiaoshuiHuang/fmr) not set: "
                                   "their side is not checked")


def test_a_folder_without_the_authors_model_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="no model.py"):
        authors_fmr.load_authors(tmp_path)


def test_a_width_their_literals_cannot_take_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="literals"):
        authors_fmr.authors_network(tmp_path, FMR(**NETWORK), {**NETWORK, "width": 0.5})


def test_the_encoders_are_mapped_layer_for_layer_in_order():
    def block(c_in: int, c_out: int) -> list[nn.Module]:
        return [nn.Conv1d(c_in, c_out, 1), nn.BatchNorm1d(c_out), nn.ReLU()]

    theirs = nn.Module()  # their PointNet's layout (model.py:65-74): h1 3-64-64, h2 64-64-128-dim_k
    theirs.encoder = nn.Module()
    theirs.encoder.h1 = nn.Sequential(*block(3, 64), *block(64, 64))
    theirs.encoder.h2 = nn.Sequential(*block(64, 64), *block(64, 128), *block(128, 64))
    pairs = authors_fmr.layer_pairs(FMR(**NETWORK), theirs)
    ours = [f"encoder.mlp.layers.{i}" for i in (0, 1, 3, 4, 6, 7, 9, 10, 12, 13)]
    their_names = [f"encoder.{h}.{i}" for h, i in [("h1", 0), ("h1", 1), ("h1", 3), ("h1", 4), ("h2", 0), ("h2", 1),
                                                   ("h2", 3), ("h2", 4), ("h2", 6), ("h2", 7)]]
    assert pairs == list(zip(ours, their_names))


@needs_authors
def test_the_authors_network_with_our_weights_is_ours():
    torch.manual_seed(0)
    ours = FMR(**NETWORK, decoder_points=96)
    with torch.no_grad():
        ours.delta.copy_(torch.tensor([[-0.002, 0.015, 0.04, 0.02, 0.019, 0.0025]]))  # learned steps, some below 0.01
    ours = ours.double().eval()
    theirs = authors_fmr.authors_network(Path(AUTHORS_DIR), ours, NETWORK)
    src, ref = torch.rand(2, 2, 96, 3, dtype=torch.float64) - 0.5
    with torch.no_grad():
        expected = ours(src, ref)["transforms"][-1].numpy()
        got = authors_fmr.pose(theirs, src, ref)
    assert np.abs(got - expected).max() < 1e-10


@pytest.mark.shared_data("data/modelnet40_normal_resampled_airplane.zip")
@needs_authors
def test_the_authors_code_gives_its_golden_file(tmp_path):
    from benchmarks.studies.golden.authors import fmr
    from benchmarks.studies.golden.pairs import golden_pairs, prepare_cache

    pairs = {k: v[:8] for k, v in golden_pairs(prepare_cache(tmp_path)).items()}
    estimates = fmr(Path(AUTHORS_DIR), pairs, torch.float64)
    np.testing.assert_array_equal(estimates, golden_file.read_golden("fmr")["transforms"][:8])
