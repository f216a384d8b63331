"""run_pairs: order, parallel workers, timeouts, crashes, exceptions and bad estimates."""

from __future__ import annotations

import numpy as np
import pytest

from baselines import RegistrationResult, get_registrator, run_pairs
from baselines.testing import ToyRegistrator, euler_transform, l_shape_surface
from src.utils.errors import CheckpointError


def _pairs(sizes):
    """Pairs whose true answer is a translation by (index, 0, 0)."""
    pairs = []
    for i, n in enumerate(sizes):
        src = l_shape_surface(n, seed=i)
        pairs.append((src, src + np.array([float(i), 0.0, 0.0])))
    return pairs


def _check_ok(result: RegistrationResult, index: int):
    assert not result.failed and not result.timed_out and result.reason == ""
    np.testing.assert_allclose(result.transform[:3, 3], [index, 0.0, 0.0], atol=1e-9)
    assert result.seconds >= 0.0 and result.fitness == 1.0 and result.inlier_rmse < 1e-9  # the toy is exact


def test_results_keep_pair_order_with_parallel_workers():
    sizes = [20 + 3 * i for i in range(12)]
    # later pairs are faster than earlier ones would be, so completion order differs
    results = run_pairs(ToyRegistrator(sleep_s=0.02), _pairs(sizes), workers=2, timeout_s=30, progress=False)
    assert len(results) == len(sizes)
    for i, result in enumerate(results):
        _check_ok(result, i)


def test_timeout_crash_exception_and_bad_estimates_are_recorded_not_dropped():
    sizes = [30, 31, 32, 33, 34, 35, 36, 37, 38, 39, 40]
    expected = {
        31: "timed out after 1.5 s",
        33: "worker process exited with code 3",
        35: "ValueError: toy failure on a 35-point cloud",
        37: "non-rigid estimate: estimate contains NaN",
        39: "non-rigid estimate: estimate's rotation is not orthonormal",
    }
    reg = ToyRegistrator(hang_on=(31,), crash_on=(33,), raise_on=(35,), nan_on=(37,), scale_on=(39,))
    results = run_pairs(reg, _pairs(sizes), workers=2, timeout_s=1.5, progress=False)
    assert len(results) == len(sizes)
    for i, (result, n) in enumerate(zip(results, sizes)):
        if n in expected:
            assert result.failed and result.timed_out == (n == 31) and result.fitness is None, result
            assert result.reason.startswith(expected[n]), result.reason
            assert "\n" not in result.reason
            np.testing.assert_array_equal(result.transform, np.eye(4))
        else:
            _check_ok(result, i)  # pairs after a killed worker still run
    assert 1.4 < results[1].seconds < 10


@pytest.mark.parametrize("option, reason", [("nan_on", "NaN"), ("scale_on", "not orthonormal")])
def test_non_rigid_estimates_fail_in_serial_mode(option, reason):
    pairs = _pairs([10, 11, 12])
    results = run_pairs(ToyRegistrator(**{option: (11,)}), pairs, workers=0, timeout_s=30, progress=False)
    _check_ok(results[0], 0)
    _check_ok(results[2], 2)
    assert results[1].failed and "non-rigid estimate" in results[1].reason and reason in results[1].reason
    np.testing.assert_array_equal(results[1].transform, np.eye(4))


def test_bad_input_pair_is_a_failure_not_an_abort():
    pairs = _pairs([10, 11])
    pairs.insert(1, (np.zeros((2, 3)), np.zeros((5, 3))))
    results = run_pairs(ToyRegistrator(), pairs, workers=1, timeout_s=30, progress=False)
    assert [r.failed for r in results] == [False, True, False]
    assert "PointCloudError" in results[1].reason and "at least 3 points" in results[1].reason


def test_serial_mode_flags_slow_pairs_and_exceptions():
    pairs = _pairs([10, 11, 12])
    results = run_pairs(ToyRegistrator(raise_on=(12,)), pairs, workers=0, progress=False)
    assert [r.failed for r in results] == [False, False, True]
    assert results[2].reason.startswith("ValueError: toy failure")
    slow = run_pairs(ToyRegistrator(sleep_s=0.05), pairs[:1], workers=0, timeout_s=0.01, progress=False)
    assert slow[0].failed and slow[0].timed_out and "timed out" in slow[0].reason


def test_empty_input_and_argument_checks():
    assert run_pairs(ToyRegistrator(), [], workers=2, timeout_s=1, progress=False) == []
    with pytest.raises(ValueError):
        run_pairs(ToyRegistrator(), _pairs([10]), workers=-1, progress=False)
    with pytest.raises(ValueError):
        run_pairs(ToyRegistrator(), _pairs([10]), workers=1, timeout_s=0, progress=False)
    with pytest.raises(TypeError):
        run_pairs(object(), _pairs([10]), workers=1, progress=False)


def test_worker_setup_user_errors_reach_the_caller():
    reg = ToyRegistrator(setup_error="checkpoint runs/x.ckpt not found")
    with pytest.raises(CheckpointError, match="runs/x.ckpt"):
        run_pairs(reg, _pairs([10, 11]), workers=1, timeout_s=30, progress=False)


def test_unpicklable_registrator_is_explained():
    reg = ToyRegistrator()
    reg.handle = lambda: None  # a native handle stand-in: lambdas do not pickle
    with pytest.raises(TypeError, match="picklable"):
        run_pairs(reg, _pairs([10]), workers=1, progress=False)
    assert not run_pairs(reg, _pairs([10]), workers=0, progress=False)[0].failed


def test_open3d_method_in_worker_processes():
    truth = euler_transform((5.0, -4.0, 3.0), (0.05, 0.02, -0.03))
    src = l_shape_surface(300, seed=0)
    ref = src @ truth[:3, :3].T + truth[:3, 3]
    results = run_pairs(get_registrator("icp"), [(src, ref)] * 3, workers=2, timeout_s=60, progress=True)
    for result in results:
        assert not result.failed
        np.testing.assert_allclose(result.transform, truth, atol=1e-4)


def test_an_idle_worker_past_its_last_deadline_does_not_stop_the_run():
    """Worker A finishes its only pair (1.5 s) and idles; B takes a second pair at 1.0 s that ends at
    4.5 s, within its own 4 s timeout but after A's last deadline (4.0 s): the run must go on."""
    sizes = [30, 31, 32]
    slow = ((30, 1.5), (31, 1.0), (32, 3.5))
    results = run_pairs(ToyRegistrator(slow_on=slow), _pairs(sizes), workers=2, timeout_s=4.0, progress=False)
    for i, result in enumerate(results):
        _check_ok(result, i)
