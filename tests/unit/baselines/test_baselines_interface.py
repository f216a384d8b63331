"""The Registrator interface: registry, config handling, input checks, rigidity checks."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from baselines import (
    Registrator,
    available_registrators,
    check_cloud,
    get_registrator,
    register_registrator,
    transform_problem,
)
from baselines.conditioning import POINT_BUDGET, budget_voxel_size, condition, voxel_down_sample, working_frame
from baselines.registry import _REGISTRY
from baselines.testing import ToyRegistrator, euler_transform, l_shape_surface, make_pair
from src.utils.errors import ConfigError, PointCloudError, RegistrationError
from src.geometry.numpy_rigid import project_to_rotation


def test_registry_lists_the_classical_methods():
    assert {"icp", "fgr", "symmetric_icp", "goicp", "identity"} <= set(available_registrators())


def test_identity_returns_the_identity():
    import numpy as np

    src = np.random.default_rng(0).normal(size=(20, 3))
    np.testing.assert_array_equal(get_registrator("identity").register(src, src + 1.0), np.eye(4))


def test_unknown_method_names_the_available_ones():
    with pytest.raises(ConfigError) as info:
        get_registrator("sparse_icp")
    msg = str(info.value)
    assert "sparse_icp" in msg and "icp" in msg and "fgr" in msg and "symmetric_icp" in msg
    assert "\n" not in msg


def test_names_are_normalised_and_aliased():
    assert get_registrator("ICP").name == "icp"
    assert get_registrator("Symmetric-ICP").name == "symmetric_icp"


def test_unknown_config_key_and_bad_value_raise_config_error():
    with pytest.raises(ConfigError, match="max_iterations"):
        get_registrator("icp", max_iteration=3)  # typo: lists the valid keys
    with pytest.raises(ConfigError, match="max_correspondence_distance"):
        get_registrator("icp", max_correspondence_distance=-1.0)
    with pytest.raises(ConfigError, match="normal_orientation"):
        get_registrator("fgr", normal_orientation="sideways")


def test_config_overrides_and_attributes():
    icp = get_registrator("icp", max_iterations=7)
    assert icp.config.max_iterations == 7
    assert icp.needs_training is False and icp.needs_normals is False
    fgr = get_registrator("fgr")
    assert fgr.needs_normals is True
    # registrators travel to worker processes
    clone = pickle.loads(pickle.dumps(icp))
    assert clone.config == icp.config


def test_register_registrator_supports_lazy_adapters():
    register_registrator("toy_adapter", "baselines.testing:ToyRegistrator")
    try:
        reg = get_registrator("toy_adapter", sleep_s=0.0)
        assert isinstance(reg, ToyRegistrator) and isinstance(reg, Registrator)
    finally:
        _REGISTRY.pop("toy_adapter")


@pytest.mark.parametrize(
    "points, match",
    [
        (np.zeros((2, 3)), "at least 3 points"),
        (np.zeros((0, 3)), "at least 3 points"),
        (np.zeros((10, 2)), r"expected an \(N, 3\) array"),
        (np.zeros((4, 3, 1)), r"expected an \(N, 3\) array"),
        (np.zeros(5), r"expected an \(N, 3\) array"),
        ([[0, 0, 0], [1, 0, 0], [0, float("nan"), 0]], "NaN or infinite"),
        ([[0, 0, 0], [1, 0, 0], [0, float("inf"), 0]], "NaN or infinite"),
        ([["a", "b", "c"]] * 3, "expected real numbers"),
        (np.ones((3, 3)), "degenerate cloud, its 3 points are all the same point"),
        ([[0, 0, 0], [1, 1, 1]] * 50, r"degenerate cloud, its 100 points are all on one line \(2 distinct\)"),
        (np.outer(np.linspace(-1, 1, 40), [1, 2, 3]) + 5, r"all on one line \(40 distinct\)"),
    ],
)
def test_bad_clouds_raise_one_line_point_cloud_errors(points, match):
    reg = ToyRegistrator()
    good = l_shape_surface(50)
    with pytest.raises(PointCloudError, match=match) as info:
        reg.register(points, good)
    assert str(info.value).startswith("src:") and "\n" not in str(info.value)
    with pytest.raises(PointCloudError, match=match) as info:
        reg.register(good, points)
    assert str(info.value).startswith("ref:")


@pytest.mark.parametrize(
    "points", [np.zeros((2, 3)), np.zeros((5, 2)), [[0, 0, 0], [1, 0, 0], [0, float("nan"), 0]], np.ones((4, 3))]
)
def test_torch_clouds_get_the_same_one_line_errors(points):
    import torch

    with pytest.raises(PointCloudError) as numpy_error:
        check_cloud(np.asarray(points), "src")
    with pytest.raises(PointCloudError) as torch_error:
        check_cloud(torch.tensor(np.asarray(points), dtype=torch.float32, requires_grad=True), "src")
    assert str(torch_error.value) == str(numpy_error.value) and "\n" not in str(numpy_error.value)
    check_cloud(np.ones((4, 3)), "normals", allow_degenerate=True)  # the one check that can be left out


def test_check_cloud_returns_float64_contiguous():
    out = check_cloud((np.arange(12, dtype=np.float32) ** 2).reshape(4, 3)[::-1])
    assert out.dtype == np.float64 and out.flags.c_contiguous


def test_register_batch_shapes_and_errors():
    reg = ToyRegistrator()
    truth = euler_transform((0, 0, 0), (0.1, -0.2, 0.3))
    pairs = [make_pair(truth, 60, seed=s) for s in range(3)]
    src = np.stack([p[0] for p in pairs])
    ref = np.stack([p[1] for p in pairs])
    out = reg.register_batch(src, ref)
    assert out.shape == (3, 4, 4)
    np.testing.assert_allclose(out[:, :3, 3], np.tile([0.1, -0.2, 0.3], (3, 1)), atol=1e-9)
    with pytest.raises(PointCloudError, match="differ in size"):
        reg.register_batch(src, ref[:2])
    with pytest.raises(PointCloudError, match=r"\(B, N, 3\)"):
        reg.register_batch(src[0], ref[0])
    bad = src.copy()
    bad[1, 4, 2] = np.nan
    with pytest.raises(PointCloudError, match=r"src\[1\]"):
        reg.register_batch(bad, ref)


def test_transform_problem():
    good = euler_transform((30, -20, 10), (0.1, 0.2, 0.3))
    assert transform_problem(good) is None
    assert "shape" in transform_problem(np.eye(3))
    nan = good.copy()
    nan[0, 0] = np.nan
    assert "NaN" in transform_problem(nan)
    assert "orthonormal" in transform_problem(np.diag([2.0, 1.0, 1.0, 1.0]))
    assert "det" in transform_problem(np.diag([-1.0, 1.0, 1.0, 1.0]))
    row = good.copy()
    row[3, 0] = 0.5
    assert "bottom row" in transform_problem(row)


def test_project_to_rotation_is_proper():
    rng = np.random.default_rng(0)
    rot = project_to_rotation(rng.normal(size=(3, 3)))
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)


class SizeRecorder(ToyRegistrator):
    """The toy method, remembering the clouds it was handed."""

    def _register(self, src, ref):
        self.seen = (src, ref)
        return super()._register(src, ref)


def test_a_plane_is_not_degenerate():
    plane = np.c_[np.random.default_rng(0).random((50, 2)), np.zeros(50)]
    assert check_cloud(plane).shape == (50, 3)


def test_pairs_of_the_protocols_are_registered_as_given():
    src, ref = make_pair(euler_transform((45, 45, 45), (0.5, -0.5, 0.5)), 717, seed=0)
    assert working_frame(src, ref) is None and working_frame(0.2 * src, 0.2 * ref) is None
    reg = SizeRecorder()
    reg.register(src, ref)
    assert np.array_equal(reg.seen[0], src) and np.array_equal(reg.seen[1], ref)


@pytest.mark.parametrize("scale, offset", [(1e9, 0.0), (1e-6, 0.0), (1.0, 1e9), (1e4, -3e7)])
def test_pairs_outside_the_working_frame_are_normalised_and_mapped_back(scale, offset):
    truth = euler_transform((0, 0, 0), (0.3, -0.2, 0.1))
    src, ref = (c * scale + offset for c in make_pair(truth, 300, seed=1))
    reg = SizeRecorder()
    estimate = reg.register(src, ref)
    seen_src, seen_ref = reg.seen
    radius = max(np.linalg.norm(c - c.mean(axis=0), axis=1).max() for c in (seen_src, seen_ref))
    assert 0.7 <= radius < 1.42 and max(np.abs(seen_src).max(), np.abs(seen_ref).max()) < 2.0
    np.testing.assert_allclose(estimate[:3, :3], np.eye(3))
    np.testing.assert_allclose(estimate[:3, 3], scale * truth[:3, 3], rtol=0, atol=1e-9 * scale + 1e-14 * abs(offset))


def test_large_clouds_are_voxel_down_sampled_to_the_point_budget():
    truth = euler_transform((0, 0, 0), (0.3, -0.2, 0.1))
    src, ref = make_pair(truth, 3 * POINT_BUDGET, seed=2)
    reg = SizeRecorder()
    estimate = reg.register(src, ref[: POINT_BUDGET // 2])
    assert max(len(c) for c in reg.seen) <= POINT_BUDGET and min(len(c) for c in reg.seen) > 0.4 * POINT_BUDGET // 2
    np.testing.assert_allclose(estimate[:3, 3], [0.3, -0.2, 0.1], atol=0.05)  # centroids of the down-sampled clouds
    reg.point_budget = None  # per instance: off
    reg.register(src, ref)
    assert len(reg.seen[0]) == 3 * POINT_BUDGET


def test_voxel_down_sample_averages_each_occupied_voxel():
    points = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.2, 0.2], [1.7, 0.2, 0.4]])
    out = voxel_down_sample(points, 1.0)
    np.testing.assert_allclose(sorted(map(tuple, out)), [(0.2, 0.2, 0.2), (1.6, 0.2, 0.3)])
    cloud = l_shape_surface(20000)
    voxel = budget_voxel_size([cloud], 1000)
    assert 700 < len(voxel_down_sample(cloud, voxel)) <= 1000


# --- the result object -----------------------------------------------------------------------------


def test_register_result_reports_the_transform_time_and_inlier_fit():
    lattice = np.stack(np.meshgrid(*[np.arange(3) * 0.5] * 3), axis=-1).reshape(-1, 3)
    src = np.concatenate([lattice, lattice + [10.0, 0.0, 0.0]])  # half of it far from the reference
    ref = lattice + [0.01, 0.0, 0.0]
    identity = get_registrator("identity")
    result = identity.register_result(src, ref)
    assert np.array_equal(result.transform, identity.register(src, ref)) and np.array_equal(result.transform, np.eye(4))
    assert not result.failed and not result.timed_out and result.reason == "" and result.seconds >= 0.0
    assert result.fitness == 0.5 and result.inlier_rmse == pytest.approx(0.01)  # threshold FIT_THRESHOLD = 0.05
    tight = identity.register_result(src, ref, threshold=0.005)
    assert (tight.fitness, tight.inlier_rmse) == (0.0, 0.0)
    unfitted = identity.register_result(src, ref, threshold=None)
    assert unfitted.fitness is None and unfitted.inlier_rmse is None
    with pytest.raises(ConfigError, match="threshold must be a distance > 0"):
        identity.register_result(src, ref, threshold=-1.0)


def test_register_result_records_failures_and_raises_on_bad_input():
    src, ref = make_pair(euler_transform((0, 0, 0), (0.1, 0.0, 0.0)), 40, seed=0)
    raised = ToyRegistrator(raise_on=(40,)).register_result(src, ref)
    assert raised.failed and not raised.timed_out and raised.reason == "ValueError: toy failure on a 40-point cloud"
    assert np.array_equal(raised.transform, np.eye(4)) and raised.fitness is None
    garbage = ToyRegistrator(scale_on=(40,)).register_result(src, ref)
    assert garbage.failed and garbage.reason.startswith("non-rigid estimate: estimate's rotation is not orthonormal")
    slow = ToyRegistrator(sleep_s=0.05).register_result(src, ref, timeout_s=0.01)
    assert slow.failed and slow.timed_out and slow.reason.startswith("timed out: took")
    with pytest.raises(PointCloudError, match="src: needs at least 3 points"):
        ToyRegistrator().register_result(src[:2], ref)


@pytest.mark.parametrize("option, problem", [("nan_on", "contains NaN"), ("scale_on", "not orthonormal")])
def test_register_never_returns_an_estimate_that_is_no_rigid_transform(option, problem):
    """Found by generated pairs: FMR and PointNetLK-Revisited returned all-NaN transforms, exit 0, on a pair with one
    point 2e9 from the others; register_result flagged them, register handed them on."""
    src, ref = make_pair(euler_transform((0, 0, 0), (0.1, 0.0, 0.0)), 40, seed=0)
    toy = ToyRegistrator(**{option: (40,)})
    for call in (lambda: toy.register(src, ref), lambda: toy.register_batch(src[None], ref[None])):
        with pytest.raises(RegistrationError, match=rf"^toy: the estimate( of pair 0)? is no rigid transform \(.*{problem}"):
            call()
    assert np.isfinite(ToyRegistrator().register(src, ref)).all()


@pytest.mark.parametrize("points, kind", [  # converted silently before: True -> 1.0, 1+2j -> 1.0, "0.5" -> 0.5
    (np.ones((10, 3), dtype=bool), "bool"),
    (np.ones((10, 3), dtype=complex), "complex128"),
    (np.array([[1, 2, 3]] * 4 + [[1, "a", 2]], dtype=object), "object"),
    ([["0.1", "0.2", "0.3"]] * 5, "<U3"),
])
def test_register_accepts_real_numbers_only(points, kind):
    ref = np.random.default_rng(0).normal(size=(10, 3))
    with pytest.raises(PointCloudError, match=rf"^src: expected real numbers \(integers or floats\), got a {kind} array"):
        get_registrator("icp").register(points, ref)


def test_a_line_stored_in_float32_is_still_degenerate():
    """float32 rounding put the line's second singular value at ~1e-8 of the first, over float64's 1e-9 limit."""
    t = np.linspace(-1, 1, 50)[:, None]
    line = (t * np.array([[0.3, 0.7, 0.11]]) + np.array([[0.1, 0.2, 0.3]])).astype(np.float32)
    assert np.linalg.svd(line.astype(np.float64) - line.mean(0), compute_uv=False)[1] > 1e-9 * 1.0  # what passed
    ref = np.random.default_rng(0).normal(size=(50, 3))
    for cloud in (line, torch.from_numpy(line)):
        with pytest.raises(PointCloudError, match="^src: degenerate cloud, its 50 points are all on one line"):
            get_registrator("icp").register(cloud, ref)
    get_registrator("icp").register(line.astype(np.float64) + np.random.default_rng(1).normal(size=(50, 3)) * 1e-3, ref)


def _kabsch(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The exact rigid transform of a noise-free pair (ref = R·src + t)."""
    cs, cr = src.mean(axis=0), ref.mean(axis=0)
    u, _, vt = np.linalg.svd((src - cs).T @ (ref - cr))
    rot = vt.T @ np.diag([1.0, 1.0, np.linalg.det(vt.T @ u.T)]) @ u.T
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rot, cr - rot @ cs
    return transform


def test_condition_is_one_step_and_its_undo_maps_the_estimate_back():
    rng = np.random.default_rng(3)
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("zyx", [30, -20, 10], degrees=True).as_matrix()
    truth[:3, 3] = [5.0, -2.0, 1.0]
    src = 250.0 * rng.normal(size=(60, 3)) + 1e4  # far outside the working frame
    ref = src @ truth[:3, :3].T + truth[:3, 3]
    cond_src, cond_ref, undo = condition(src, ref)
    assert max(np.abs(cond_src).max(), np.abs(cond_ref).max()) < 10  # moved into the working frame
    np.testing.assert_allclose(undo(_kabsch(cond_src, cond_ref)), truth, atol=1e-8)
    inside_src, inside_ref = src / 1e4 - 1.0, ref / 1e4 - 1.0
    same_src, same_ref, same_undo = condition(inside_src, inside_ref, frame=None, budget=None)
    assert same_src is inside_src and same_ref is inside_ref and same_undo(truth) is truth
