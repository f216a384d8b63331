"""A learned method registers a pair in the frame its network was trained in, whatever the caller's units: the same
pair in millimetres, at 1e6 or 1e-3, or far from the origin gives the rotation of the pair at training scale and the
translation in the caller's units; a pair of the protocols is registered exactly as given (the shipped checkpoints)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from baselines import get_registrator
from baselines.conditioning import TrainingFrame, condition
from baselines.learned.adapter import card_frame, run_batches
from baselines.methods import learned_methods
from baselines.register_cli import register_files
from baselines.testing import euler_transform, make_pair, paper_range_pair
from src.data.point_files import read_points
from src.data.scans import shared_similarity
from src.utils.errors import CheckpointError

LEARNED = [method.key for method in learned_methods()]
#: (scale, offset) of the same pair: in kilometres, in millimetres, at 1e6, and 1e4 away from the origin.
UNITS = [(1e-3, 0.0), (1e3, 0.0), (1e6, 0.0), (1.0, 1e4)]
#: Largest difference of a rotation entry from the pair's at training scale: the network sees the same float32 clouds
#: (measured: 0 at every scale) except where the offset leaves the input 1e-12 of its size in float64 and a handful of
#: coordinates round to the neighbouring float32 (measured: up to 2.4e-7, RPM-Net).
ROTATION_ATOL = 1e-5


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray]:
    """A twice-sampled L-shaped pair (128 points: every network's fewest and more) in the training frame's own
    similarity (the union's centroid at the origin, its farthest point on the unit sphere): the similarity that takes
    the pair in other units into the frame gives back these very clouds, to float64 rounding."""
    src, ref = make_pair(euler_transform((20.0, 10.0, 30.0), (0.1, -0.2, 0.15)), 128, seed=3, twice_sampled=True)
    centre, scale = shared_similarity(src, ref)
    return (src - centre) / scale, (ref - centre) / scale


@pytest.mark.parametrize("name", LEARNED)
def test_a_learned_method_gives_the_training_scale_rotation_in_any_units(name, pair):
    registrator = get_registrator(name, device="cpu")
    src, ref = pair
    assert registrator.frame(src, ref) is None  # registered as given
    unit = registrator.register(src, ref)
    for scale, offset in UNITS:
        estimate = registrator.register(src * scale + offset, ref * scale + offset)
        np.testing.assert_allclose(estimate[:3, :3], unit[:3, :3], rtol=0, atol=ROTATION_ATOL, err_msg=f"{scale, offset}")
        shift = np.full(3, offset)  # ref' = R src' + (s t + o - R o) for src' = s src + o, ref' = s ref + o
        np.testing.assert_allclose(estimate[:3, 3], scale * unit[:3, 3] + shift - estimate[:3, :3] @ shift, rtol=0,
                                   atol=ROTATION_ATOL * scale, err_msg=f"{scale, offset}")


def test_pairs_of_the_protocols_are_registered_exactly_as_given():
    transform = np.eye(4)
    for seed in range(20):
        src, ref, _ = paper_range_pair(768, seed)  # unit-sphere shape, rotations to 45 deg, translations to 0.5
        ref = ref + np.clip(np.random.default_rng(seed).normal(0.0, 0.01, ref.shape), -0.05, 0.05)  # clipped noise
        same_src, same_ref, undo = condition(src, ref, frame=TrainingFrame(), budget=None)
        assert same_src is src and same_ref is ref and undo(transform) is transform
    dcp = get_registrator("dcp", device="cpu")
    assert np.array_equal(dcp.register(src, ref), dcp._forward(src[None], ref[None])[0])


def test_the_grid_and_the_scan_command_take_the_same_path(pair, tmp_path):
    """run_batches (the grid) conditions each pair of a batch on its own; `python -m baselines register` registers the
    clouds of its files with the same call."""
    dcp = get_registrator("dcp", device="cpu")
    src, ref = pair
    unit = dcp.register(src, ref)
    results = run_batches(dcp, [(src, ref), (1e3 * src, 1e3 * ref), (src + 1e4, ref + 1e4)], progress=False)
    assert np.array_equal(results[0].transform, unit)
    for result in results[1:]:
        np.testing.assert_allclose(result.transform[:3, :3], unit[:3, :3], rtol=0, atol=ROTATION_ATOL)
    files = [tmp_path / "a.xyz", tmp_path / "b.xyz"]
    for path, cloud in zip(files, (src, ref)):
        np.savetxt(path, 1e3 * cloud, fmt="%.9f")
    record = register_files(*files, "dcp", {"device": "cpu"}, points=768, threshold=None)
    assert np.array_equal(np.asarray(record["transform"]), dcp.register(read_points(files[0]), read_points(files[1])))
    np.testing.assert_allclose(np.asarray(record["transform"])[:3, :3], unit[:3, :3], rtol=0, atol=ROTATION_ATOL)
    assert record["normalisation"]["scale"] == pytest.approx(1e3)


def test_the_frame_is_the_one_the_card_beside_the_checkpoint_records(tmp_path):
    checkpoint = tmp_path / "run.ckpt"
    assert card_frame(str(checkpoint)) == TrainingFrame() == card_frame(None)  # no card: the data pipeline's
    checkpoint.with_suffix(".json").write_text(json.dumps({"experiment": {"pair": {"trans_mag": 2.0, "noise_clip": 0.0}}}))
    wide = card_frame(str(checkpoint))
    assert wide == TrainingFrame(translation=2.0, noise_clip=0.0)
    src, ref = make_pair(euler_transform((0.0, 0.0, 0.0), (2.0, 2.0, 0.0)), 200, seed=0)  # moved by 2 along x and y
    assert wide(src, ref) is None and TrainingFrame()(src, ref) is not None
    checkpoint.with_suffix(".json").write_text("not json")
    with pytest.raises(CheckpointError, match=r"run\.json lies beside .*run\.ckpt but is no checkpoint card"):
        card_frame(str(checkpoint))
