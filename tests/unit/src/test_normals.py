"""Normals through the pair pipelines: rotated with their cloud, selected row for row with its points,
untouched by noise, absent pipelines unchanged; PairDataset and the datamodule's ``data.normals``."""

import hydra
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from scipy.spatial import cKDTree

from baselines.learned.common.correspondence import estimate_normals
from baselines.learned.rpmnet import RPMNet
from src.config import register_resolvers
from src.data.cache import CacheSplit, write_cache
from src.data.datamodule import RegistrationDataModule
from src.data.dataset import PairDataset
from src.data.pipelines import build_pair_transforms
from src.data.prepare import prepare
from src.data.sampling import sample_shape
from src.data.synthetic import generate_shapes
from src.data.transforms import (
    GaussianNoise,
    OverlapRatioCrop,
    PRNetCrop,
    RandomRigidTransform,
    Resample,
    RPMNetCrop,
    Shuffle,
)
from src.utils.errors import ConfigError, DatasetError, PointCloudError
from src.utils.paths import REPO_ROOT, shared_path

AIRPLANES = shared_path("data", "modelnet40_normal_resampled_airplane.zip")

CASES = [(pair_sampling, sampling, partial, None) for pair_sampling in ("independent_samplings", "disjoint_subsets")
         for sampling in ("os", "ts") for partial in ("prnet", "rpmnet", "none")]
CASES += [("independent_samplings", sampling, "prnet", 0.5) for sampling in ("os", "ts")]


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _shape(pair_sampling, seed=0):
    """Points (S, P, 3) of an anisotropic blob and random unit normals unrelated to the positions, so
    a normal identifies its point only through its row."""
    rng = np.random.default_rng(seed)
    samplings, points = (4, 2048) if pair_sampling == "independent_samplings" else (1, 5000)
    base = rng.normal(size=(1, points, 3)) * [1.0, 0.6, 0.3]
    cloud = base + rng.normal(scale=0.01, size=(samplings, points, 3))
    return cloud.astype(np.float32), _unit(rng.normal(size=cloud.shape)).astype(np.float32)


def _pair(case, seed=0, noise=0.0, with_normals=True):
    pair_sampling, sampling, partial, ratio = case
    points, normals = _shape(pair_sampling)
    pipeline = build_pair_transforms(pair_sampling, sampling=sampling, partial=partial, noise_sigma=noise,
                                     overlap_ratio=ratio)
    start = {"shape_points": points, **({"shape_normals": normals} if with_normals else {})}
    return pipeline(start, np.random.default_rng(seed)), points, normals


def _apply(transform, points):
    return points @ transform[:3, :3].T + transform[:3, 3]


@pytest.mark.parametrize("case", CASES, ids=lambda c: "-".join(map(str, c)))
def test_each_normal_is_its_points_normal_rotated_into_the_clouds_frame(case):
    """Map each cloud back to the canonical frame (identity, gt or gt⁻¹: whichever the manner moved),
    find each point's row among the shape's points: its normal is that row's normal, rotated."""
    sample, points, normals = _pair(case)
    tree = cKDTree(points.reshape(-1, 3))
    gt = sample["transform_gt"]
    for cloud in ("src", "ref"):
        cloud_points, cloud_normals = sample[f"points_{cloud}"], sample[f"normals_{cloud}"]
        assert cloud_normals.shape == cloud_points.shape and cloud_normals.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(cloud_normals, axis=1), 1.0, atol=1e-6)
        frames = [np.eye(4), gt, np.linalg.inv(gt)]
        matches = [tree.query(_apply(np.linalg.inv(frame), cloud_points)) for frame in frames]
        k = int(np.argmin([dist.max() for dist, _ in matches]))
        dist, rows = matches[k]
        assert dist.max() < 1e-4, cloud
        expected = normals.reshape(-1, 3)[rows] @ frames[k][:3, :3].T
        np.testing.assert_allclose(cloud_normals, expected, atol=1e-5)


