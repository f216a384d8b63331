"""Classical baselines recover known transforms on a small asymmetric L-shaped cloud."""

from __future__ import annotations

import numpy as np
import pytest

from baselines import get_registrator, run_pairs, transform_problem
from baselines.conditioning import POINT_BUDGET
from baselines.classical import goicp as goicp_module
from baselines.classical.fgr import FGR
from baselines.classical.symmetric_icp import symmetric_step
from baselines.testing import euler_transform, make_pair, rotation_error_deg, translation_error
from src.utils.errors import ConfigError, PointCloudError, RegistrationError
from src.geometry.numpy_rigid import apply_transform

SMALL = euler_transform((10.0, -8.0, 6.0), (0.1, -0.05, 0.08))  # ~10° about a tilted axis
LARGE = euler_transform((40.0, -35.0, 30.0), (0.3, -0.2, 0.25))  # ~60° in total



def _errors(estimate, truth):
    assert transform_problem(estimate) is None, transform_problem(estimate)
    return rotation_error_deg(estimate, truth), translation_error(estimate, truth)


@pytest.mark.parametrize("method", ["icp", "symmetric_icp"])
def test_local_methods_recover_a_small_transform(method):
    reg = get_registrator(method)
    rot, trans = _errors(reg.register(*make_pair(SMALL, 600, seed=1)), SMALL)
    assert rot < 0.1 and trans < 1e-3  # same points: exact up to convergence tolerance
    rot, trans = _errors(reg.register(*make_pair(SMALL, 600, seed=2, twice_sampled=True)), SMALL)
    assert rot < 3.0 and trans < 0.05  # independent samples of the surface


def _point_rmse(estimate, truth, points):
    diff = apply_transform(estimate, points) - apply_transform(truth, points)
    return float(np.sqrt(np.mean(np.sum(diff**2, axis=1))))


def test_symmetric_icp_converges_and_is_at_least_as_good_as_icp():
    icp = get_registrator("icp")
    sym = get_registrator("symmetric_icp")
    for seed in (1, 2):  # clean, small angle, independently sampled clouds
        src, ref = make_pair(SMALL, 600, seed=seed, twice_sampled=True)
        icp_est, sym_est = icp.register(src, ref), sym.register(src, ref)
        icp_rot, _ = _errors(icp_est, SMALL)
        sym_rot, _ = _errors(sym_est, SMALL)
        assert sym_rot <= icp_rot
        assert _point_rmse(sym_est, SMALL, src) <= _point_rmse(icp_est, SMALL, src) + 0.005
        # converged: more iterations change nothing ...
        longer = get_registrator("symmetric_icp", max_iterations=200).register(src, ref)
        np.testing.assert_allclose(longer, sym_est, atol=1e-6)
        # ... and it gets there fast: 5 iterations suffice, where point-to-point ICP is far off
        sym5 = get_registrator("symmetric_icp", max_iterations=5).register(src, ref)
        icp5 = get_registrator("icp", max_iterations=5).register(src, ref)
        assert _errors(sym5, SMALL)[0] < sym_rot + 0.1 < _errors(icp5, SMALL)[0]


def test_symmetric_step_is_exact_in_rotation_for_exact_correspondences():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(200, 3))
    n_p = rng.normal(size=(200, 3))
    n_p /= np.linalg.norm(n_p, axis=1, keepdims=True)
    truth = euler_transform((12.0, -7.0, 20.0), (0.2, 0.1, -0.3))
    q = p @ truth[:3, :3].T + truth[:3, 3]
    n_q = n_p @ truth[:3, :3].T
    step = symmetric_step(p, q, n_p + n_q)
    rot, trans = _errors(step, truth)
    assert rot < 1e-6 and trans < 0.01


def test_icp_needs_a_large_enough_correspondence_distance():
    # with a tiny threshold no pair is within reach: ICP found nothing, and says so instead of returning the identity
    reg = get_registrator("icp", max_correspondence_distance=1e-4)
    with pytest.raises(RegistrationError, match=r"^icp: found no transform: ICP ended with 0 correspondences"):
        reg.register(*make_pair(SMALL, 300, seed=1))


@pytest.mark.parametrize("noise", [0.0, 0.005])
def test_fgr_recovers_a_large_transform(noise):
    reg = get_registrator("fgr")
    rot, trans = _errors(reg.register(*make_pair(LARGE, 600, seed=0, noise=noise)), LARGE)
    assert rot < 2.0 and trans < 0.02


