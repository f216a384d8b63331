"""Batched torch geometry against SciPy's Rotation on random inputs; its NumPy counterparts against it."""

import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from src.geometry import numpy_rigid
from src.geometry import (
    euler_to_matrix,
    matrix_to_euler,
    matrix_to_quat,
    quat_multiply,
    quat_conjugate,
    quat_to_matrix,
    rotation_angle,
    se3_apply,
    se3_compose,
    se3_from_rt,
    se3_inverse,
)

RNG = np.random.default_rng(0)
ROTS = Rotation.random(256, random_state=1)


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(x, dtype=torch.float64)


def _scipy_quat_wxyz(rot: Rotation) -> np.ndarray:
    xyzw = rot.as_quat()
    q = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    return np.where(q[:, :1] < 0, -q, q)


def test_quat_to_matrix_matches_scipy():
    q = _scipy_quat_wxyz(ROTS)
    np.testing.assert_allclose(quat_to_matrix(_t(q)).numpy(), ROTS.as_matrix(), atol=1e-12)


def test_matrix_to_quat_matches_scipy_including_near_pi():
    near_pi = Rotation.from_rotvec(RNG.normal(size=(64, 3)) * 0 + np.pi * np.eye(3)[RNG.integers(0, 3, 64)])
    rots = Rotation.concatenate([ROTS, near_pi])
    np.testing.assert_allclose(
        torch.abs(matrix_to_quat(_t(rots.as_matrix()))).numpy(), np.abs(_scipy_quat_wxyz(rots)), atol=1e-9
    )
    q = matrix_to_quat(_t(ROTS.as_matrix()))
    np.testing.assert_allclose(q.numpy(), _scipy_quat_wxyz(ROTS), atol=1e-9)


def test_quat_multiply_is_composition():
    a, b = Rotation.random(50, random_state=2), Rotation.random(50, random_state=3)
    qa, qb = _t(_scipy_quat_wxyz(a)), _t(_scipy_quat_wxyz(b))
    np.testing.assert_allclose(quat_to_matrix(quat_multiply(qa, qb)).numpy(), (a * b).as_matrix(), atol=1e-12)
    identity = quat_multiply(qa, quat_conjugate(qa))
    np.testing.assert_allclose(identity.numpy(), np.tile([1.0, 0, 0, 0], (50, 1)), atol=1e-12)


@pytest.mark.parametrize("seq", ["xyz", "zyx"])
def test_euler_round_trip_matches_scipy(seq):
    angles = RNG.uniform(-80, 80, size=(200, 3))
    expected = Rotation.from_euler(seq, angles, degrees=True).as_matrix()
    rot = euler_to_matrix(_t(angles), seq, degrees=True)
    np.testing.assert_allclose(rot.numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(
        matrix_to_euler(_t(ROTS.as_matrix()), seq, degrees=True).numpy(), ROTS.as_euler(seq, degrees=True), atol=1e-8
    )


def test_unknown_euler_sequence_is_rejected():
    with pytest.raises(ValueError, match="Euler sequence"):
        matrix_to_euler(torch.eye(3), "xzy")


def test_se3_inverse_compose_apply():
    rot = _t(ROTS.as_matrix()[:20])
    trans = _t(RNG.normal(size=(20, 3)))
    transform = se3_from_rt(rot, trans)
    points = _t(RNG.normal(size=(20, 30, 3)))
    moved = se3_apply(transform, points)
    expected = np.einsum("bij,bnj->bni", rot.numpy(), points.numpy()) + trans.numpy()[:, None]
    np.testing.assert_allclose(moved.numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(se3_apply(se3_inverse(transform), moved).numpy(), points.numpy(), atol=1e-12)
    eye = se3_compose(se3_inverse(transform), transform)
    np.testing.assert_allclose(eye.numpy(), np.tile(np.eye(4), (20, 1, 1)), atol=1e-12)


def test_rotation_angle_matches_scipy_magnitude():
    np.testing.assert_allclose(
        rotation_angle(_t(ROTS.as_matrix())).numpy(), np.degrees(ROTS.magnitude()), atol=1e-6
    )


@pytest.mark.parametrize("seq", ["xyz", "zyx"])
def test_numpy_helpers_match_the_torch_geometry(seq):
    angles, trans = RNG.uniform(-80, 80, size=3), RNG.normal(size=3)
    transform = numpy_rigid.euler_transform(angles, trans, seq)
    batched = se3_from_rt(euler_to_matrix(_t(angles), seq, degrees=True), _t(trans))
    np.testing.assert_allclose(transform, batched.numpy(), atol=1e-12)
    points = RNG.normal(size=(30, 3))
    np.testing.assert_allclose(numpy_rigid.apply_transform(transform, points), se3_apply(batched, _t(points)).numpy(),
                               atol=1e-12)
    np.testing.assert_allclose(numpy_rigid.inverse_transform(transform), se3_inverse(batched).numpy(), atol=1e-12)
    np.testing.assert_allclose(numpy_rigid.inverse_transform(transform) @ transform, np.eye(4), atol=1e-12)
    assert numpy_rigid.rotation_angle(transform[:3, :3]) == pytest.approx(rotation_angle(batched[:3, :3]).item())
    assert numpy_rigid.rotation_angle(transform[:3, :3], degrees=False) == pytest.approx(
        np.radians(rotation_angle(batched[:3, :3]).item()))


def test_the_numpy_helpers_and_cloud_checks_import_no_torch():
    code = ("import sys, src.geometry.numpy_rigid, src.geometry.clouds, src.data.transforms, baselines.base; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    subprocess.run([sys.executable, "-c", code], check=True)
