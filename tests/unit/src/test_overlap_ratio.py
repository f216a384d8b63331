"""The overlap-ratio protocol (partial X, Y from adjacent overlapping + non-overlapping parts) and
the evaluation sharding sampler used under DDP."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from torch.utils.data import DataLoader

from src.data.dataset import EvalShardSampler
from src.data.pipelines import build_pair_transforms
from src.data.transforms import (
    OverlapRatioCrop,
    RandomRigidTransform,
    median_spacing,
    overlap_fraction,
)
from src.utils.errors import ConfigError


def _surface(n=2048, seed=0):
    """Points on an ellipsoid surface (a closed shape like a CAD sampling)."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return (v * [0.9, 0.6, 0.4]).astype(np.float32)


def _ts_pair(seed):
    """Twice-sampled pair: two independent samplings of one surface, the source moved."""
    rng = np.random.default_rng(seed)
    sample = {"points_src": _surface(seed=2 * seed), "points_ref": _surface(seed=2 * seed + 1), "transform_gt": np.eye(4)}
    return RandomRigidTransform()(sample, rng), rng


def _apply(transform, points):
    return points @ transform[:3, :3].T + transform[:3, 3]


@pytest.mark.parametrize("ratio", [1.0, 0.8, 0.5, 0.3, 0.1])
def test_once_sampled_overlap_is_exactly_the_requested_ratio(ratio):
    """OS: the overlap is measured exactly, as the points of Y with an exact counterpart in X."""
    for seed in range(3):
        rng = np.random.default_rng(seed)
        points = _surface(seed=seed)
        sample = RandomRigidTransform()({"points_src": points.copy(), "points_ref": points.copy(), "transform_gt": np.eye(4)}, rng)
        out = OverlapRatioCrop(ratio, num_keep=768)(sample, rng)
        x, y = _apply(out["transform_gt"], out["points_src"]), out["points_ref"]
        assert out["points_src"].shape == (768, 3) and y.shape == (768, 3)
        assert overlap_fraction(y, x, 1e-4) == round(ratio * 768) / 768
        assert len(np.unique(y, axis=0)) == 768  # no repeated points when the regions are large enough


@pytest.mark.parametrize("ratio", [1.0, 0.9, 0.7, 0.5, 0.3, 0.1])
def test_twice_sampled_overlap_is_close_to_the_requested_ratio(ratio):
    """TS (no exact counterparts): the fraction of Y within 2 point spacings of X under-counts
    (sparse spots), within 3 spacings over-counts (a band past the border); they bracket the ratio."""
    tight, loose = [], []
    for seed in range(4):
        sample, rng = _ts_pair(seed)
        spacing = median_spacing(sample["points_ref"])
        out = OverlapRatioCrop(ratio, num_keep=768)(sample, rng)
        x, y = _apply(out["transform_gt"], out["points_src"]), out["points_ref"]
        assert y.shape == (768, 3)
        tight.append(overlap_fraction(y, x, 2 * spacing))
        loose.append(overlap_fraction(y, x, 3 * spacing))
        # the two parts of Y are adjacent: no piece of Y lies away from the rest
        assert cKDTree(y).query(y, k=2)[0][:, 1].max() < 6 * spacing
    assert np.mean(tight) <= ratio + 0.03 and np.mean(loose) >= ratio - 0.03
    assert np.mean(tight) == pytest.approx(ratio, abs=0.06)


def test_overlap_decreases_monotonically_and_pairs_are_deterministic():
    pipeline = lambda r: build_pair_transforms("independent_samplings", sampling="ts", overlap_ratio=r)  # noqa: E731
    shapes = np.stack([_surface(seed=s) for s in range(3)])
    fractions = []
    for ratio in (0.9, 0.6, 0.3):
        a = pipeline(ratio)({"shape_points": shapes}, np.random.default_rng(7))
        b = pipeline(ratio)({"shape_points": shapes}, np.random.default_rng(7))
        np.testing.assert_array_equal(a["points_ref"], b["points_ref"])
        x = _apply(a["transform_gt"], a["points_src"])
        fractions.append(overlap_fraction(a["points_ref"], x, 2.0 * median_spacing(shapes[0])))
    assert fractions[0] > fractions[1] > fractions[2]


def test_overlap_ratio_options_are_checked():
    with pytest.raises(ConfigError, match="PRNet manner"):
        build_pair_transforms("independent_samplings", partial="rpmnet", overlap_ratio=0.5)
    with pytest.raises(ConfigError, match=r"\[0, 1\]"):
        OverlapRatioCrop(1.5)
    # without overlap_ratio the PRNet pipeline is unchanged
    names = [type(t).__name__ for t in build_pair_transforms("independent_samplings").transforms]
    assert names == ["PickPair", "RandomRigidTransform", "PRNetCrop", "GaussianNoise", "Shuffle"]


@pytest.mark.parametrize("size,batch,world", [(7, 3, 2), (10, 2, 3), (64, 8, 4), (5, 5, 1)])
def test_eval_shard_sampler_covers_every_pair_once_in_the_single_process_batches(size, batch, world):
    shards = [list(EvalShardSampler(size, batch, world=world, rank=r)) for r in range(world)]
    assert sorted(i for s in shards for i in s) == list(range(size))  # no padding, no repeats
    assert [len(EvalShardSampler(size, batch, world=world, rank=r)) for r in range(world)] == [len(s) for s in shards]
    single = [list(b) for b in DataLoader(range(size), batch_size=batch)]
    got = [list(b) for s in shards for b in DataLoader(s, batch_size=batch)]
    assert sorted(map(tuple, got)) == sorted(map(tuple, single))  # every batch as in one process


def test_eval_shard_sampler_single_process_is_sequential_and_too_few_batches_fail():
    assert list(EvalShardSampler(5, 2)) == [0, 1, 2, 3, 4]
    with pytest.raises(ConfigError, match="fewer than the 4 DDP processes"):
        EvalShardSampler(5, 2, world=4, rank=0)
