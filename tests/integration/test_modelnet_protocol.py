"""+exp=modelnet / modellonet (Predator's and RegTR's partial ModelNet40 protocol) and their real-airplane
stand-ins (real airplanes, real bathtubs): the composed settings are the authors' code's, and their pairs are what
that code draws."""

import numpy as np
import pytest

from src.compose import compose_experiment
from src.data.dataset import PairDataset
from src.data.pipelines import build_pair_transforms

PROTOCOL = {"sampling": "os", "partial": "rpmnet", "num_points": 2048, "rot_mag": 45.0, "trans_mag": 0.5,
            "rpmnet_resample_points": 717, "noise_sigma": 0.01, "noise_clip": 0.05}
P_KEEP = {"modelnet": 0.7, "modellonet": 0.5, "real_airplane_modelnet": 0.7, "real_airplane_modellonet": 0.5,
          "real_bathtub_modelnet": 0.7, "real_bathtub_modellonet": 0.5}


def _compose(experiment: str, *overrides: str):
    return compose_experiment([f"+exp={experiment}", *overrides])


@pytest.mark.parametrize("experiment", P_KEEP)
def test_protocol_values(experiment):
    pair = _compose(experiment).data.pair
    assert {key: pair[key] for key in PROTOCOL} == PROTOCOL
    assert pair.rpmnet_p_keep == P_KEEP[experiment]


@pytest.mark.parametrize("experiment", ["modelnet", "modellonet"])
def test_unseen_categories_none_removed(experiment):
    """Train and validate on the first 20 categories, test on the test split of the other 20, the
    axisymmetric ones kept (the authors' category files list all 20 of each half)."""
    cfg = _compose(experiment)
    assert cfg.data.dataset == "modelnet40" and cfg.data.remove_axisymmetric is False
    splits = {stage: (spec.split, spec.categories) for stage, spec in cfg.data.splits.items()}
    assert splits == {"train": ("train", "half1"), "val": ("test", "half1"), "test": ("test", "half2")}
    assert _compose(experiment, "data=synthetic").data.dataset == "synthetic"  # the synthetic data, when asked for


@pytest.mark.parametrize("experiment", ["real_airplane_modelnet", "real_airplane_modellonet"])
def test_stand_ins_keep_the_real_airplane_carve_out(experiment):
    cfg, real = _compose(experiment), _compose("real_airplane")
    assert cfg.data.dataset == real.data.dataset == "modelnet40_resampled"
    assert cfg.data.splits == real.data.splits


@pytest.mark.parametrize("crop", ["modelnet", "modellonet"])
def test_bathtub_stand_ins_differ_from_the_airplane_ones_only_in_the_test_category(crop):
    """The same pairs and training splits; the test set the last 100 bathtub train ids instead of the airplanes'."""
    bathtub, airplane = _compose(f"real_bathtub_{crop}"), _compose(f"real_airplane_{crop}")
    assert bathtub.data.pair == airplane.data.pair and bathtub.data.dataset == airplane.data.dataset
    assert {s: bathtub.data.splits[s] for s in ("train", "val")} == {s: airplane.data.splits[s] for s in ("train", "val")}
    test, plane_test = bathtub.data.splits.test, airplane.data.splits.test
    assert list(test.categories) == ["bathtub"] and list(plane_test.categories) == ["airplane"]
    assert (test.split, list(test.slice)) == (plane_test.split, list(plane_test.slice)) == ("train", ["-100", None])


@pytest.mark.parametrize("experiment", ["modelnet", "modellonet"])
def test_pairs_are_717_points_with_the_clean_full_reference(experiment):
    """Both clouds 717 points (at 50 % crops too), noisy; ``points_raw`` the clean 2,048 points the
    (once-sampled) pair was cut from, on which the ground truth lays the source within the noise."""
    pair = dict(_compose(experiment).data.pair)
    shapes = np.random.default_rng(0).normal(size=(2, 1, 2048, 3)).astype(np.float32)
    dataset = PairDataset(shapes, np.zeros(2), np.arange(2), build_pair_transforms("single_sampling", **pair), seed=1)
    item = dataset[0]
    assert item["points_src"].shape == (717, 3) and item["points_ref"].shape == (717, 3)
    raw = item["points_raw"].numpy()
    assert raw.shape == (2048, 3)
    np.testing.assert_allclose(np.sort(raw, axis=0), np.sort(shapes[0, 0], axis=0), atol=1e-6)  # the reference frame
    gt = item["transform_gt"].numpy().astype(np.float64)
    moved = item["points_src"].numpy() @ gt[:3, :3].T + gt[:3, 3]
    gaps = np.linalg.norm(moved[:, None] - raw[None], axis=2).min(axis=1)
    assert gaps.max() <= 2 * 0.05 * np.sqrt(3) and gaps.mean() > 1e-3  # noise, clipped, on both clouds