@pytest.mark.parametrize("case", [c for c in CASES if c[1] == "os"], ids=lambda c: "-".join(map(str, c)))
def test_once_sampled_counterparts_normals_map_by_the_ground_truth_rotation(case):
    sample, _, _ = _pair(case, seed=3)
    gt = sample["transform_gt"]
    dist, idx = cKDTree(sample["points_ref"]).query(_apply(gt, sample["points_src"]))
    matched = dist < 1e-4
    assert matched.sum() > 100
    np.testing.assert_allclose(sample["normals_src"][matched] @ gt[:3, :3].T, sample["normals_ref"][idx[matched]],
                               atol=1e-5)


@pytest.mark.parametrize("case", CASES, ids=lambda c: "-".join(map(str, c)))
def test_points_and_ground_truth_are_the_same_with_or_without_normals(case):
    with_normals, _, _ = _pair(case, seed=5, noise=0.01)
    without, _, _ = _pair(case, seed=5, noise=0.01, with_normals=False)
    assert {"normals_src", "normals_ref"} <= set(with_normals) and not {"normals_src", "normals_ref"} & set(without)
    for key in ("points_src", "points_ref", "transform_gt"):
        np.testing.assert_array_equal(with_normals[key], without[key])


def _identified_cloud(n=2048, seed=0):
    """A sample whose normals encode their points (n = unit(p − c) for a c outside the cloud)."""
    rng = np.random.default_rng(seed)
    src, ref = (rng.normal(size=(n, 3)).astype(np.float32) for _ in range(2))
    return {"points_src": src, "points_ref": ref, "normals_src": _unit(src - 10.0), "normals_ref": _unit(ref - 10.0),
            "transform_gt": np.eye(4)}


@pytest.mark.parametrize("transform", [PRNetCrop(768), RPMNetCrop(0.7), Resample(1024, 0.7), Shuffle(),
                                       OverlapRatioCrop(0.5)], ids=lambda t: type(t).__name__)
def test_every_selecting_transform_keeps_each_points_normal(transform):
    out = transform(_identified_cloud(), np.random.default_rng(1))
    for cloud in ("src", "ref"):
        assert len(out[f"normals_{cloud}"]) == len(out[f"points_{cloud}"])
        np.testing.assert_allclose(out[f"normals_{cloud}"], _unit(out[f"points_{cloud}"] - 10.0), atol=1e-6)


@pytest.mark.parametrize("apply_to", ["src", "ref"])
def test_the_rigid_transform_rotates_only_the_moved_clouds_normals(apply_to):
    sample = _identified_cloud()
    before = {k: v.copy() for k, v in sample.items()}
    out = RandomRigidTransform(apply_to=apply_to)(sample, np.random.default_rng(2))
    still = "ref" if apply_to == "src" else "src"
    np.testing.assert_array_equal(out[f"normals_{still}"], before[f"normals_{still}"])
    drawn = out["transform_gt"] if apply_to == "ref" else np.linalg.inv(out["transform_gt"])
    np.testing.assert_allclose(out[f"normals_{apply_to}"], before[f"normals_{apply_to}"] @ drawn[:3, :3].T, atol=1e-6)


def test_noise_moves_points_only():
    sample = _identified_cloud()
    normals = sample["normals_src"].copy()
    out = GaussianNoise(sigma=0.01)(sample, np.random.default_rng(3))
    np.testing.assert_array_equal(out["normals_src"], normals)
    assert not np.allclose(out["points_src"], _identified_cloud()["points_src"])