def test_fgr_is_deterministic_with_a_seed():
    reg = get_registrator("fgr", seed=3)
    pair = make_pair(LARGE, 400, seed=6, noise=0.01)
    np.testing.assert_array_equal(reg.register(*pair), reg.register(*pair))


@pytest.mark.goicp
def test_goicp_recovers_a_large_transform():
    # Branch-and-bound time depends on the data (deterministically): these two pairs take
    # ~1-3 s each; run them through the runner so a regression fails instead of hanging.
    pairs = [make_pair(LARGE, 500, seed=0, twice_sampled=ts) for ts in (False, True)]
    results = run_pairs(get_registrator("goicp"), pairs, workers=2, timeout_s=120, progress=False)
    for result, limit in zip(results, (0.1, 3.0)):
        assert not result.failed, result.reason
        rot, trans = _errors(result.transform, LARGE)
        assert rot < limit and trans < 0.05


@pytest.mark.goicp
def test_goicp_keeps_stdout_clean(capfd):
    get_registrator("goicp", dt_size=50).register(*make_pair(SMALL, 200, seed=1))
    out, _ = capfd.readouterr()
    assert out == ""


def test_goicp_without_the_extension_names_the_install_script(monkeypatch):
    monkeypatch.setattr(goicp_module, "goicp_available", lambda: False)
    with pytest.raises(ConfigError, match="install_goicp.sh"):
        get_registrator("goicp")


def test_goicp_config_validation():
    with pytest.raises(ConfigError, match="trim_fraction"):
        goicp_module.GoICPConfig(trim_fraction=1.0)
    with pytest.raises(ConfigError, match="rotation_half_width"):
        goicp_module.GoICPConfig(rotation_half_width=4.0)


def test_goicp_normalisation_round_trip():
    src, ref = make_pair(LARGE, 100, seed=0)
    src_n, ref_n, c_src, c_ref, scale = goicp_module.normalise_pair(src, ref)
    assert max(np.abs(src_n).max(), np.abs(ref_n).max()) == pytest.approx(1.0)
    np.testing.assert_allclose(src_n * scale + c_src, src)
    np.testing.assert_allclose(ref_n * scale + c_ref, ref)


@pytest.mark.parametrize("scale, offset", [(1e9, 0.0), (1e-6, 0.0), (1.0, 1e9)])
@pytest.mark.parametrize("method, truth, limit", [("icp", SMALL, 0.1), ("symmetric_icp", SMALL, 0.1), ("fgr", LARGE, 2.0)])
def test_methods_work_on_unnormalised_input(method, truth, limit, scale, offset):
    """Far from the unit-sphere frame their options assume (x1e9 gave ICP the identity, FGR a wrong
    pose), every method registers in the working frame and maps the estimate back."""
    src, ref = make_pair(truth, 600, seed=1)
    shift = np.array([offset, -offset, offset])
    estimate = get_registrator(method).register(src * scale + shift, ref * scale + shift)
    rot = estimate[:3, :3]
    in_object_units = (estimate[:3, 3] - shift + rot @ shift) / scale  # x' = scale x + shift undone
    assert rotation_error_deg(estimate, truth) < limit
    assert np.linalg.norm(in_object_units - truth[:3, 3]) < 0.02


@pytest.mark.parametrize("method", ["icp", "fgr", "symmetric_icp", pytest.param("goicp", marks=pytest.mark.goicp)])
def test_degenerate_clouds_are_refused_by_every_method(method):
    with pytest.raises(PointCloudError, match="src: degenerate cloud, its 3 points are all the same point"):
        get_registrator(method).register(np.ones((3, 3)), np.ones((3, 3)))  # FGR: Open3D RuntimeError before


def test_fgr_registers_large_clouds_within_the_point_budget(monkeypatch):
    """FGR on 200k points had not finished after 300 s; a call now sees at most POINT_BUDGET points."""
    seen = []
    original = FGR._register
    monkeypatch.setattr(FGR, "_register", lambda self, src, ref: seen.append((len(src), len(ref))) or original(self, src, ref))
    src, ref = make_pair(LARGE, 3 * POINT_BUDGET, seed=0)
    rot, trans = _errors(get_registrator("fgr").register(src, ref), LARGE)
    assert max(seen[0]) <= POINT_BUDGET and rot < 2.0 and trans < 0.02