def test_pair_dataset_returns_unit_normal_tensors_only_when_given():
    points, normals = _shape("independent_samplings")
    points, normals = np.stack([points, points]), 3.0 * np.stack([normals, normals])  # non-unit in the cache
    pipeline = build_pair_transforms("independent_samplings", sampling="ts", partial="rpmnet", noise_sigma=0.01)
    plain = PairDataset(points, np.zeros(2), np.arange(2), pipeline, seed=0)[1]
    item = PairDataset(points, np.zeros(2), np.arange(2), pipeline, seed=0, normals=normals)[1]
    assert "normals_src" not in plain and item["normals_src"].shape == item["points_src"].shape == (717, 3)
    torch.testing.assert_close(item["normals_ref"].norm(dim=1), torch.ones(717))
    torch.testing.assert_close(item["points_src"], plain["points_src"], rtol=0, atol=0)
    with pytest.raises(PointCloudError, match="do not match"):
        PairDataset(points, np.zeros(2), np.arange(2), pipeline, seed=0, normals=normals[:, :1])
    normals[0, :, 7] = 0.0
    with pytest.raises(DatasetError, match="zero-length or NaN normals"):
        PairDataset(points, np.zeros(2), np.arange(2), pipeline, seed=0, normals=normals)[0]


@pytest.fixture(scope="module")
def mesh_cache(tmp_path_factory):
    """A mesh-sampled cache that keeps the synthetic meshes' face normals (as prepare would with
    normals kept), and the same cache without them."""
    root = tmp_path_factory.mktemp("normals_cache")
    shapes = list(generate_shapes(0, 1, seed=0))[:4]
    sampled = [sample_shape(shape, 2, 2048, seed=0, shape_index=i) for i, shape in enumerate(shapes)]
    points, normals = (np.stack([s[k] for s in sampled]) for k in (0, 1))
    fields = {"dataset": "modelnet40", "source_layout": "procedural", "pair_sampling": "independent_samplings",
              "categories": sorted({s.category for s in shapes}), "halves": {"1": [], "2": []}, "sampling": {},
              "source": {}}
    labels = np.array([fields["categories"].index(s.category) for s in shapes])
    names = [s.name for s in shapes]
    write_cache(root / "with" / "modelnet40", fields, {"test": CacheSplit("test", points, normals, labels, names)})
    write_cache(root / "without" / "modelnet40", fields, {"test": CacheSplit("test", points, None, labels, names)})
    return root


def _datamodule(root, normals):
    return RegistrationDataModule(
        dataset="modelnet40", cache_root=str(root), splits={"test": {"split": "test", "categories": "all"}},
        remove_axisymmetric=False, pair={"sampling": "ts", "partial": "rpmnet", "noise_sigma": 0.01},
        eval_batch_size=4, num_workers=0, normals=normals,
    )


def test_datamodule_carries_face_normals_that_fit_the_received_points(mesh_cache):
    dm = _datamodule(mesh_cache / "with", "cache")
    dm.setup("test")
    batch = next(iter(dm.test_dataloader()))
    plain = _datamodule(mesh_cache / "with", "none")
    plain.setup("test")
    plain_batch = next(iter(plain.test_dataloader()))
    assert "normals_src" not in plain_batch
    torch.testing.assert_close(batch["points_src"], plain_batch["points_src"], rtol=0, atol=0)
    for cloud in ("src", "ref"):
        given = batch[f"normals_{cloud}"]
        assert given.shape == (4, 717, 3)
        cosine = (given * estimate_normals(batch[f"points_{cloud}"], k=20)).sum(-1).abs()
        assert cosine.median() > 0.9  # each face normal is its (noisy, cropped, moved) point's surface normal


def test_datamodule_normals_switch_errors(mesh_cache):
    with pytest.raises(ConfigError, match="data.normals must be one of"):
        _datamodule(mesh_cache / "with", "estimated")
    dm = _datamodule(mesh_cache / "without", "cache")
    with pytest.raises(DatasetError, match="stores no normals for split 'test'"):
        dm.setup("test")


@pytest.mark.shared_data("data/modelnet40_normal_resampled_airplane.zip")
def test_real_airplane_normals_reach_rpmnet_with_the_files_sign(tmp_path):
    """data.normals=cache on the PointNet++ resampled airplanes: unit normals that fit the received
    points, given to RPMNet as they are (not re-signed like the centroid-signed estimates)."""
    register_resolvers()
    prepare("modelnet40_resampled", source=AIRPLANES, cache_root=tmp_path, limit=4, workers=1)
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=real_airplane", "test_size=1", "val_size=1", "val_repeat=2", "partial=rpmnet", "data.normals=cache",
                                           f"data.cache_root={tmp_path}", "data.num_workers=0",
                                           f"output_dir={tmp_path / 'unused'}"])
    dm = hydra.utils.instantiate(cfg.data)
    dm.setup("validate")
    batch = next(iter(dm.val_dataloader()))
    cosine = (batch["normals_src"] * estimate_normals(batch["points_src"], k=30)).sum(-1)
    torch.testing.assert_close(batch["normals_src"].norm(dim=-1), torch.ones(2, 717))
    assert cosine.abs().median() > 0.9 and (cosine < 0).any()  # same lines, the files' own signs
    model = RPMNet(width=0.125, num_neighbors=16, normals="given").eval()
    with torch.no_grad():
        out = model(batch["points_src"], batch["points_ref"], normals_src=batch["normals_src"],
                    normals_ref=batch["normals_ref"])
    assert torch.isfinite(out["transforms"][-1]).all()


def test_synthetic_and_mesh_caches_keep_face_normals_when_asked(tmp_path, princeton_dir):
    """data.build.normals / --normals: the cache stores the sampled faces' normals (unit, one per point);
    without it the cache is the same as before (no normals, the same sampling record)."""
    from src.data.prepare import build_synthetic_cache, prepare

    plain = build_synthetic_cache(tmp_path / "a", num_train_per_category=1, num_test_per_category=1, num_samplings=2,
                                  num_points=64)
    assert plain.split("train").normals is None and "normals" not in plain.manifest["sampling"]
    with_normals = build_synthetic_cache(tmp_path / "a", num_train_per_category=1, num_test_per_category=1,
                                         num_samplings=2, num_points=64, normals=True)
    split = with_normals.split("train")
    assert split.normals is not None and split.normals.shape == split.points.shape
    np.testing.assert_allclose(np.linalg.norm(split.normals, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(split.points, plain.split("train").points)  # same samplings, normals added
    mesh = prepare("modelnet40", source=princeton_dir, cache_root=tmp_path / "m", num_samplings=2, num_points=32,
                   normals=True)
    assert mesh.split("train").normals.shape == mesh.split("train").points.shape


def test_registration_module_hands_the_batch_normals_to_a_network_that_uses_them():
    """RegistrationModule passes normals_src/normals_ref only to a network with uses_normals (RPMNet
    normals=given): its training and evaluation steps run on a batch with normals; OMNet gets points only."""
    from src.models.module import RegistrationModule

    rng = torch.Generator().manual_seed(0)
    points = torch.rand(2, 64, 3, generator=rng)
    normals = torch.nn.functional.normalize(torch.randn(2, 64, 3, generator=rng), dim=-1)
    batch = {"points_src": points, "points_ref": points.clone(), "transform_gt": torch.eye(4).expand(2, 4, 4),
             "normals_src": normals, "normals_ref": normals.clone()}
    given = RegistrationModule({"_target_": "baselines.learned.rpmnet.RPMNet", "width": 0.125, "num_neighbors": 8,
                                "normals": "given"})
    assert torch.isfinite(given.training_step(batch, 0))
    assert given(points, points, normals, normals).shape == (2, 4, 4)
    omnet = RegistrationModule({"_target_": "src.models.omnet.OMNet", "width": 0.0625})
    assert omnet._normals(normals, normals) == {}
    assert torch.isfinite(omnet.training_step(batch, 0))
